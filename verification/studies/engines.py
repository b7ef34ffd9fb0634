"""The questions users of other engines ask, answered on a scene (``tissuebench engines SCENE``;
docs/engines.md): for every adapter's model, its error against the reference as a function of its own
knobs, its largest stable step, and whether its answer depends on its iteration count.

The plan is fixed before anything runs, so that ``mpirun -n P`` spreads it over ranks as ``sweep`` does:

- the time step: an explicit solver (newton's semi-implicit, MuJoCo's Euler) at ``EXPLICIT_FRACTIONS`` of
  the scene mesh's explicit critical step (the built-in linear model's, the same P1 mesh: one axis for
  every engine); an implicit one (newton's VBD and XPBD, MuJoCo's discrete integrator) at
  ``IMPLICIT_STEPS``, the steps real-time loops take, from 10 kHz to 100 Hz;
- the iterations of a solver that has them (VBD, XPBD): ``ITERATIONS`` at ``ITERATION_DT``, the 1 ms step
  newton's examples take.

Each planned step is also probed for stability as the built-in models' are (``STABLE_STEPS`` plain steps
from rest under the scene's loads, no damping of ours: ``AdapterSimulation.probe``). The largest stable
step is the largest planned one the probe passed, bracketed by the smallest above it that blew up (a
factor of 2 to 3 apart: the grid's resolution). The probes go down the grid from its largest step and
stop at the first that holds: the steps below it cannot change that answer, and an implicit solver's
probes that hold are the costly ones (newton's VBD: 20 s each on the liver). It can exceed the largest
step whose static relaxation settles: kinetic damping's velocity resets make some steps gradient descent, stable only below
sqrt(2) / omega_max (adapters/exported.py, RELAX_FRACTION). The answer depends on
the iteration count when the answers at the two largest counts differ by more than ``DEPENDS`` of the
reference's norm.
"""

from __future__ import annotations

import time
from concurrent.futures import ThreadPoolExecutor, as_completed

import numpy as np

from realtime.models import linear_tm
from reference.errors import ReferenceSolveError
from reference.progress import line
from verification.engines import ENGINES, engine_for
from verification.engines.adapters import AdapterEngine
from verification.engines.builtin import BUILTIN
from verification.engines.settling import omega2_min_rest
from verification.inputs import scene_inputs
from verification.runs.compare import cancelling
from verification.runs.reference import P1_OWN_MESH, REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row
from verification.runs.store import cached_compare
from verification.scene import Scene
from verification.studies.stable_step import STABLE_STEPS

#: Explicit solvers' steps, as fractions of the scene mesh's explicit critical step.
EXPLICIT_FRACTIONS = (0.25, 0.5, 1.0, 2.0, 4.0)
#: Implicit solvers' steps, s: 10 kHz, about 3 kHz, 1 kHz, about 300 Hz, 100 Hz.
IMPLICIT_STEPS = (1e-4, 3e-4, 1e-3, 3e-3, 1e-2)
#: Iteration counts, at ITERATION_DT s. An iterative solver's time-step runs take ADAPTER_ITERATIONS (the
#: adapters' default, adapters/exported.py ``arguments``), named: its run at ITERATION_DT is that count's.
ITERATIONS, ITERATION_DT, ADAPTER_ITERATIONS = (1, 2, 5, 10, 20, 50), 1e-3, 10
#: A static run's step budget in the study: an answer the engine does not reach in SETTLE_PERIODS of the
#: scene's slowest period (at rest, the built-in linear model's on the scene mesh), or STUDY_MIN_STEPS
#: where that is more, and at most STUDY_MAX_STEPS, is "not settled" at that step. Kinetic damping's
#: restarts settle a run in slowest periods, not steps. Every settled run of the study on cantilever and
#: sofa-liver: those past 20 000 steps took 2.5 to 5.4 periods (newton's semi-implicit solver, MuJoCo's
#: flex, PyBullet at their small steps); those that took more periods (VBD at 1 ms and 2 iterations: 47,
#: MuJoCo's discrete flex at 10 ms: 167) took at most 5 700 steps. Without a budget a relaxation caught
#: in a cycle ran into the adapter's 300 s wall (a verdict of the machine's load); with 200 000 steps
#: alone, newton's XPBD at 0.3 ms on the liver (60 s simulated, 140 periods) took 269 s of the study.
SETTLE_PERIODS, STUDY_MIN_STEPS, STUDY_MAX_STEPS = 30.0, 20_000, 200_000
#: Two answers closer than this (their distance, relative L2 over the reference's norm) are the same:
#: three times the relaxation's own round-off in float32 (measured 2.8e-4 with newton's semi-implicit
#: solver on the built-in cantilever). A run whose relaxation stalled (adapters/exported.py: ``stalled_at``,
#: its last relative change) has a floor of its own: two answers are told apart only above three times
#: the larger of the two runs' stalls too.
DEPENDS = 1e-3


def adapter_models(models=None) -> list[tuple[AdapterEngine, str]]:
    """The (engine, model) pairs to study: the registered adapters' models, or those of ``models``."""
    pairs = [(e, m) for e in ENGINES.values() if isinstance(e, AdapterEngine) for m in e.models]
    return [(e, m) for e, m in pairs if models is None or m in models]


def engines_plan(scene: Scene, pairs, device: str | None = None) -> list[dict]:
    """Every run of the study: model, dt (s), options, the knob it varies ("dt", "iterations", or
    "stability": one item a model, its probes' steps largest first in ``dts``), and a static run's step
    budget ``max_steps`` (``study_budget``); ``device``, warp's device, goes in the options of every model
    whose engine takes one (newton's, MuJoCo Warp's)."""
    sim = BUILTIN.build(scene_inputs(scene), linear_tm.NAME, "symplectic-euler", {})
    dt_crit, slowest = sim.critical_dt(), omega2_min_rest(sim.inputs, sim.model_obj)
    plan = []
    for engine, model in pairs:
        base = {"device": device} if device is not None and "device" in engine.knobs else {}
        steps = [f * dt_crit for f in EXPLICIT_FRACTIONS] if model in engine.explicit else list(IMPLICIT_STEPS)
        counted = model in engine.iterative
        run = {**base, "iterations": ADAPTER_ITERATIONS} if counted else base
        plan += [
            {"model": model, "dt": float(dt), "options": dict(run), "knob": "dt", "counts": counted and dt == ITERATION_DT}
            for dt in steps
        ]  # fmt: skip
        down = sorted((float(dt) for dt in steps), reverse=True)
        plan.append({"model": model, "dt": down[0], "dts": down, "options": dict(base), "knob": "stability"})
        if counted:
            plan += [
                {"model": model, "dt": ITERATION_DT, "options": {**base, "iterations": k}, "knob": "iterations"}
                for k in ITERATIONS
                if not (k == ADAPTER_ITERATIONS and ITERATION_DT in steps)  # that run is in the steps' already
            ]
    for item in plan:
        item["max_steps"] = study_budget(slowest, item["dt"])
    return plan


def study_budget(omega2_slowest: float | None, dt: float) -> int:
    """A static run's step budget at step ``dt`` (s) (STUDY_MAX_STEPS's comment), from the scene's slowest
    omega^2 (1/s^2; None where it is not cheap to find: STUDY_MAX_STEPS)."""
    if not omega2_slowest or omega2_slowest <= 0.0:
        return STUDY_MAX_STEPS
    periods = SETTLE_PERIODS * 2.0 * np.pi / np.sqrt(omega2_slowest) / dt
    return int(min(STUDY_MAX_STEPS, max(STUDY_MIN_STEPS, np.ceil(periods))))


def _own_law_truths(scene: Scene, pairs) -> None:
    """The P1 truths of the engines' own laws on the scene's mesh, solved before the runs: the runs go
    in threads (``engines_study``), and dolfinx's solves are not for two threads at once; each run then
    reads its own law's truth from the cache. One that cannot solve is the runs' to report (``own_law``)."""
    for law in sorted({e.laws[m] for e, m in pairs if m in e.laws}):
        try:
            reference_result(scene.with_material(law=law), **P1_OWN_MESH)
        except ReferenceSolveError:
            pass


def _run(scene: Scene, item: dict, ref, use_cache: bool) -> Row:
    """One planned run as a row; a run that gives no answer (unsettled, stopped past its time bound,
    failed) is a row saying so, and the study goes on."""
    from realtime import NotConvergedError
    from realtime.errors import InputError, ModelRestriction

    try:
        return _probe(scene, item) if item["knob"] == "stability" else _compare(scene, item, ref, use_cache)
    except ModelRestriction as exc:  # the engine cannot represent the scene: its answer, said so
        return Row(scene.name, item["model"], "own", "not applicable", dt=item["dt"], message=str(exc))
    except (NotConvergedError, InputError) as exc:
        return Row(scene.name, item["model"], "own", "not settled", dt=item["dt"], message=str(exc))


def _compare(scene: Scene, item: dict, ref, use_cache: bool) -> Row:
    return cached_compare(
        scene, item["model"], "own", item["dt"], None, ref, use_cache=use_cache, max_steps=item["max_steps"],
        budget=scene.time.mode == "static", options=item["options"] or None,
        keep_answer=_counts(item),  # the iteration counts' answers are compared with each other
    )  # fmt: skip


def _counts(item: dict) -> bool:
    """Whether a planned run is one of the iteration counts' (its own knob's, or the time steps' run at
    ITERATION_DT with the adapters' count)."""
    return item["knob"] == "iterations" or bool(item.get("counts"))


def _answer(scene: Scene, item: dict):
    """The displacements (T, N, 3) m a planned run kept (``_compare``), or None."""
    from verification.runs.store import cached_answer

    budget, options = scene.time.mode == "static", item["options"] or None
    return cached_answer(scene, item["model"], "own", item["dt"], None, budget=budget, options=options,
                         max_steps=item["max_steps"])  # fmt: skip


def _probe(scene: Scene, item: dict) -> Row:
    """A planned step's stability probe, as a row: "ok" when it held, "diverged" with its step when not."""
    engine = engine_for(item["model"])
    sim = engine.build(scene_inputs(scene), item["model"], "own", dict(item["options"]))
    out = sim.probe(item["dt"], STABLE_STEPS)
    status = "ok" if out["stable"] else "diverged"
    return Row(scene.name, item["model"], sim.integrator, status, dt=item["dt"], step=out.get("step"),
               message=f"{STABLE_STEPS} plain steps from rest: {'held' if out['stable'] else 'blew up'}")  # fmt: skip


def builtin_beside(scene: Scene, ref, use_cache: bool) -> list[dict]:
    """The built-in models in the same run, for the table beside the adapters: each at its default step
    (0.9 of its critical one, or its quasi-static update) with its error, its step time and its largest
    stable step (``largest_stable_fraction``, the same STABLE_STEPS probe from rest)."""
    from verification.studies.stable_step import largest_stable_fraction

    out = []
    for model in BUILTIN.models:
        row = cached_compare(scene, model, reference=ref, use_cache=use_cache, budget=scene.time.mode == "static")
        stable = (
            None if BUILTIN.models[model].quasi_static else largest_stable_fraction(scene, model, use_cache=use_cache)
        )
        out.append(
            {
                "model": model,
                "status": row.status,
                "rel_l2": row.rel_l2,
                "step_us": row.step_us,
                "dt": row.dt,
                "model_part": (row.error_budget or {}).get("model"),
                "largest_stable_dt": None if stable is None else stable["stable"] * stable["dt_crit"],
                "first_diverged_dt": None if stable is None else stable["unstable"] * stable["dt_crit"],
            }
        )
        line(f"engines {scene.name}: built-in {model}: {_state(row)}")
    return out


def engines_study(
    scene: Scene,
    models=None,
    use_cache: bool = True,
    comm=None,
    builtin: bool = False,
    on_run=None,
    jobs: int = 1,
    device: str | None = None,
) -> dict:
    """The study (module docstring): its rows, each model's summary, the mesh's own error (the P1 solution
    of the scene's law on its mesh against the reference: what every engine on this mesh pays); with
    ``builtin``, the built-in models measured in the same run (``builtin_beside``). ``on_run(run)`` is
    called with each run's entry of "runs" as it finishes (the command prints it). ``jobs`` runs go at
    once (each an adapter's process: one a core), on every MPI rank of ``comm``; ``device`` is warp's
    device for the engines that take one (``engines_plan``). Stopped by Ctrl-C, the study returns what
    had finished, with ``stopped`` saying how far it came (every finished run is in the cache: the same
    command resumes)."""
    pairs = adapter_models(models)
    rank, size = (comm.rank, comm.size) if comm is not None else (0, 1)
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    try:
        p1 = reference_result(scene, **P1_OWN_MESH)
        mesh_part = float(np.linalg.norm(p1.displacement - ref.displacement) / np.linalg.norm(ref.displacement))
    except ReferenceSolveError:
        mesh_part = None
    _own_law_truths(scene, pairs)
    scale = float(np.linalg.norm(ref.displacement))
    plan = engines_plan(scene, pairs, device)
    mine = [(k, item) for k, item in enumerate(plan) if k % size == rank]
    rows, refused, stopped = [], {}, None
    who = f" (rank {rank})" if size > 1 else ""

    def one(k: int, item: dict) -> tuple[dict, Row]:
        t0 = time.perf_counter()
        if item["model"] in refused:  # the engine cannot represent the scene: no run of it will
            row = refused[item["model"]].replace(dt=item["dt"], plan_index=k)
        else:
            row = _run(scene, item, ref, use_cache).replace(plan_index=k)
        if row.status == "not applicable":
            refused[item["model"]] = row
        # every rank and worker says what it finished: the runs are each a process of their own, minutes long
        line(f"engines {scene.name}{who}: run {k + 1} of {len(plan)}, {item['model']} {item['knob']} "
             f"{_knob_value(item)}: {_state(row)} ({time.perf_counter() - t0:.0f} s)")  # fmt: skip
        return item, row

    pool = ThreadPoolExecutor(max_workers=max(1, jobs))
    try:
        for done in as_completed([pool.submit(_item_runs, one, k, item) for k, item in mine]):
            for item, row in done.result():
                rows.append((item, row))
                if on_run is not None:
                    on_run(_entry(item, row))
    except KeyboardInterrupt:
        stopped = f"stopped after {len(rows)} of the {len(plan)} runs; the same command resumes from the cache"
    finally:
        pool.shutdown(wait=stopped is None, cancel_futures=True)
    rows.sort(key=lambda ir: ir[1].plan_index)
    if comm is not None and size > 1:
        gathered = comm.gather(rows, root=0)
        if rank != 0:
            return {}
        rows = sorted((r for part in gathered for r in part), key=lambda ir: ir[1].plan_index)
    return {
        "scene": scene.name,
        "builtin": builtin_beside(scene, ref, use_cache) if builtin and not stopped else [],
        "reference_estimate": ref.meta.get("ref_err_estimate"),
        "mesh_error": mesh_part,
        "runs": [_entry(item, row) for item, row in rows],
        "summary": [
            _summary(model, [(i, r) for i, r in rows if r.model == model], lambda i: _answer(scene, i), scale)
            for _, model in pairs
        ],
        **({"stopped": stopped} if stopped else {}),
    }


def _item_runs(one, k: int, item: dict) -> list[tuple[dict, Row]]:
    """Planned item ``k``'s runs (``one(k, item)`` makes each): one, or a stability scan's probes down its
    steps to the first that holds."""
    out = []
    for dt in item.get("dts", [item["dt"]]):
        out.append(one(k, {**item, "dt": dt}))
        if out[-1][1].status in ("ok", "not applicable"):
            break
    return out


def _entry(item: dict, row: Row) -> dict:
    """A run's entry of the study's "runs": its knob and options with its row."""
    return {"knob": item["knob"], "options": item["options"], **row.to_json()}


def run_line(r: dict) -> str:
    """One run (an entry of "runs") as a line of the table."""
    knob = f"iterations {r['options']['iterations']}" if r["knob"] == "iterations" else f"dt {r['dt']:.3g} s"
    if r["knob"] == "stability" and r["status"] in ("ok", "diverged"):
        state = f"probe: {'stable' if r['status'] == 'ok' else 'diverged at step ' + str(r['step'])}"
    elif r["status"] == "ok":
        model = (r.get("error_budget") or {}).get("model")
        state = f"rel_l2 {r['rel_l2']:.4g}  {r['step_us']:.4g} us" + (
            f"  (model part {model:.3g})" if model is not None else ""
        )
    else:
        state = r["status"] + (f": {r['message']}" if r["status"] == "not applicable" and r.get("message") else "")
    return f"  {r['model']:<22} {knob:<18} {state}"


def _knob_value(item: dict) -> str:
    return str(item["options"]["iterations"]) if item["knob"] == "iterations" else f"{item['dt']:.3g} s"


def _state(row: Row) -> str:
    if row.message and row.message.startswith(f"{STABLE_STEPS} plain steps"):
        return row.message
    if not row.ok:
        return row.status
    return f"rel_l2 {row.rel_l2:.3g}" + (f", {row.step_us:.4g} us" if row.step_us is not None else "")


def _summary(model: str, runs: list[tuple[dict, Row]], answer=lambda item: None, scale: float = 1.0) -> dict:
    """One model's answers: the largest stable step (and the smallest diverged above it), its best run,
    and whether its answer depends on the iteration count."""
    probes = sorted((r.dt, r.ok) for i, r in runs if i["knob"] == "stability" and r.status in ("ok", "diverged"))
    stable = [dt for dt, held in probes if held]
    largest = max(stable) if stable else None
    above = [dt for dt, held in probes if not held and (largest is None or dt > largest)]
    settles = [r.dt for i, r in runs if i["knob"] == "dt" and r.ok]
    ok = [r for i, r in runs if r.ok and i["knob"] != "stability"]
    best = min(ok, key=lambda r: r.rel_l2) if ok else None
    out = {
        "model": model,
        "engine": (best.engine if best else None),
        "largest_stable_dt": largest,
        "first_diverged_dt": min(above) if above else None,
        "largest_settling_dt": max(settles) if settles else None,
        "best": None
        if best is None
        else {
            "rel_l2": best.rel_l2,
            "dt": best.dt,
            "step_us": best.step_us,
            "model_part": (best.error_budget or {}).get("model"),
            "own_law": best.own_law,
        },
        "iterations": None,
        "not_applicable": next((r.message for _, r in runs if r.status == "not applicable"), None),
    }
    by_count = sorted(((i["options"]["iterations"], r, i) for i, r in runs if _counts(i)), key=lambda t: t[0])
    if by_count:
        done = [(k, r, answer(i)) for k, r, i in by_count if r.ok]
        out["iterations"] = {
            "rel_l2": {str(k): (r.rel_l2 if r.ok else r.status) for k, r, _ in by_count},
            "depends": _depends(done, scale),
        }
    return out


def _depends(done: list[tuple[int, Row, np.ndarray | None]], scale: float) -> dict:
    """Whether the answer still moves with the iteration count: the distance between the answers (T, N, 3)
    m of the two largest counts that ran, relative to ``scale`` (the reference's norm, m), against DEPENDS
    and three times the larger of the two runs' stalls. Their errors' difference is no test: two different
    answers can be equally far from the truth. "undecided" with the reason where fewer than two answers
    were kept, or their distance lies within a stall's floor above DEPENDS."""
    if len(done) < 2:
        return {"verdict": "undecided", "why": "fewer than two iteration counts ran to an answer"}
    (k1, r1, a1), (k2, r2, a2) = done[-2], done[-1]
    if a1 is None or a2 is None:
        return {"verdict": "undecided", "why": f"the answers of {k1} and {k2} iterations were not kept"}
    distance = float(np.linalg.norm(a2 - a1)) / max(scale, 1e-300)
    stall = max(float((r.engine or {}).get("stalled_at") or 0.0) for r in (r1, r2))
    floor = max(DEPENDS, 3.0 * stall)
    out = {"distance": distance, "between": [k1, k2], "floor": floor}
    out["spread"] = max(r.rel_l2 for _, r, _ in done) - min(r.rel_l2 for _, r, _ in done)
    if distance > floor:
        return {**out, "verdict": "depends"}
    if distance <= DEPENDS and floor == DEPENDS:
        return {**out, "verdict": "converged"}
    return {
        **out,
        "verdict": "undecided",
        "why": f"the answers are {distance:.2g} apart, within their relaxation's floor ({floor:.2g}: a stall)",
    }


def stable_text(s: dict) -> str:
    """A model's summary's largest stable step, bracketed by the first step above it that diverged."""
    big, bad = s["largest_stable_dt"], s["first_diverged_dt"]
    text = f"{big:.3g} s" if big else "none of the steps tried"
    return text + (f" (diverged at {bad:.3g} s)" if bad else " (none tried diverged)")


def format_engines(out: dict) -> str:
    """The study as text: each model's summary, then every run."""
    est, mesh = out.get("reference_estimate"), out.get("mesh_error")
    lines = [f"{out['scene']}: other engines against the reference (its estimate {est:.2g})" if est else out["scene"]]
    if mesh is not None:
        lines.append(f"  the mesh's own error (P1 on this mesh, what every engine here pays): {mesh:.3g}")
    for s in out["summary"]:
        if s.get("not_applicable"):
            lines.append(f"\n{s['model']}: not applicable: {s['not_applicable']}")
            continue
        lines.append(f"\n{s['model']}: {(s['engine'] or {}).get('engine', 'no run reached an answer')}")
        if s["engine"]:
            lines.append(f"  law: {s['engine'].get('law')}")
        lines.append(
            "  largest stable step: "
            + stable_text(s)
            + (
                f"; its static answer reached up to {s['largest_settling_dt']:.3g} s"
                if s["largest_settling_dt"]
                else ""
            )
        )
        if s["best"]:
            b = s["best"]
            own = b.get("model_part")
            lines.append(
                f"  best: rel_l2 {b['rel_l2']:.3g} at dt {b['dt']:.3g} s, {b['step_us']:.4g} us a step"
                + (f"; its distance from P1 on the same mesh {own:.3g}" if own is not None else "")
                + (
                    " (below the mesh's own error: right for a wrong reason)"
                    if cancelling(b["rel_l2"], mesh, own)
                    else ""
                )
            )
            law = b.get("own_law") or {}
            if law.get("rel_l2") is not None:
                lines.append(
                    f"  against P1 of its own law ({law['law']}) on the same mesh: {law['rel_l2']:.3g}, its numerics "
                    f"alone (against the scene's law: {own:.3g})"
                    if own is not None
                    else f"  against P1 of its own law ({law['law']}) on the same mesh: {law['rel_l2']:.3g}"
                )
        it = s["iterations"]
        if it:
            counts = ", ".join(f"{k}: {v if isinstance(v, str) else f'{v:.3g}'}" for k, v in it["rel_l2"].items())
            d = it["depends"]
            why = (
                f" (the answers of {d['between'][0]} and {d['between'][1]} iterations {d['distance']:.2g} apart)"
                if "distance" in d
                else ""
            )
            lines.append(f"  rel_l2 by iterations at {ITERATION_DT:g} s: {counts}; answer {d['verdict']}{why}")
    if out.get("builtin"):
        lines.append("\nthe built-in models, in the same run (their default step; largest stable by the same probe):")
        for b in out["builtin"]:
            if b["status"] != "ok":
                lines.append(f"  {b['model']:<22} {b['status']}")
                continue
            big = "quasi-static" if b["largest_stable_dt"] is None else f"largest stable {b['largest_stable_dt']:.3g} s"
            lines.append(f"  {b['model']:<22} rel_l2 {b['rel_l2']:.4g}  {b['step_us']:.4g} us  {big}")
    lines.append("\nruns:")
    lines += [run_line(r) for r in out["runs"]]
    if out.get("stopped"):
        lines.append(f"\n{out['stopped']}: the table above is partial")
    return "\n".join(lines)
