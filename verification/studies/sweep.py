"""Sweep: every model at several time steps against the reference; error against step time and the
Pareto front. Under ``mpirun -n P`` the runs are spread over the ranks (the reference is solved once,
collectively, first) and rank 0 gathers and prints the table.
"""

from __future__ import annotations

import math

from realtime.errors import did_you_mean
from reference.errors import ReferenceSolveError
from verification.engines import offered, plug_in, spec_of
from verification.metrics import METRICS
from verification.progress import Bar
from verification.runs.reference import P1_OWN_MESH, REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row
from verification.runs.store import compare_or_unsettled
from verification.scene import Scene, SceneError
from verification.studies.frame import true_range
from verification.studies.stable_step import largest_stable_fraction

#: Time steps a sweep tries by default on a dynamic scene, as fractions of each model's critical step.
DEFAULT_FRACTIONS = (0.25, 0.5, 0.9)
#: ... and on a static scene: there every stable step settles to the same answer, and the time to it
#: grows as 1 / dt, so a smaller step only adds a row as accurate as 0.9's and slower to settle (a quarter
#: step four times, half a step twice: together two thirds of a static sweep's settling). 0.9 is stable
#: by construction (the critical step is the smaller of rest's and equilibrium's), and the largest
#: stable step is run beside it; others only when asked for (``fractions``).
STATIC_FRACTIONS = (0.9,)


def default_fractions(scene: Scene) -> tuple[float, ...]:
    """The fractions of the critical step a sweep of ``scene`` runs unless told otherwise."""
    return DEFAULT_FRACTIONS if scene.time.mode == "dynamic" else STATIC_FRACTIONS


def pareto_front(points: list[tuple[float, float]]) -> list[int]:
    """Indices of the points no other point dominates, for two costs to minimise (x, y).

    A point dominates another if it is no worse in both and better in one. Returned sorted by x.
    Sorting by x then y and keeping each point whose y is below every y seen so far is exact: a later
    point has x >= every earlier one, so it survives only by a strictly lower y.
    """
    order = sorted(range(len(points)), key=lambda i: (points[i][0], points[i][1]))
    front, best = [], math.inf
    for i in order:
        if points[i][1] < best:
            front.append(i)
            best = points[i][1]
    return front


def sweep_plan(models, fractions, dts, integrator: str) -> list[dict]:
    """The runs of a sweep: each model at each fraction (or each dt in seconds); quasi-static once."""
    plan = []
    for m in models:
        if spec_of(m).quasi_static:
            plan.append({"model": m, "integrator": "quasi-static", "dt": None, "fraction": None})
            continue
        if plug_in(m):  # its steps are its own: one run
            plan.append({"model": m, "integrator": integrator, "dt": None, "fraction": None})
            continue
        for f in fractions or []:
            plan.append({"model": m, "integrator": integrator, "dt": None, "fraction": float(f)})
        for dt in dts or []:
            plan.append({"model": m, "integrator": integrator, "dt": float(dt), "fraction": None})
    return plan


def _run_plan(
    scene: Scene,
    plan: list[dict],
    ref,
    ref_opts: dict,
    integrator: str,
    use_cache: bool,
    float32: bool,
    rank,
    size,
    screen=None,
):
    """This rank's share of the plan's runs (every size-th from its rank), each through the run cache,
    with its index in the plan; the largest stable step found first where the plan asks for it.
    ``screen(scene, model, integrator, dt, fraction)``: a row that decides a run without making it, or
    None to make it. ``ref``: the reference, solved with ``ref_opts`` (the run cache's key)."""
    progress = Bar(len(plan), f"sweep {scene.name}") if rank == 0 else None
    rows = []
    for k, item in enumerate(plan):
        if k % size != rank:
            continue
        fraction = item["fraction"]
        largest = fraction == "largest-stable"
        if largest:
            fraction = largest_stable_fraction(scene, item["model"], integrator, use_cache=use_cache)["stable"]
        stepper = item["integrator"] if item["integrator"] != "quasi-static" else integrator
        row = screen and screen(scene, item["model"], stepper, item["dt"], fraction)
        row = row or compare_or_unsettled(
            scene, item["model"], stepper, item["dt"], fraction, reference=ref, ref_opts=ref_opts,
            use_cache=use_cache, float32=float32,
        )  # fmt: skip
        rows.append(row.replace(plan_index=k, **({"largest_stable": True} if largest else {})))
        if progress:
            progress.step(f"{item['model']} {fraction}")
    return rows


def sweep(
    scene: Scene,
    models=None,
    fractions=None,
    dts=None,
    integrator: str = "symplectic-euler",
    largest_stable: bool = True,
    use_cache: bool = True,
    comm=None,
    float32: bool = False,
    screen=None,
    ref_opts: dict | None = None,
) -> dict:
    """Models x time steps -> rows of metrics and the Pareto front of error (rel_l2) against step_us.

    Default: every model (the plug-ins' too: each runs once, at its own step) at
    ``default_fractions(scene)`` of its critical step, plus (``largest_stable``) each
    explicit model at the largest stable fraction that ``largest_stable_fraction`` finds. ``float32``:
    each row of a model that runs in float32 also carries its float32 twin (``runs.compare.float32_twin``), whose
    distance from the float64 run stands beside the model's error. ``screen``: see ``_run_plan`` (the
    advisor's, which leaves out the runs too slow for its rate). ``ref_opts``: the reference's options
    (default REFERENCE_DEFAULTS; the advisor's sharper truth, ``truth.sharp_reference``).
    """
    models = list(models or offered())
    if fractions is None and dts is None:
        fractions = list(default_fractions(scene))
    unknown = [m for m in models if m not in offered()]
    if unknown:
        hint = did_you_mean(unknown[0], offered())
        raise SceneError(f"model = {unknown[0]!r}{hint}: must be one of {', '.join(offered())}")
    rank, size = (comm.rank, comm.size) if comm is not None else (0, 1)
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    ref = reference_result(scene, **ref_opts)  # collective under MPI; cached afterwards
    # the error budget's P1 solution too, before the runs are spread over the ranks: a solve is collective
    try:
        reference_result(scene, **P1_OWN_MESH)
    except ReferenceSolveError:
        pass  # each row's budget then says why it has no mesh part
    if comm is not None and size > 1:
        comm.Barrier()  # rank 0 has written both to the cache before any rank looks for them there
    plan = sweep_plan(models, fractions, dts, integrator)
    if largest_stable:
        for m in models:
            if not spec_of(m).quasi_static and integrator != "implicit-euler" and not plug_in(m):
                plan.append({"model": m, "integrator": integrator, "dt": None, "fraction": "largest-stable"})
    rows = _run_plan(scene, plan, ref, ref_opts, integrator, use_cache, float32, rank, size, screen)
    if comm is not None and size > 1:
        gathered = comm.gather(rows, root=0)
        if rank != 0:
            return {}
        rows = [r for part in gathered for r in part]
    rows.sort(key=lambda r: r.plan_index)
    ok = [i for i, r in enumerate(rows) if r.ok and r.step_us is not None]  # timed: a plug-in may report none
    front = [ok[i] for i in pareto_front([(rows[i].step_us, rows[i].rel_l2) for i in ok])]
    rows = [r.replace(pareto=i in front) for i, r in enumerate(rows)]
    return {
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "integrator": integrator,
        "reference": {
            k: ref.meta.get(k) for k in ("law", "degree", "refine", "ref_err_estimate", "min_det_F", "cache_key")
        },
        "rows": rows,
        "pareto": [rows[i].model + (f"@{rows[i].dt:.3g}s" if rows[i].dt else "") for i in front],
        "computed": sum(not r.cached for r in rows),
        "cached": sum(bool(r.cached) for r in rows),
    }


def sweep_csv(result: dict) -> str:
    cols = [
        "model",
        "integrator",
        "status",
        "fraction",
        "dt",
        "dt_crit",
        *METRICS,
        "ref_err_estimate",
        "step_us",
        "step_us_min",
        "step_us_max",
        "rate_hz",
        "pareto",
    ]
    parts = ("mesh", "model", "time")
    single = ("rel_l2_vs_float64", "rel_l2", "step_us")
    lines = [",".join(cols + [f"budget_{p}" for p in parts] + [f"float32_{c}" for c in single] + ["unrepresented"])]
    for r in result["rows"]:
        budget = r.error_budget or {}
        twin = r.float32 or {}
        values = [getattr(r, c) for c in cols] + [budget.get(p) for p in parts] + [twin.get(c) for c in single]
        values.append(" and ".join(r.unrepresented or []).replace(",", ";") or None)
        lines.append(",".join("" if v is None else str(v) for v in values))
    return "\n".join(lines) + "\n"


def _float32_cells(r: Row) -> str:
    """A row's float32 columns: its twin's distance from the float64 run and its step time; '-' where
    the row has no twin (that model or integrator runs in float64 only)."""
    twin = r.float32
    if not twin:
        return f" {'-':>10} {'-':>9}"
    return f" {twin['rel_l2_vs_float64']:>10.2g} {twin['step_us']:>9.1f}"


def format_sweep(result: dict) -> str:
    est = result["reference"].get("ref_err_estimate")
    twins = any(r.float32 for r in result["rows"])
    out = [
        f"sweep {result['scene']}: reference {result['reference']['law']} P{result['reference']['degree']}, "
        f"own error estimate {est:.3g}"
        if est is not None
        else f"sweep {result['scene']}"
    ]
    head = f"{'model':<16} {'dt (s)':>10} {'dt/crit':>8} {'rel_l2':>10} {'reaction':>9} {'step us':>9} {'Hz':>9}"
    out.append(head + (f" {'f32 vs f64':>10} {'f32 us':>9}" if twins else "") + "  ")
    for r in result["rows"]:
        if r.status == "diverged":
            out.append(f"{r.model:<16} {r.dt:>10.3g} {r.dt / r.dt_crit:>8.2f} diverged at step {r.step}")
            continue
        if r.status != "ok":  # not applicable, not settled, over budget: no step to show, the reason instead
            out.append(f"{r.model:<16} {'-':>10} {'-':>8} {r.status}: {r.message}")
            continue
        ratio = "-" if r.dt is None or not r.dt_crit else f"{r.dt / r.dt_crit:.2f}"
        dt = "-" if r.dt is None else f"{r.dt:.3g}"
        reaction = "-" if r.reaction_rel_err is None else f"{r.reaction_rel_err:.3g}"
        flag = " pareto" if r.pareto else ""
        span = true_range(r.rel_l2, r.ref_err_estimate)
        flag += f" ({span})" if span else ""
        flag += "".join(f" (without {term})" for term in r.unrepresented or [])
        flag += re_adapted(r)
        out.append(
            f"{r.model:<16} {dt:>10} {ratio:>8} {r.rel_l2:>10.4g} {reaction:>9} {fmt(r.step_us, '.1f'):>9} "
            f"{fmt(r.rate_hz, '.0f'):>9}{_float32_cells(r) if twins else ''} {flag}"
        )
    out.append(f"Pareto front (error against step time): {', '.join(result['pareto'])}")
    out.append(f"{result['computed']} runs computed, {result['cached']} from the cache")
    return "\n".join(out)


def re_adapted(r: Row) -> str:
    """What a re-adapting run's row adds to a table (its mesh over time: its dt is its last mesh's,
    against the first mesh's critical step), or ""."""
    a = r.adaptation
    return "" if not a else f" (re-adapted: {a['tets_first']} to {a['tets_max']} tetrahedra, dt of the last mesh)"


def fmt(v, spec: str) -> str:
    """A number formatted, "-" for None (a plug-in that reports no step time)."""
    return "-" if v is None else format(v, spec)
