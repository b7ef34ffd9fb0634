"""The advisor (docs/verification.md): the cheapest model, integrator and time step that meet
an error tolerance while a simulator holds a frame rate on this machine, on the scene's mesh or, when
the mesh's own error is what stops every model, on the refinement of it that the observed convergence
rate says is needed.

0. The reference is made sharp enough for the tolerance where that is affordable (``truth``).
1. Every model runs on the scene at the sweep's steps (and, on a static scene, with implicit Euler).
2. Each run's frame budget (``frame_budget``) says whether it holds the rate and what it costs (and at
   the haptic rate, where one is asked).
3. Runs of one model and integrator whose errors agree (the step changes nothing, as on a static
   scene) are one candidate, the one that reaches its answer soonest.
4. The cheapest candidate within the tolerance, whatever the reference's own error (``frame.judgement``:
   its error's whole interval), that holds the rate is the answer; every cheaper one is named with the
   reason it failed: its error (with the budget's mesh, model and time parts), its frame budget or its
   stability, or that the truth's bar leaves it undecided.
5. When none qualifies and the budget's mesh part is what stops them (``proposal``), the P1 solution
   on one uniform refinement gives the observed order of the mesh's error; the coarsest level whose predicted mesh
   part leaves room for a model's own part is proposed, and the models are run there, cheapest
   predicted first, until one meets both. The answer is a measured run, never a prediction.
"""

from __future__ import annotations

import math

import numpy as np

from verification.engines import engine_for, offered, spec_of
from verification.progress import Bar, log
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row
from verification.runs.simulate import step_time_ahead
from verification.runs.store import compare_or_unsettled
from verification.scene import Scene, SceneError
from verification.scene_file import builtin_scenes
from verification.studies.frame import (
    FRAME_SHARE,
    QUALIFIES,
    UNDECIDED,
    cost,
    frame_budget,
    judgement,
    label,
    merge_same_answers,
    row_interval,
    verdict,
    with_bar,
)
from verification.studies.proposal import (
    BUILD_LIMIT_S,
    OPTIMISM,
    own_part,
    proposal_summary,
    propose_mesh,
    refined_times,
    run_plans,
)
from verification.studies.sweep import sweep
from verification.studies.truth import MARGIN, SHARP, sharp_reference

#: On a dynamic scene, implicit Euler's steps per frame at the rate asked: one (the state changes once a
#: frame), 4 and 16 (less numerical damping, more work: the runs too slow are screened out). On the
#: stiff beam at 60 Hz, one step a frame was 16% off, four 1.4%, in 4.4 ms of a 16.7 ms frame.
IMPLICIT_STEPS_PER_FRAME = (1, 4, 16)


def deformation_summary(points: np.ndarray, tets: np.ndarray, u: np.ndarray) -> dict:
    """Largest displacement relative to the body's size and largest element rotation (degrees) of a
    displacement u (N, 3) m on a mesh with points (N, 3) m and tets (M, 4) int: the two numbers that
    decide whether linear elasticity is enough. Rotation: the angle of the polar rotation of each
    tetrahedron's P1 deformation gradient."""
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


def over_budget(rate: float):
    """The advisor's screen of a sweep's runs on a dynamic scene (sweep's ``screen``): a built-in model's
    steps timed ahead (``step_time_ahead``) whose frame does not fit even in OPTIMISM x FRAME_SHARE of a
    frame at ``rate`` cannot qualify whatever its error, so its run is not made (the stiff beam's
    adaptive-tm at 8.5e-8 s steps: 2.3 million steps, over 10 minutes, for a verdict its first 150 steps
    decide). It is a row of status "over budget" with its step, its step time and its frame."""

    def screen(scene: Scene, model: str, integrator: str, dt, fraction) -> Row | None:
        ahead = step_time_ahead(scene, model, dt, fraction, integrator)
        if ahead is None:
            return None
        row = Row(
            scene.name, model, integrator, "over budget", dt=ahead["dt"], dt_crit=ahead["dt_crit"],
            step_us=ahead["step_us"], step_us_min=ahead["step_us_min"], step_us_max=ahead["step_us_max"],
            fraction=fraction, n_vertices=scene.mesh.n_vertices, n_tets=scene.mesh.n_tets,
        )  # fmt: skip
        if frame_budget(row, rate, True, share=FRAME_SHARE * OPTIMISM)["holds"]:
            return None
        frame = frame_budget(row, rate, True)
        return row.replace(frame=frame, message=f"not run: its steps timed ahead, {frame['why']}")

    return screen


def _candidates(
    scene: Scene,
    metric: str,
    rate: float,
    use_cache: bool,
    comm,
    progress_label: str,
    models=None,
    ref_opts=None,
    haptic=None,
) -> list[Row]:
    """The scene's runs of ``models`` (default all), each with its frame budget, merged by
    ``merge_same_answers``; on a dynamic scene the runs too slow for ``rate`` are not made
    (``over_budget``). ``ref_opts``: the reference judged against (default REFERENCE_DEFAULTS);
    ``haptic``: the haptic loop's rate and force tolerance (``frame_budget``), or None."""
    dynamic = scene.time.mode == "dynamic"
    # the model steps at the haptic loop's rate where there is one: what does not fit its frame cannot qualify
    stepping = haptic["rate"] if haptic else rate
    screen = over_budget(stepping) if dynamic else None
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    res = sweep(scene, models=models, use_cache=use_cache, comm=comm, screen=screen, ref_opts=ref_opts)
    if comm is not None and comm.size > 1:
        # every rank goes on with the same rows: the reference solves below are collective
        res = comm.bcast(res, root=0)
    rows = list(res["rows"])
    # the time-stepping models whose spec lists implicit Euler, tried with it on static scenes (it settles
    # in tens of steps) and on dynamic ones
    extra = [m for m in (models or offered()) if "implicit-euler" in spec_of(m).integrators]
    if not dynamic:
        progress = Bar(len(extra), progress_label)
        for m in extra:
            rows.append(
                compare_or_unsettled(scene, m, "implicit-euler", None, None, ref_opts=ref_opts, use_cache=use_cache)
            )
            progress.step(f"{m} implicit-euler")
    else:
        # implicit Euler at a frame's step and finer: where a stiff body's explicit steps cannot keep up
        # with the clock (thousands a frame), its steps may, at the price of its numerical damping
        progress = Bar(len(extra) * len(IMPLICIT_STEPS_PER_FRAME), progress_label)
        for m in extra:
            for k in IMPLICIT_STEPS_PER_FRAME:
                dt = 1.0 / (k * stepping)
                row = screen(scene, m, "implicit-euler", dt, None)
                rows.append(
                    row
                    or compare_or_unsettled(
                        scene, m, "implicit-euler", dt, None, ref_opts=ref_opts, use_cache=use_cache
                    )
                )
                progress.step(f"{m} implicit-euler, dt {dt:.3g} s")
    rows = [r.replace(frame=frame_budget(r, rate, dynamic, haptic=haptic)) if r.ok else r for r in rows]
    return merge_same_answers(rows, metric, dynamic)


def _pick(rows: list[Row], metric: str, tol: float, dynamic: bool):
    ok = [r for r in rows if verdict(r, metric, tol)[0]]
    return min(ok, key=lambda r: cost(r, dynamic)) if ok else None


def _summary(scene: Scene, tol: float, rate: float, metric: str, ref_opts: dict, truth: dict) -> tuple[dict, str]:
    """The advice's header (the question, the reference's deformation and estimate, the mesh, and how
    sharp the truth is: ``truth``, from ``sharp_reference``) and the deformation in words."""
    ref = reference_result(scene, **ref_opts)
    mesh = scene.mesh
    defo = deformation_summary(
        mesh.points, mesh.tets, ref.displacement[np.argmax(np.abs(ref.displacement).max(axis=(1, 2)))]
    )
    physics = (
        f"displacements reach {100 * defo['displacement_ratio']:.1f}% of the size and elements rotate up to "
        f"{defo['max_rotation_deg']:.0f} degrees"
    )
    out = {
        "scene": scene.name,
        "tol": tol,
        "rate": rate,
        "metric": metric,
        "frame_share": FRAME_SHARE,
        "deformation": defo,
        "mesh": _mesh_summary(scene),
        "reference_err_estimate": ref.meta.get("ref_err_estimate"),
        "reference": {"options": ref_opts, **truth},
    }
    return out, physics


def advise(
    scene: Scene,
    tol: float,
    rate: float,
    metric: str = "rel_l2",
    use_cache: bool = True,
    comm=None,
    models=None,
    haptic_rate: float | None = None,
    force_tol: float | None = None,
    truth_budget: float | None = None,
) -> dict:
    """The cheapest (model, integrator, dt, mesh) whose ``metric`` is at most ``tol`` while a simulator
    holds ``rate`` frames per second on this machine (``frame_budget`` with FRAME_SHARE of each frame),
    with the runner-up and why every cheaper option failed, and every candidate on the scene's mesh with
    its step, its error and why it qualifies or not (``candidates``); on a refined mesh when the mesh's own error
    stops every model on the scene's (module docstring). ``models``: the ones to choose from (default
    all: a simulator may have only some). ``command`` re-runs the pick with compare.

    ``haptic_rate``: the simulator also runs a haptic loop at that rate (Hz): the model steps there, and
    a candidate qualifies only if its tool force is within ``force_tol`` (default ``tol``) too, judged
    at the haptic rate (``frame.judgement``). ``truth_budget``: the seconds a sharper truth may take
    (``truth.sharp_reference``'s ``budget_s``)."""
    haptic = check_question(scene, tol, rate, metric, haptic_rate, force_tol)
    dynamic = scene.time.mode == "dynamic"
    # the truth is made sharper only where a candidate it leaves undecided asks for it, and as far as it asks
    ref_opts, truth = sharp_reference(scene, tol, metric, haptic, tighten=False)
    rows = _candidates(scene, metric, rate, use_cache, comm, f"advise {scene.name}", models, ref_opts, haptic)
    need = needed_bar(rows, metric, tol, dynamic)
    if need is not None and not (truth["sharp"] and truth["bar"] <= need):
        log(f"advise {scene.name}: {_undecided_count(rows, metric, tol)} undecided; the truth's bar asked: {need:.3g}")
        sharper_opts, truth = sharp_reference(scene, tol, metric, haptic, target=need, budget_s=truth_budget)
        if sharper_opts != ref_opts:  # judged again against the sharper truth (its runs are cached by it)
            ref_opts = sharper_opts
            rows = _candidates(scene, metric, rate, use_cache, comm, f"advise {scene.name}", models, ref_opts, haptic)
    out, physics = _summary(scene, tol, rate, metric, ref_opts, truth)
    out["haptic"] = haptic
    choice = _pick(rows, metric, tol, dynamic)
    proposal = None
    tried = []
    if choice is None:
        blocked_by_mesh = any(
            r.status == "ok"
            and (mesh := (r.error_budget or {}).get("mesh")) is not None
            and (own := own_part(r)) is not None
            and mesh > tol - own
            for r in rows
        )
        if blocked_by_mesh:
            proposal = propose_mesh(scene, rows, metric, tol, rate, use_cache, ref_opts, truth["bar"], haptic)
            choice, tried = run_plans(scene, proposal, metric, tol, rate, use_cache, ref_opts, haptic)
    out["undecided"] = [line for r in rows for state, line in [judgement(r, metric, tol)] if state == UNDECIDED]
    out["undecided"] += [t["why"] for t in tried if t.get("undecided")]
    ranked = sorted((r for r in rows if r.status == "ok"), key=lambda r: cost(r, dynamic))
    rejected = [verdict(r, metric, tol)[1] for r in rows if not verdict(r, metric, tol)[0]]
    out["proposal"] = proposal_summary(proposal, tried)
    out["candidates"] = [_candidate(r, metric, tol) for r in rows]
    if choice is None:
        why = _why_none(rows, metric, tol, rate, proposal, tried, haptic)
        if out["undecided"]:
            why = f"cannot decide: {truth['why']}; {why}"
        out.update(model=None, integrator=None, dt=None, why=f"{why}; {physics}", rejected=rejected, runner_up=None)
        return out
    out.update(_answer(scene, choice, rows, ranked, rejected, metric, tol, physics, proposal))
    out["command"] = _command(scene, choice, choice.level, haptic["rate"] if haptic else rate)
    return out


def needed_bar(rows: list[Row], metric: str, tol: float, dynamic: bool) -> float | None:
    """The bar on ``metric`` the truth must reach to decide the candidates that matter: those undecided
    (``frame.judgement``) and cheaper than the cheapest that surely qualifies. Each needs a bar under its
    distance to the tolerance; asked for MARGIN of the smallest (its error moves with a sharper truth), at
    most SHARP ``tol``. None when no candidate that matters is undecided: the truth is then sharp enough."""
    states = [(r, judgement(r, metric, tol)[0]) for r in rows]
    cheapest = min((cost(r, dynamic) for r, state in states if state == QUALIFIES), default=math.inf)
    undecided = [r for r, state in states if state == UNDECIDED and cost(r, dynamic) < cheapest]
    if not undecided:
        return None
    gaps = [abs(v - tol) for r in undecided if (v := getattr(r, metric)) is not None]
    return min([SHARP * tol] + [MARGIN * g for g in gaps])


def _undecided_count(rows: list[Row], metric: str, tol: float) -> str:
    n = sum(1 for r in rows if judgement(r, metric, tol)[0] == UNDECIDED)
    return f"{n} candidate{'s' if n != 1 else ''}"


def check_question(scene: Scene, tol: float, rate: float, metric: str, haptic_rate, force_tol) -> dict | None:
    """The question checked against the scene (SceneError in one line), and its haptic part for
    ``frame_budget``: {"rate", "force_tol" (default ``tol``)}, or None without a haptic rate."""
    if metric == "reaction_rel_err" and not scene.problem.held_by_tools:
        raise SceneError(
            f"{scene.path}: --metric reaction_rel_err measures the tool's force, and this scene has no "
            "displacement load (tool); use rel_l2 or surface_rel_l2"
        )
    if not (tol > 0 and rate > 0):
        raise SceneError(f"--tol {tol!r} and --rate {rate!r}: both must be positive")
    if haptic_rate is None:
        return None
    if not scene.problem.held_by_tools:
        raise SceneError(
            f"{scene.path}: --haptic-rate judges the tool's force, and this scene has no displacement "
            "load (tool) for a haptic device to hold"
        )
    force_tol = tol if force_tol is None else force_tol
    if not (haptic_rate > 0 and force_tol > 0):
        raise SceneError(f"--haptic-rate {haptic_rate!r} and --force-tol {force_tol!r}: both must be positive")
    return {"rate": float(haptic_rate), "force_tol": float(force_tol)}


def _answer(scene, choice: Row, rows, ranked, rejected, metric: str, tol: float, physics: str, proposal) -> dict:
    """The advice's fields for its pick ``choice``: the run, its mesh, why, the runner-up and every
    cheaper option with why it failed."""
    dynamic = scene.time.mode == "dynamic"
    level = choice.level
    target = scene.refined(level) if level else scene
    cheaper = [verdict(r, metric, tol)[1] for r in ranked if cost(r, dynamic) < cost(choice, dynamic)]
    cheaper += [verdict(r, metric, tol)[1] for r in rows if r.status != "ok"]  # unstable or unsettled
    if level:
        cheaper = [f"on the scene's mesh: {line}" for line in rejected]
    runner = None if level else _runner_up(ranked, choice, metric, tol)
    why = _why_pick(choice, rows, metric, tol, dynamic, level, physics)
    if level:
        why = (
            f"the mesh's part of the error ({proposal['mesh_part'][0]:.3g}) stops every model on the scene's mesh; "
            f"refined {refined_times(level)} (observed order {proposal['observed_order']:.2f}) it is "
            f"{(choice.error_budget or {}).get('mesh', float('nan')):.3g}, and {why}"
        )
    return dict(
        model=choice.model,
        integrator=choice.integrator,
        dt=choice.dt,
        dt_fraction=choice.fraction,
        value=getattr(choice, metric),
        interval=row_interval(choice, metric),
        error_budget=choice.error_budget,
        step_us=choice.step_us,
        rate_hz=choice.rate_hz,
        frame=choice.frame,
        refine=level,
        mesh=_mesh_summary(target),
        why=why,
        runner_up=None
        if runner is None
        else {
            "model": runner.model,
            "integrator": runner.integrator,
            "dt": runner.dt,
            "value": getattr(runner, metric),
            "frame": runner.frame,
        },
        cheaper_failed=cheaper,
    )


def _candidate(r: Row, metric: str, tol: float) -> dict:
    """One candidate of the scene's mesh, whatever engine ran it: its step, error with the interval the
    reference's bar leaves (``frame.row_interval``) and verdict. ``best_tol``: the smallest tolerance it
    can be said to meet at the rate asked (its interval's top, where its frame holds); with a haptic loop,
    ``best_force_tol`` the same of its tool force at the haptic rate."""
    state, why = judgement(r, metric, tol)
    interval = row_interval(r, metric)
    frame = r.frame or {}
    best = interval[1] if interval and r.ok and frame.get("holds") else None
    haptic = frame.get("haptic") if r.ok else None
    force = row_interval(r, "reaction_rel_err") if haptic and haptic.get("holds") else None
    return {"model": r.model, "integrator": r.integrator, "dt": r.dt, "step_us": r.step_us,
            metric: getattr(r, metric), "interval": interval, "best_tol": best,
            **({"best_force_tol": force[1] if force else None} if haptic else {}),
            "qualifies": state == QUALIFIES, "verdict": state, "why": why}  # fmt: skip


def _runner_up(ranked: list[Row], choice: Row, metric: str, tol: float) -> Row | None:
    """The cheapest qualifying row of another model than the pick's."""
    return next((r for r in ranked if r is not choice and r.model != choice.model and verdict(r, metric, tol)[0]), None)


def _why_none(rows: list[Row], metric: str, tol: float, rate: float, proposal, tried: list, haptic=None) -> str:
    """Why no candidate qualified: the most accurate (in the tool force too, with a haptic loop: the
    question's part that may be the one failing), and what the mesh proposal found."""
    ok = [r for r in rows if r.status == "ok"]
    best = min(ok, key=lambda r: getattr(r, metric), default=None)
    asked = "" if not haptic else f" with its tool force within {haptic['force_tol']:g} at {haptic['rate']:g} Hz"
    why = f"no model meets {metric} <= {tol:g} at {rate:g} Hz{asked} on this mesh"
    if best is not None:
        why += f": the most accurate is {label(best)} with {getattr(best, metric):.3g}"
    forces = [r for r in ok if r.reaction_rel_err is not None]
    if haptic and forces:
        f = min(forces, key=lambda r: r.reaction_rel_err)
        why += f", the most accurate tool force {label(f)}'s with {f.reaction_rel_err:.3g}"
    if proposal is not None and proposal.get("level") is None:
        why += f"; {proposal['why']}"
    elif proposal is not None and tried:
        why += f"; on the mesh refined {refined_times(proposal['level'])} no candidate tried qualified either"
    elif proposal is not None:
        first = proposal["plans"][0]
        why += (
            f"; the mesh's part ({proposal['mesh_part'][0]:.3g}, observed order "
            f"{proposal['observed_order']:.2f}) leaves room for a model's own only on the mesh refined "
            f"{refined_times(first['level'])}, and there no model is predicted to hold {rate:g} Hz within "
            f"memory and time: the first, {label(first['row'])}, "
            + (
                first["predicted"]["why"]
                if not first["predicted"]["holds"]
                else f"would need {first['memory_bytes'] / 1e9:.0f} GB"
                if not first["fits_memory"]
                else "has no measured time to its first answer (its precomputation or settling): unknown, so "
                "it was not run"
                if first["predicted_build_s"] is None
                else f"would take {first['predicted_build_s']:.0f} s to its first answer (its precomputation or "
                f"settling), over {BUILD_LIMIT_S:.0f} s"
            )
        )
    return why


def _why_pick(choice: Row, rows: list[Row], metric: str, tol: float, dynamic: bool, level: int, physics: str) -> str:
    """Why the pick: linear is enough, or what the linear models lack (their error, or the rate)."""
    if spec_of(choice.model).linear:
        why = (
            f"linear is enough: {physics}, and {choice.model} meets {metric} <= {tol:g} ({getattr(choice, metric):.3g})"
        )
    elif level:
        # on the scene's mesh the linear models' totals carry the mesh's part; their own part does not
        own = [own_part(r) for r in rows if r.status == "ok" and spec_of(r.model).linear]
        own = [x for x in own if x is not None]
        why = f"{choice.model} is the first candidate that qualifies there: {physics}" + (
            f"; the linear models' own part of the error (against P1 on the same mesh) is at least {min(own):.3g}"
            if own
            else ""
        )
    else:
        linear = [r for r in rows if r.status == "ok" and spec_of(r.model).linear]
        accurate = [r for r in linear if getattr(r, metric) <= tol]
        if not linear:
            why = f"{choice.model} is the cheapest that qualifies: {physics}"
        elif not accurate:
            why = f"needs a rotation-invariant model: {physics}; the linear models' {metric} is at least " + format(
                min(getattr(r, metric) for r in linear), ".3g"
            )
        elif any(verdict(r, metric, tol)[0] for r in accurate):
            best = min((r for r in accurate if verdict(r, metric, tol)[0]), key=lambda r: cost(r, dynamic))
            why = (
                f"{choice.model} is the cheapest that qualifies; linear is accurate enough too ({physics}): "
                f"{label(best)} meets {metric} {getattr(best, metric):.3g} but costs more"
            )
        else:
            why = f"the linear models accurate enough do not hold the rate ({physics}): " + "; ".join(
                verdict(r, metric, tol)[1] for r in accurate
            )
    return why


def _mesh_summary(scene: Scene) -> dict:
    m = scene.mesh
    return {"level": scene.level, "n_vertices": m.n_vertices, "n_tets": m.n_tets, "mean_edge_m": m.mean_edge()}


def _command(scene: Scene, row: Row, level: int, rate: float) -> str:
    """The compare command that re-runs the pick (with its plug-in engine, where it is one)."""
    builtin = builtin_scenes().get(scene.name) == scene.path
    parts = ["tissuebench compare", scene.name if builtin else str(scene.path)]
    spec = getattr(engine_for(row.model), "spec", None)
    if spec:
        parts.append(f"--engine {spec}")
    parts.append(f"--model {row.model}")
    if row.dt is not None and row.integrator != "quasi-static":  # a quasi-static model updates once a frame
        parts.append(f"--integrator {row.integrator}")
        if row.integrator != "implicit-euler" or scene.time.mode == "dynamic":
            parts.append(f"--dt {row.dt:.6g}")
    # the scene's file may refine its mesh already ([mesh] refine); --mesh-refine adds to it
    in_file = (scene.base or scene).raw.get("mesh", {}).get("refine", 0)
    extra = scene.level + level - in_file
    if extra:
        parts.append(f"--mesh-refine {extra}")
    parts.append(f"--rate {rate:g}")
    return " ".join(parts)


def _best_tolerances(out: dict) -> list[str]:
    """The smallest tolerance each candidate on the scene's mesh that holds the rate can be said to meet
    (the top of its interval), one per model and integrator, smallest first."""
    best, force = {}, {}
    for c in out.get("candidates") or []:
        key = f"{c['model']} ({c['integrator']})"
        if c.get("best_tol") is not None and c["best_tol"] < best.get(key, math.inf):
            best[key] = c["best_tol"]
        if c.get("best_force_tol") is not None and c["best_force_tol"] < force.get(key, math.inf):
            force[key] = c["best_force_tol"]
    head = f"best tolerance at {out['rate']:g} Hz on the scene's mesh: "
    lines = [head + ", ".join(f"{k} {v:.3g}" for k, v in sorted(best.items(), key=lambda kv: kv[1]))]
    if not best:
        lines = [head + "none (no candidate holds the rate with a known interval)"]
    if out.get("haptic"):
        head = f"best tolerance of the tool force at {out['haptic']['rate']:g} Hz on the scene's mesh: "
        said = ", ".join(f"{k} {v:.3g}" for k, v in sorted(force.items(), key=lambda kv: kv[1]))
        lines.append(head + (said or "none (no candidate holds the haptic rate with a known interval)"))
    return lines


def _cheapest_change(out: dict) -> list[str]:
    """Where nothing qualifies: the refined mesh the proposal predicts to meet the tolerance and the rate
    at the fewest refinements (then the smallest predicted error), not one tried there and failed, with
    its predicted error, frame and first answer's wait."""
    prop = out.get("proposal") or {}
    failed = {(t["model"], t["integrator"], t["level"]) for t in prop.get("tried") or [] if not t["ok"]}
    plans = [
        p for p in prop.get("predicted") or []
        if p["holds"] and p["fits_memory"] and (p["model"], p["integrator"], p["level"]) not in failed
    ]  # fmt: skip
    if not plans:
        return []
    p = min(plans, key=lambda p: (p["level"], p["predicted_error"]))
    wait = "" if p["predicted_build_s"] is None else f", its first answer in about {p['predicted_build_s']:.3g} s"
    force = "; its tool force there is not predicted, only measured once run" if out.get("haptic") else ""
    return [
        f"cheapest change: the mesh refined {refined_times(p['level'])} for {p['model']} ({p['integrator']}): "
        f"{out['metric']} predicted {p['predicted_error']:.3g} (at most {p['error_bound']:.3g}); "
        f"{p['predicted_frame']}{wait}{force}"
    ]


def _change_made(out: dict) -> list[str]:
    """Where the pick is on a refined mesh: that refinement as the change to make, with what the mesh
    proposal predicted it would give and cost before it was run, beside what the run measured."""
    if not out.get("refine"):
        return []
    key = (out["model"], out["integrator"], out["refine"])
    plans = (out.get("proposal") or {}).get("predicted") or []
    plan = next((p for p in plans if (p["model"], p["integrator"], p["level"]) == key), None)
    said = f"change: the scene's mesh refined {refined_times(out['refine'])} ({out['mesh']['n_vertices']} vertices)"
    if plan is not None:
        wait = (
            ""
            if plan["predicted_build_s"] is None
            else f", its first answer in about {plan['predicted_build_s']:.3g} s"
        )
        said += (
            f": predicted {out['metric']} {plan['predicted_error']:.3g} (at most {plan['error_bound']:.3g}), "
            f"{plan['predicted_frame']}{wait}"
        )
    return [f"{said}; measured {out['metric']} {out['value']:.3g}, {out['frame']['why']}"]


def format_advice(out: dict) -> str:
    """The advisor's answer as text."""
    lines = []
    prop = out.get("proposal")
    truth = (out.get("reference") or {}).get("why")
    if out.get("model") is None:
        lines.append(out["why"])
        lines += _best_tolerances(out) + _cheapest_change(out)
    else:
        m = out["mesh"]
        mesh = (
            f" on the mesh refined {refined_times(out['refine'])} ({m['n_vertices']} vertices, {m['n_tets']} tetrahedra, "
            f"mean edge {m['mean_edge_m'] * 1e3:.3g} mm)"
            if out["refine"]
            else ""
        )
        dt = "quasi-static" if out["dt"] is None else f"{out['integrator']}, dt = {out['dt']:.3g} s"
        bar = (out.get("reference") or {}).get("bar")
        lines.append(f"{out['model']} ({dt}){mesh}: {out['metric']} {with_bar(out['value'], bar)} <= {out['tol']:g}")
        lines.append(f"frame: {out['frame']['why']} (at most {out['frame_share']:.0%} of each frame)")
        if out["frame"].get("haptic"):
            h = out["frame"]["haptic"]
            lines.append(f"haptic loop at {h['rate']:g} Hz: {h['why']}; tool force within {h['force_tol']:g}")
        lines.append(f"why: {out['why']}")
        if out.get("runner_up"):
            r = out["runner_up"]
            lines.append(f"runner-up: {r['model']} ({out['metric']} {r['value']:.3g}; {r['frame']['why']})")
        lines.append(f"check it: {out['command']}")
        lines += _best_tolerances(out) + _change_made(out)
    if prop and prop.get("mesh_part"):
        lines.append(
            f"mesh: P1's error is {prop['mesh_part'][0]:.3g} on the scene's mesh and {prop['mesh_part'][1]:.3g} refined "
            f"once (observed order {prop['observed_order']:.2f})"
        )
        for t in prop.get("tried", []):
            lines.append(f"  tried on the mesh refined {refined_times(t['level'])}: {t['why']}")
    if truth:
        lines.append(f"truth: {truth}")
    for line in out.get("undecided") or []:
        lines.append(f"  undecided: {line}")
    for line in out.get("cheaper_failed") or out.get("rejected") or []:
        if line not in (out.get("undecided") or []):
            lines.append(f"  rejected: {line}")
    return "\n".join(lines)
