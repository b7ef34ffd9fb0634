"""Studies over many runs: sweep (error against speed, Pareto front), converge, stability, advise.

Every run a study makes is cached as one JSON file under ``$TISSUEBENCH_CACHE/runs``, keyed by the
scene's hash, the model, the integrator and the time step (as a fraction of the critical one, or in
seconds), so a study killed half-way and started again recomputes only what it had not finished.
Under ``mpirun -n P`` the runs of a sweep are spread over the ranks (the reference is solved once,
collectively, first) and rank 0 gathers and prints the table.
"""

from __future__ import annotations

import dataclasses
import json
import math
import sys
import time

import numpy as np

from realtime import MODELS
from realtime.models import QUASI_STATIC

from .results import atomic_write_text
from .runner import (
    REFERENCE_DEFAULTS,
    RUN_CODE,
    cache_dir,
    code_digest,
    compare,
    digest,
    machine_id,
    reference_result,
)
from .scene import Scene, SceneError

#: Time steps a sweep tries by default, as fractions of each model's critical step.
DEFAULT_FRACTIONS = (0.25, 0.5, 0.9)
#: Bisection of the largest stable step: the span searched and the steps each trial runs.
STABLE_SEARCH = (0.5, 3.0)
STABLE_STEPS = 2000


class Progress:
    """A one-line progress bar on a terminal (stderr); silent when stderr is not a TTY (CI, pipes)."""

    def __init__(self, total: int, label: str):
        self.total, self.label, self.done, self.t0 = total, label, 0, time.perf_counter()
        self.tty = sys.stderr.isatty()

    def step(self, what: str) -> None:
        self.done += 1
        if not self.tty:
            return
        width = 30
        fill = int(width * self.done / max(self.total, 1))
        elapsed = time.perf_counter() - self.t0
        sys.stderr.write(
            f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] {self.done}/{self.total} "
            f"{elapsed:5.0f}s {what[:40]:<40}"
        )
        if self.done >= self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


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


def _run_key(
    scene: Scene, model: str, integrator: str, dt: float | None, fraction: float | None, ref_opts, budget: bool = True
) -> str:
    return digest(
        {
            "code": code_digest(RUN_CODE),
            "machine": machine_id(),  # a row holds timings: another machine's are not this one's
            "scene": scene.sha256(),
            "model": model,
            "integrator": integrator,
            "dt": dt,
            "fraction": fraction,
            "reference": ref_opts,
            "budget": budget,
        }
    )


def cached_compare(
    scene: Scene,
    model: str,
    integrator: str = "symplectic-euler",
    dt: float | None = None,
    fraction: float | None = None,
    reference=None,
    ref_opts=None,
    use_cache: bool = True,
    max_steps: int = 2_000_000,
    budget: bool = True,
) -> dict:
    """``runner.compare`` through the run cache. The row says whether it came from the cache."""
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    path = (
        cache_dir() / "runs" / f"{scene.name}-{_run_key(scene, model, integrator, dt, fraction, ref_opts, budget)}.json"
    )
    if use_cache and path.exists():
        row = json.loads(path.read_text())
        row["cached"] = True
        return row
    ref = reference if reference is not None else reference_result(scene, **ref_opts)
    row = compare(
        scene,
        model,
        dt=dt,
        dt_fraction=fraction,
        integrator=integrator,
        reference=ref,
        max_steps=max_steps,
        budget=budget,
    )
    row["fraction"] = fraction
    if use_cache:
        atomic_write_text(path, json.dumps(row, default=_jsonable))
    row["cached"] = False
    return row


def _jsonable(x):
    if isinstance(x, np.generic):
        return x.item()
    return str(x)


def sweep_plan(models, fractions, dts, integrator: str) -> list[dict]:
    """The runs of a sweep: each model at each fraction (or each dt in seconds); quasi-static once."""
    plan = []
    for m in models:
        if m in QUASI_STATIC:
            plan.append({"model": m, "integrator": "quasi-static", "dt": None, "fraction": None})
            continue
        for f in fractions or []:
            plan.append({"model": m, "integrator": integrator, "dt": None, "fraction": float(f)})
        for dt in dts or []:
            plan.append({"model": m, "integrator": integrator, "dt": float(dt), "fraction": None})
    return plan


def sweep(
    scene: Scene,
    models=None,
    fractions=None,
    dts=None,
    integrator: str = "symplectic-euler",
    largest_stable: bool = True,
    use_cache: bool = True,
    comm=None,
) -> dict:
    """Models x time steps -> rows of metrics and the Pareto front of error (rel_l2) against step_us.

    Default: every model at DEFAULT_FRACTIONS of its critical step, plus (``largest_stable``) each
    explicit model at the largest stable fraction that ``largest_stable_fraction`` finds.
    """
    models = list(models or MODELS)
    if fractions is None and dts is None:
        fractions = list(DEFAULT_FRACTIONS)
    unknown = [m for m in models if m not in MODELS]
    if unknown:
        raise SceneError(f"model = {unknown[0]!r}: must be one of {', '.join(MODELS)}")
    rank, size = (comm.rank, comm.size) if comm is not None else (0, 1)
    ref = reference_result(scene, **REFERENCE_DEFAULTS)  # collective under MPI; cached afterwards
    plan = sweep_plan(models, fractions, dts, integrator)
    if largest_stable:
        for m in models:
            if m not in QUASI_STATIC and integrator != "implicit-euler":
                plan.append({"model": m, "integrator": integrator, "dt": None, "fraction": "largest-stable"})
    progress = Progress(len(plan), f"sweep {scene.name}") if rank == 0 else None
    rows = []
    for k, item in enumerate(plan):
        if k % size != rank:
            continue
        fraction = item["fraction"]
        if fraction == "largest-stable":
            fraction = largest_stable_fraction(scene, item["model"], integrator, use_cache=use_cache)["stable"]
            row = cached_compare(scene, item["model"], integrator, None, fraction, ref, use_cache=use_cache)
            row["largest_stable"] = True
        else:
            row = cached_compare(
                scene,
                item["model"],
                item["integrator"] if item["integrator"] != "quasi-static" else integrator,
                item["dt"],
                fraction,
                ref,
                use_cache=use_cache,
            )
        rows.append({**row, "plan_index": k})
        if progress:
            progress.step(f"{item['model']} {fraction}")
    if comm is not None and size > 1:
        gathered = comm.gather(rows, root=0)
        if rank != 0:
            return {}
        rows = [r for part in gathered for r in part]
    rows.sort(key=lambda r: r["plan_index"])
    ok = [i for i, r in enumerate(rows) if r["status"] == "ok"]
    front = [ok[i] for i in pareto_front([(rows[i]["step_us"], rows[i]["rel_l2"]) for i in ok])]
    for i, r in enumerate(rows):
        r["pareto"] = i in front
    return {
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "integrator": integrator,
        "reference": {
            k: ref.meta.get(k) for k in ("law", "degree", "refine", "ref_err_estimate", "min_det_F", "cache_key")
        },
        "rows": rows,
        "pareto": [rows[i]["model"] + (f"@{rows[i]['dt']:.3g}s" if rows[i]["dt"] else "") for i in front],
        "computed": sum(not r.get("cached") for r in rows),
        "cached": sum(bool(r.get("cached")) for r in rows),
    }


def sweep_csv(result: dict) -> str:
    cols = [
        "model",
        "integrator",
        "status",
        "fraction",
        "dt",
        "dt_crit",
        "rel_l2",
        "surface_rel_l2",
        "max_err",
        "reaction_rel_err",
        "volume_err",
        "ref_err_estimate",
        "step_us",
        "step_us_min",
        "step_us_max",
        "rate_hz",
        "pareto",
    ]
    parts = ("mesh", "model", "time")
    lines = [",".join(cols + [f"budget_{p}" for p in parts])]
    for r in result["rows"]:
        budget = r.get("error_budget") or {}
        values = [r.get(c) for c in cols] + [budget.get(p) for p in parts]
        lines.append(",".join("" if v is None else str(v) for v in values))
    return "\n".join(lines) + "\n"


def format_sweep(result: dict) -> str:
    est = result["reference"].get("ref_err_estimate")
    out = [
        f"sweep {result['scene']}: reference {result['reference']['law']} P{result['reference']['degree']}, "
        f"own error estimate {est:.3g}"
        if est is not None
        else f"sweep {result['scene']}"
    ]
    out.append(f"{'model':<16} {'dt (s)':>10} {'dt/crit':>8} {'rel_l2':>10} {'reaction':>9} {'step us':>9} {'Hz':>9}  ")
    for r in result["rows"]:
        if r["status"] != "ok":
            out.append(f"{r['model']:<16} {r['dt']:>10.3g} {r['dt'] / r['dt_crit']:>8.2f} diverged at step {r['step']}")
            continue
        ratio = "-" if r["dt"] is None or not r["dt_crit"] else f"{r['dt'] / r['dt_crit']:.2f}"
        dt = "-" if r["dt"] is None else f"{r['dt']:.3g}"
        reaction = "-" if r["reaction_rel_err"] is None else f"{r['reaction_rel_err']:.3g}"
        flag = " pareto" if r["pareto"] else ""
        flag += " (at reference accuracy)" if r["at_reference_accuracy"] else ""
        out.append(
            f"{r['model']:<16} {dt:>10} {ratio:>8} {r['rel_l2']:>10.4g} {reaction:>9} {r['step_us']:>9.1f} "
            f"{r['rate_hz']:>9.0f} {flag}"
        )
    out.append(f"Pareto front (error against step time): {', '.join(result['pareto'])}")
    out.append(f"{result['computed']} runs computed, {result['cached']} from the cache")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------


def largest_stable_fraction(
    scene: Scene,
    model_name: str,
    integrator: str = "symplectic-euler",
    steps: int = STABLE_STEPS,
    iterations: int = 7,
    use_cache: bool = True,
) -> dict:
    """Bisection on dt / dt_crit in STABLE_SEARCH for the largest step that runs ``steps`` steps from a
    small perturbation of rest (1e-6 of the mesh size) without blowing up, with the scene's loading and
    damping. Returns the stable and unstable fractions bracketing the limit, dt_crit and the ratio
    observed / predicted (1 when the prediction is exact)."""
    from realtime import DivergenceError, State, make_integrator, max_eigenvalue

    from .runner import model_for

    key = digest(
        {
            "code": code_digest(RUN_CODE),
            "scene": scene.sha256(),
            "model": model_name,
            "integrator": integrator,
            "steps": steps,
            "iterations": iterations,
        }
    )
    path = cache_dir() / "runs" / f"{scene.name}-stable-{key}.json"
    if use_cache and path.exists():
        return json.loads(path.read_text())
    model = model_for(scene, model_name)
    integ = make_integrator(integrator, scene.time.damping_mass, scene.time.damping_stiffness)
    dt_crit = integ.critical_dt(model, max_eigenvalue(model))
    size = float(np.ptp(model.points, axis=0).max())
    rng = np.random.default_rng(0)
    u0 = 1e-6 * size * rng.standard_normal(model.points.shape) * model.loading.free

    def stable(frac):
        st = State(u=u0.copy(), v=np.zeros_like(u0))
        try:
            integ.step(model, st, frac * dt_crit, steps, dt_crit=dt_crit)
            return True
        except DivergenceError:
            return False

    lo, hi = STABLE_SEARCH
    if not stable(lo):
        out = {"stable": None, "unstable": lo, "dt_crit": dt_crit, "ratio": None}
    elif stable(hi):
        out = {"stable": hi, "unstable": None, "dt_crit": dt_crit, "ratio": hi}
    else:
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if stable(mid) else (lo, mid)
        out = {"stable": lo, "unstable": hi, "dt_crit": dt_crit, "ratio": lo, "steps": steps}
    if use_cache:
        atomic_write_text(path, json.dumps(out))
    return out


# ---------------------------------------------------------------------------------------------
# stability at the extremes (docs/architecture.md section 7)

EXTREME_POISSON = (0.3, 0.45, 0.49, 0.4999)
#: Steps a static relaxation may take in the stability study before the cell is "not settled".
STABILITY_BUDGET = 200_000
#: The stability study's references: P2 without the refined solve behind the error estimate (ten
#: variants of a scene, each a non-linear solve: the estimate would triple the cost).
#: References that could not be solved in this process, by scene hash (they are not cached on disk).
_FAILED_REFERENCES: dict[str, str] = {}
STABILITY_REFERENCE = {"degree": 2, "refine": 0, "estimate": False, "newton_steps": 4, "min_increment": 1e-2}
EXTREME_YOUNG = (1e3, 1e5, 1e7)


def _far_face_tool(scene: Scene, kind: str):
    """A variant of a scene whose loads are replaced by one tool on the face of largest x: a 90 degree
    twist about the x axis ("rotation") or a push to half the length ("compression")."""
    from meshes.regions import BoxRegion
    from reference.problem import Displacement, Problem

    lo, hi = scene.mesh.bounding_box()
    eps = 1e-6 * float((hi - lo).max())
    region = BoxRegion((float(hi[0]) - eps, -1e9, -1e9), (1e9, 1e9, 1e9))
    centre = (float(hi[0]), float(0.5 * (lo[1] + hi[1])), float(0.5 * (lo[2] + hi[2])))
    if kind == "rotation":
        tool = Displacement(region=region, axis=(1.0, 0.0, 0.0), center=centre, angle=90.0, ramp=1.0)
    else:
        tool = Displacement(region=region, translation=(-0.5 * float(hi[0] - lo[0]), 0.0, 0.0), ramp=1.0)
    raw = json.loads(json.dumps(scene.raw))
    raw["load"] = [{"variant": kind}]
    return dataclasses.replace(
        scene, name=f"{scene.name}-{kind}", problem=Problem(scene.problem.fixed, (tool,)), raw=raw
    )


def _sliver_variant(scene: Scene):
    """The scene on its mesh with one interior vertex moved to make a sliver of its closest tetrahedron:
    the vertex is pushed to 2% of its height above the opposite face (aspect ratio ~50)."""
    from meshes import TetMesh

    mesh = scene.mesh
    interior = np.setdiff1d(np.arange(mesh.n_vertices), mesh.surface_vertices)
    pts = mesh.points.copy()
    if len(interior) == 0:
        return None
    v = int(interior[len(interior) // 2])
    tets = np.flatnonzero(np.any(mesh.tets == v, axis=1))
    best = None
    for t in tets:
        others = [int(w) for w in mesh.tets[t] if w != v]
        a, b, c = pts[others]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n)
        h = float(np.dot(pts[v] - a, n))
        target = pts[v] - 0.98 * h * n
        trial = pts.copy()
        trial[v] = target
        vol = np.linalg.det(
            np.stack([trial[mesh.tets[tets, k]] - trial[mesh.tets[tets, 0]] for k in (1, 2, 3)], axis=2)
        )
        if np.all(vol > 0):
            best = trial
            break
    if best is None:
        return None
    raw = json.loads(json.dumps(scene.raw))
    raw["mesh"] = {"sliver_of": scene.mesh.sha256()}
    sliver = TetMesh(best, mesh.tets, vertex_tags=mesh.vertex_tags, source=f"{mesh.source} with a sliver at vertex {v}")
    return dataclasses.replace(scene, name=f"{scene.name}-sliver", raw=raw, _mesh=sliver)


def _cell(scene: Scene, model: str, integrator: str, tol: float, baseline: float | None, use_cache: bool) -> dict:
    from realtime import NotConvergedError
    from reference.fem import ReferenceSolveError

    if scene.sha256() in _FAILED_REFERENCES:  # a reference that failed once fails again: do not re-solve it
        return _alone(scene, model, integrator, f"no reference ({_FAILED_REFERENCES[scene.sha256()]})")
    try:
        row = cached_compare(
            scene,
            model,
            integrator,
            None,
            None,
            None,
            ref_opts=STABILITY_REFERENCE,
            use_cache=use_cache,
            max_steps=STABILITY_BUDGET,
            budget=False,  # the extremes ask what a model does, not whose error is whose
        )
    except ReferenceSolveError as exc:
        _FAILED_REFERENCES[scene.sha256()] = str(exc)
        return _alone(scene, model, integrator, f"no reference ({exc})")
    except NotConvergedError as exc:
        return {"status": "not settled", "detail": str(exc)}
    if row["status"] != "ok":
        return {
            "status": "diverged",
            "detail": f"at step {row['step']} (dt {row['dt']:.3g} s, critical {row['dt_crit']:.3g} s)",
            "dt": row["dt"],
            "dt_crit": row["dt_crit"],
        }
    status = "ok" if row["rel_l2"] <= tol else "inaccurate"
    ref = row.get("reference", {})
    out = {
        "status": status,
        "rel_l2": row["rel_l2"],
        # the extremes are where a reference is least reliable: say what is known of it
        "reference": "verified" if ref.get("verified") else "reference unverified",
        "ref_err_estimate": ref.get("ref_err_estimate"),
        "ref_min_det_F": ref.get("min_det_F"),
        "dt": row["dt"],
        "dt_crit": row["dt_crit"],
        "step_us": row["step_us"],
        "settle_steps": row.get("settle_steps"),
        "settle_ms": row.get("settle_ms"),
    }
    if baseline:
        out["vs_baseline"] = row["rel_l2"] / baseline
    return out


def _alone(scene: Scene, model: str, integrator: str, why: str) -> dict:
    """A cell whose reference failed (buckling, StVK softening): the model's own fate, and how many of
    its elements ended inverted."""
    from realtime import DivergenceError, NotConvergedError
    from realtime.geometry import signed_volumes

    from .runner import run_model

    try:
        res = run_model(scene, model, integrator=integrator, max_steps=STABILITY_BUDGET)
    except DivergenceError as exc:
        return {"status": "diverged", "detail": f"{why}; the model diverged at step {exc.step}"}
    except NotConvergedError:
        return {"status": "not settled", "detail": f"{why}; the model did not settle in {STABILITY_BUDGET} steps"}
    inverted = int(np.sum(signed_volumes(scene.mesh.points + res.displacement[-1], scene.mesh.tets) <= 0.0))
    return {
        "status": "settled, no reference",
        "inverted": inverted,
        "detail": f"{why}; the model settled with {inverted} inverted elements",
    }


def stability(scene: Scene, models=None, tol: float = 0.1, use_cache: bool = True) -> dict:
    """The largest stable explicit step of every model against its predicted critical step, and what
    each model does at the extremes: nu -> 0.4999 (explicit and implicit), E from 1 kPa to 10 MPa,
    a 90 degree twist, compression to half the length, a sliver element. A cell is ok, inaccurate
    (rel_l2 above tol), diverged (with the step) or not settled; where the reference itself cannot
    follow (buckling, StVK softening) it gives the model's own fate: settled (with its inverted
    elements), diverged or not settled."""
    if scene.time.mode != "static":
        raise SceneError(f"{scene.path}: stability studies a static scene (time.mode = static)")
    models = list(models or MODELS)
    explicit = [m for m in models if m not in QUASI_STATIC]
    cases = []
    for nu in EXTREME_POISSON:
        cases.append(("poisson", nu, scene.with_material(poisson=nu)))
    for E in EXTREME_YOUNG:
        cases.append(("young", E, scene.with_material(young=E)))
    for kind in ("rotation", "compression"):
        cases.append((kind, 90.0 if kind == "rotation" else 0.5, _far_face_tool(scene, kind)))
    sliver = _sliver_variant(scene)
    if sliver is not None:
        cases.append(("sliver", sliver.mesh.quality()["max_aspect_ratio"], sliver))
    progress = Progress(len(explicit) + len(cases) * len(models), f"stability {scene.name}")
    limits = {}
    for m in explicit:
        limits[m] = largest_stable_fraction(scene, m, use_cache=use_cache)
        progress.step(f"{m} largest stable step")
    baselines = {}
    for m in models:
        base = _cell(scene, m, "symplectic-euler", tol, None, use_cache)
        baselines[m] = base.get("rel_l2")
    table = []
    for what, value, variant in cases:
        row = {"case": what, "value": value, "models": {}}
        for m in models:
            row["models"][m] = _cell(variant, m, "symplectic-euler", tol, baselines.get(m), use_cache)
            if what == "poisson" and value >= 0.49 and m in ("linear-tm", "stvk-tm"):
                row["models"][m + " (implicit)"] = _cell(variant, m, "implicit-euler", tol, baselines.get(m), use_cache)
            progress.step(f"{what}={value} {m}")
        table.append(row)
    return {
        "scene": scene.name,
        "tol": tol,
        "limits": limits,
        "baselines": baselines,
        "table": table,
        "summary": _stability_summary(limits, baselines, table),
    }


def _stability_summary(limits, baselines, table) -> list[str]:
    lines = []
    for m, lim in limits.items():
        if lim.get("stable") is not None:
            lines.append(
                f"{m}: stable up to {lim['stable']:.3g} x the predicted critical step "
                f"({lim['dt_crit']:.3g} s), unstable at {lim['unstable']:.3g} x"
                if lim.get("unstable")
                else f"{m}: stable at every step tried"
            )
    nearly = next((r for r in table if r["case"] == "poisson" and r["value"] == max(EXTREME_POISSON)), None)
    if nearly:
        locks = [m for m, c in nearly["models"].items() if c.get("vs_baseline", 0) > 2.0]
        fine = [m for m, c in nearly["models"].items() if c.get("status") == "ok"]
        lines.append(
            f"nu = {nearly['value']}: error more than doubles (locking) for {', '.join(locks) or 'none'}; "
            f"within tolerance: {', '.join(fine) or 'none'}"
        )
        for m in ("linear-tm", "stvk-tm"):
            ex, im = nearly["models"].get(m, {}), nearly["models"].get(m + " (implicit)", {})
            if ex.get("settle_ms") and im.get("settle_ms"):
                lines.append(
                    f"nu = {nearly['value']}: {m} explicit settles in {ex['settle_steps']} steps of "
                    f"{ex['dt']:.2g} s ({ex['settle_ms']:.0f} ms), implicit in {im['settle_steps']} steps of "
                    f"{im['dt']:.2g} s ({im['settle_ms']:.0f} ms)"
                    + ("; needs the implicit integrator" if im["settle_ms"] < ex["settle_ms"] else "")
                )
            elif ex.get("status") in ("not settled", "diverged"):
                lines.append(f"nu = {nearly['value']}: {m} explicit {ex['status']}; implicit {im.get('status')}")
    return lines


def format_stability(res: dict) -> str:
    out = [f"stability {res['scene']} (tolerance on rel_l2: {res['tol']})"]
    out += ["  " + line for line in res["summary"]]
    for row in res["table"]:
        out.append(f"{row['case']} = {row['value']:.4g}:")
        for m, c in row["models"].items():
            extra = f" rel_l2 {c['rel_l2']:.3g}" if "rel_l2" in c else ""
            extra += f", dt_crit {c['dt_crit']:.3g} s" if c.get("dt_crit") else ""
            extra += f" ({c['vs_baseline']:.2g} x baseline)" if "vs_baseline" in c else ""
            extra += ", reference unverified" if c.get("reference") == "reference unverified" else ""
            extra += f" {c['detail']}" if "detail" in c else ""
            out.append(f"    {m:<28} {c['status']:<16}{extra}")
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# advise

LINEAR_MODELS = ("linear-tm", "precomputed", "condensed")


def deformation_summary(points: np.ndarray, tets: np.ndarray, u: np.ndarray) -> dict:
    """Largest displacement relative to the body's size and largest element rotation (degrees) of a
    displacement u (N, 3) m on a mesh: the two numbers that decide whether linear elasticity is enough.
    Rotation: the angle of the polar rotation of each tetrahedron's P1 deformation gradient."""
    from realtime.geometry import shape_gradients

    g, _ = shape_gradients(points, tets)
    F = np.eye(3) + np.einsum("eai,eaj->eij", u[tets], g)
    U, _, Vt = np.linalg.svd(F)
    R = U @ Vt
    flip = np.linalg.det(R) < 0
    U[flip, :, 2] *= -1
    R = U @ Vt
    angle = np.degrees(np.arccos(np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)))
    size = float(np.linalg.norm(points.max(axis=0) - points.min(axis=0)))
    return {
        "max_displacement_m": float(np.linalg.norm(u, axis=-1).max()),
        "size_m": size,
        "displacement_ratio": float(np.linalg.norm(u, axis=-1).max() / size),
        "max_rotation_deg": float(angle.max()),
    }


def advise(scene: Scene, tol: float, rate: float, metric: str = "rel_l2", use_cache: bool = True, comm=None) -> dict:
    """The cheapest (model, integrator, dt) whose ``metric`` is at most ``tol`` and whose step runs at
    ``rate`` Hz or more on this machine, with the runner-up (the next feasible model) and why the
    cheaper ones failed. Candidates are the rows of ``sweep`` (all models, default steps)."""
    if metric == "reaction_rel_err" and not scene.problem.tools:
        raise SceneError(
            f"{scene.path}: --metric reaction_rel_err measures the tool's force, and this scene has no "
            "displacement load (tool); use rel_l2 or surface_rel_l2"
        )
    res = sweep(scene, use_cache=use_cache, comm=comm)
    if not res:
        return {}
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    mesh = scene.mesh
    defo = deformation_summary(
        mesh.points, mesh.tets, ref.displacement[np.argmax(np.abs(ref.displacement).max(axis=(1, 2)))]
    )
    rows = [r for r in res["rows"] if r["status"] == "ok"]
    feasible = sorted(
        (r for r in rows if r.get(metric) is not None and r[metric] <= tol and r["rate_hz"] >= rate),
        key=lambda r: r["step_us"],
    )
    physics = (
        f"displacements reach {100 * defo['displacement_ratio']:.1f}% of the size and elements rotate up to "
        f"{defo['max_rotation_deg']:.0f} degrees"
    )

    def reason(r):
        if r["status"] != "ok":
            return f"{r['model']}: diverged at dt = {r['dt']:.3g} s"
        bad = []
        if r.get(metric) is None or r[metric] > tol:
            bad.append(f"{metric} {r.get(metric, float('nan')):.3g} > {tol:g}")
        if r["rate_hz"] < rate:
            bad.append(f"{r['rate_hz']:.0f} Hz < {rate:g} Hz")
        return f"{r['model']} at {'-' if r['dt'] is None else format(r['dt'], '.3g')} s: {', '.join(bad)}"

    if not feasible:
        best = min(rows, key=lambda r: r[metric]) if rows else None
        return {
            "scene": scene.name,
            "model": None,
            "integrator": None,
            "dt": None,
            "runner_up": None,
            "why": f"no model meets {metric} <= {tol:g} at {rate:g} Hz: "
            + (
                f"the most accurate is {best['model']} ({best[metric]:.3g} at {best['rate_hz']:.0f} Hz); "
                if best
                else ""
            )
            + physics,
            "deformation": defo,
            "rejected": [reason(r) for r in res["rows"]],
        }
    choice = feasible[0]
    runner = next((r for r in feasible[1:] if r["model"] != choice["model"]), None)
    cheaper = [r for r in res["rows"] if r["status"] != "ok" or (r["step_us"] < choice["step_us"] and r is not choice)]
    cheaper_failed = [reason(r) for r in cheaper if r not in feasible]
    if choice["model"] in LINEAR_MODELS:
        why = f"linear is enough: {physics}, and {choice['model']} meets {metric} <= {tol:g} ({choice[metric]:.3g})"
    else:
        linear_errs = [r[metric] for r in rows if r["model"] in LINEAR_MODELS]
        why = f"needs a rotation-invariant model: {physics}" + (
            f"; the linear models' {metric} is at least {min(linear_errs):.3g}" if linear_errs else ""
        )
    return {
        "scene": scene.name,
        "model": choice["model"],
        "integrator": choice["integrator"],
        "dt": choice["dt"],
        "metric": metric,
        "value": choice[metric],
        "step_us": choice["step_us"],
        "rate_hz": choice["rate_hz"],
        "why": why,
        "runner_up": None
        if runner is None
        else {
            "model": runner["model"],
            "integrator": runner["integrator"],
            "dt": runner["dt"],
            "value": runner[metric],
            "step_us": runner["step_us"],
        },
        "cheaper_failed": cheaper_failed,
        "deformation": defo,
    }


# ---------------------------------------------------------------------------------------------
# converge


def converge_manufactured(scene: Scene) -> dict:
    """Observed orders of the reference on the scene's manufactured solution, P1 and P2."""
    from reference.fem import manufactured_errors

    spec = scene.manufactured
    out = {"scene": scene.name, "kind": "manufactured", "law": scene.material.law, "series": []}
    for degree in spec["degrees"]:
        sizes = spec["sizes"][str(degree)]
        runs = [manufactured_errors(scene.material.law, degree, n, scene.material) for n in sizes]
        h = np.array([r["h"] for r in runs])
        for norm, theory in (("l2", degree + 1), ("h1", degree)):
            e = np.array([r[norm] for r in runs])
            out["series"].append(
                {
                    "label": f"P{degree} {norm.upper()}",
                    "h": h.tolist(),
                    "error": e.tolist(),
                    "order": float(np.polyfit(np.log(h), np.log(e), 1)[0]),
                    "theory": theory,
                }
            )
    return out


def _carried(scene: Scene, mesh) -> Scene:
    """The scene on a uniform refinement of its mesh, each region replaced by the refined vertices that
    the scene mesh's selection spans: the rule the reference applies on its own refined meshes, so
    that every level poses the same problem."""
    from meshes.regions import VertexRegion, spanned

    def carry(region):
        return VertexRegion(tuple(np.flatnonzero(spanned(scene.mesh, region.vertices(scene.mesh), mesh.points))))

    problem = dataclasses.replace(
        scene.problem,
        fixed=tuple(dataclasses.replace(f, region=carry(f.region)) for f in scene.problem.fixed),
        loads=tuple(
            dataclasses.replace(ld, region=carry(ld.region)) if hasattr(ld, "region") else ld
            for ld in scene.problem.loads
        ),
    )
    raw = {**scene.raw, "level_of": scene.mesh.sha256(), "vertices": mesh.n_vertices}
    return dataclasses.replace(scene, problem=problem, raw=raw, _mesh=mesh)


def converge_space(scene: Scene, models=("linear-tm", "stvk-tm"), levels: int = 3) -> dict:
    """Nested mesh refinement: the scene's mesh and its uniform refinements (h, h/2, h/4, ...; the coarse
    vertices are vertices of every finer level), each model's error at each level's vertices against
    one P2 reference on the finest level, solved once, and the reference's own self-convergence (P1
    and P2 at each level against it). The geometry never changes, curved or not: refinement splits the
    coarse mesh's own tetrahedra. Orders are fitted against h."""
    from reference.driver import solve_static as reference_static

    from .runner import run_model

    if scene.time.mode != "static":
        raise SceneError(f"{scene.path}: converge --in space studies static scenes")
    meshes = [scene.mesh]
    for _ in range(levels - 1):
        meshes.append(meshes[-1].refined())
    e = scene.mesh.edges
    h0 = float(np.linalg.norm(scene.mesh.points[e[:, 1]] - scene.mesh.points[e[:, 0]], axis=1).mean())  # mean edge
    hs = [h0 / 2**k for k in range(levels)]
    progress = Progress(1 + levels * (len(models) + 2), f"converge {scene.name}")
    fine = reference_static(
        scene.mesh, scene.material, scene.problem, degree=2, refine=levels - 1, estimate=False, points=meshes[-1].points
    )["displacement"]
    progress.step("truth: P2 on the finest level")
    series = {m: [] for m in list(models) + ["reference P1", "reference P2"]}
    for k, mesh in enumerate(meshes):
        truth = fine[: mesh.n_vertices]  # nested: level k's vertices come first at every finer level
        scale = np.linalg.norm(truth)
        level = _carried(scene, mesh) if k else scene
        for m in models:
            u = run_model(level, m).displacement[-1]
            series[m].append(float(np.linalg.norm(u - truth) / scale))
            progress.step(f"level {k} {m}")
        for deg in (1, 2):
            if k == levels - 1 and deg == 2:
                series["reference P2"].append(None)  # the truth itself
            else:
                u = reference_static(
                    scene.mesh, scene.material, scene.problem, degree=deg, refine=k, estimate=False, points=mesh.points
                )["displacement"]
                series[f"reference P{deg}"].append(float(np.linalg.norm(u - truth) / scale))
            progress.step(f"level {k} reference P{deg}")
    out = {"scene": scene.name, "kind": "space", "h": hs, "series": []}
    for label, errs in series.items():
        pts = [(h, e) for h, e in zip(hs, errs, strict=True) if e]
        order = (
            float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0]) if len(pts) >= 2 else None
        )
        theory = {"reference P1": 2, "reference P2": 3}.get(label)  # L2 of displacements at the vertices
        out["series"].append(
            {"label": label, "h": [p[0] for p in pts], "error": [p[1] for p in pts], "order": order, "theory": theory}
        )
    return out


def converge_time(scene: Scene, models=("linear-tm",), integrators=("symplectic-euler", "central-difference")) -> dict:
    """dt halving on a dynamic scene: each (model, integrator)'s trajectory at 0.4, 0.2, 0.1 x dt_crit
    against its own run at 0.025 x dt_crit; the observed order of the integrator."""
    from .runner import run_model

    if scene.time.mode != "dynamic":
        raise SceneError(f"{scene.path}: converge --in time needs a dynamic scene (time.mode = dynamic)")
    out = {"scene": scene.name, "kind": "time", "series": []}
    for m in models:
        for integ in integrators:
            fine = run_model(scene, m, dt_fraction=0.025, integrator=integ)
            dts, errs = [], []
            for f in (0.4, 0.2, 0.1):
                r = run_model(scene, m, dt_fraction=f, integrator=integ)
                dts.append(r.meta["dt"])
                errs.append(
                    float(np.linalg.norm(r.displacement - fine.displacement) / np.linalg.norm(fine.displacement))
                )
            out["series"].append(
                {
                    "label": f"{m} {integ}",
                    "h": dts,
                    "error": errs,
                    "order": float(np.polyfit(np.log(dts), np.log(errs), 1)[0]),
                    "theory": {"symplectic-euler": 1, "central-difference": 2, "implicit-euler": 1}[integ],
                }
            )
    return out


def format_converge(res: dict) -> str:
    unit = "dt (s)" if res["kind"] == "time" else "h"
    out = [f"converge {res['scene']} ({res['kind']})"]
    for s in res["series"]:
        theory = f" (theory {s['theory']})" if s.get("theory") is not None else ""
        order = "-" if s["order"] is None else f"{s['order']:.2f}"
        errs = ", ".join(f"{e:.3g}" for e in s["error"])
        out.append(
            f"  {s['label']:<28} order {order}{theory}   errors {errs} at {unit} {', '.join(f'{h:.3g}' for h in s['h'])}"
        )
    return "\n".join(out)
