"""The advisor's mesh proposal (docs/verification.md, "Mesh"): when the mesh's own error stops
every model on the scene's mesh, the refinement the observed order of that error says is needed, and
the candidates run there, cheapest predicted first, until one meets the tolerance and the rate."""

from __future__ import annotations

import math

import numpy as np

from verification.engines import spec_of
from verification.progress import Bar
from verification.runs.reference import P1_OWN_MESH, REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row
from verification.runs.store import compare_or_unsettled
from verification.scene import Scene
from verification.studies.frame import (
    FRAME_SHARE,
    QUALIFIES,
    UNDECIDED,
    available_memory,
    frame_budget,
    judgement,
    memory_bytes,
    predict,
)

#: The longest wait for a candidate's first answer that a proposal may ask a user for, s, and that the
#: advisor itself makes to try it: a quasi-static model's precomputation, or a time-stepping model's
#: settling on a static scene (predicted, ``frame.predict``'s time to answer). stvk-tm on SOFA's liver
#: refined twice (95 552 tetrahedra) had settled for 205 s, a third of its way, when it was stopped.
BUILD_LIMIT_S = 120.0
#: Growth of a quasi-static model's build per refinement: 4 times the surface dofs (right-hand sides),
#: each solved with a sparse factor of 8^(4/3) = 16 times the entries (nested dissection in 3D).
BUILD_GROWTH = 64.0
#: The most uniform refinements the advisor proposes (each multiplies the tetrahedra by 8).
MAX_LEVEL = 3
#: Refined candidates the advisor runs before it gives up on a level.
MAX_TRIALS = 4
#: A refined candidate is run when its predicted work fits in OPTIMISM x FRAME_SHARE of a frame: the
#: prediction scales a noisy level-0 timing by 8^L (on the cantilever, 11.4 to 12.6 us per step at
#: level 0 between two runs, 639 to 734 us measured at level 2).
OPTIMISM = 1.5
#: P1's order of convergence of vertex displacements in L2, the most the advisor extrapolates with:
#: a pre-asymptotic observed order above it would promise a coarser mesh than the one needed.
P1_ORDER = 2.0


def propose_mesh(
    scene: Scene,
    rows: list[Row],
    metric: str,
    tol: float,
    rate: float,
    use_cache: bool,
    ref_opts=None,
    bar=None,
    haptic=None,
) -> dict:
    """The refinement level that the observed convergence of the mesh's part predicts is needed, and
    the candidates to run there, cheapest predicted first (see the module docstring, step 5), judged
    against the reference of ``ref_opts`` (default REFERENCE_DEFAULTS), whose ``bar`` a candidate's
    error must leave room for."""
    budgets = [r.error_budget for r in rows if r.status == "ok" and (r.error_budget or {}).get("mesh")]
    if not budgets:
        return {"level": None, "why": "no error budget (no P1 solution on this mesh): no mesh size can be proposed"}
    e0 = budgets[0]["mesh"]
    truth = reference_result(scene, **(ref_opts or REFERENCE_DEFAULTS))
    scale = float(np.linalg.norm(truth.displacement))
    e1 = float(np.linalg.norm(_refined_p1_here(scene) - truth.displacement) / scale)
    observed = math.log2(e0 / e1) if e1 > 0 else math.inf
    out = {"mesh_part": [e0, e1], "observed_order": observed}
    if not observed > 0.5:
        out.update(
            level=None,
            why=f"the mesh's part does not fall with refinement ({e0:.3g} -> {e1:.3g}, order {observed:.2f}): "
            "a finer mesh would not help",
        )
        return out
    order = min(observed, P1_ORDER)
    dynamic = scene.time.mode == "dynamic"
    if bar is None:
        out.update(level=None, why="the reference's bar is unknown: no refined candidate's verdict could be decided")
        return out
    plans = _plans(scene, rows, e1, order, tol - bar, rate, haptic)
    if not plans:
        out.update(
            level=None,
            why=f"even {MAX_LEVEL} refinements (8^{MAX_LEVEL} times the tetrahedra) leave every model above "
            f"{metric} {tol:g}: the mesh's part would be {e1 / 2.0 ** (order * (MAX_LEVEL - 1)):.3g} at order "
            f"{order:.2f} and the models' own parts are at least "
            f"{_smallest_model_part(rows)}",
        )
        return out
    plans.sort(
        key=lambda p: (
            not (p["predicted"]["holds"] and p["fits_memory"] and p["builds_in_time"] is True),
            not (p["hopeful"] and p["fits_memory"] and p["builds_in_time"] is True),
            p["level"],
            _known(p["predicted"]["work_us"] if dynamic else p["predicted"]["time_to_answer_s"]),
        )
    )
    out.update(level=plans[0]["level"], order=order, plans=plans)
    return out


def _refined_p1_here(scene: Scene) -> np.ndarray:
    """P1 on the scene's mesh refined once, at the scene's vertices (T, N, 3) m: the refined mesh's first
    vertices are the base's (nested). A scene with events is taken state by state, the refined state's P1
    evaluated at the base state's vertices (nudged into their own side's cells: a cut's lips are no
    nested vertices), and stitched as its truth is (``runs.staged``)."""
    fine = scene.refined(1)
    if not scene.events:
        return reference_result(fine, **P1_OWN_MESH).displacement[:, : scene.mesh.n_vertices]
    from verification.events import nudged, states
    from verification.runs.reference import reference_at
    from verification.runs.staged import stitched

    parts = [
        (s, reference_at(f.scene, nudged(s), **P1_OWN_MESH)) for s, f in zip(states(scene), states(fine), strict=True)
    ]
    return stitched(scene, parts).displacement


def _plans(scene: Scene, rows: list[Row], e1: float, order: float, tol: float, rate: float, haptic=None) -> list[dict]:
    """For each candidate row, the levels to try it on: from where its predicted total (the mesh's part
    at ``order`` from ``e1`` on one refinement, and its own) likely meets ``tol`` (the tolerance less the
    reference's bar) up to where it surely does, with its predicted frame budget (at the haptic rate
    too, where ``haptic`` asks), memory and build time."""
    dynamic = scene.time.mode == "dynamic"
    memory = available_memory()
    n, surface = scene.mesh.n_vertices, len(scene.mesh.surface_vertices)
    plans = []
    for r in rows:
        # a model on a mesh of its own: its error's mesh part is not P1's on the scene's mesh (adaptive-tm
        # refined twice more would be a third level, at 64 times the cost, for a part the model already cut)
        if r.status != "ok" or spec_of(r.model).own_mesh:
            continue
        own = own_part(r)
        if own is None:  # its own part unknown: no prediction of its total, so no level to plan for it
            continue
        for level in range(1, MAX_LEVEL + 1):
            mesh_part = e1 / 2.0 ** (order * (level - 1))
            # the parts' errors are distances between solutions: the total is at most their sum and, when
            # they are unrelated (as P1's locking and a model's linearity are), close to their
            # root-sum-square. A row is tried from the level where the latter meets the tolerance up to the
            # one where the former does; the run on the level decides.
            likely, bound = math.hypot(mesh_part, own), mesh_part + own
            if likely > tol:
                continue
            predicted = predict(r, level, dynamic, rate)
            # a level-0 timing scaled by 8^L carries its noise 8^L-fold: a candidate a little over the
            # budget by prediction is still worth a run, which decides
            hopeful = predict(r, level, dynamic, rate, share=FRAME_SHARE * OPTIMISM)["holds"]
            if haptic:
                at = predict(r, level, dynamic, haptic["rate"])
                predicted = predicted if not predicted["holds"] or at["holds"] else at
                hopeful = hopeful and predict(r, level, dynamic, haptic["rate"], share=FRAME_SHARE * OPTIMISM)["holds"]
            need = memory_bytes(r.model, n * 8**level, surface * 4**level)
            # None where the run did not measure it: unknown, never "builds in time"
            if r.integrator == "quasi-static":
                build = None if r.build_s is None else r.build_s * BUILD_GROWTH**level
            elif dynamic:  # a dynamic run starts at once and takes its own time, a frame at a time
                build = 0.0
            else:  # a static scene's settling from rest
                build = predicted.get("time_to_answer_s")
            plans.append(
                {
                    "row": r,
                    "level": level,
                    "predicted_error": likely,
                    "error_bound": bound,
                    "predicted_mesh_part": mesh_part,
                    "predicted": predicted,
                    "hopeful": hopeful,
                    "memory_bytes": need,
                    "fits_memory": need <= memory,
                    "predicted_build_s": build,
                    "builds_in_time": None if build is None else build <= BUILD_LIMIT_S,
                }
            )
            if bound <= tol:
                break
    return plans


def _smallest_model_part(rows: list[Row]) -> str:
    """The smallest known model part among the rows that ran, or "unknown" where none is known."""
    known = [
        r.error_budget["model"] for r in rows if r.status == "ok" and (r.error_budget or {}).get("model") is not None
    ]
    return f"{min(known):.3g}" if known else "unknown"


def _known(value: float | None) -> float:
    """A predicted cost for sorting: an unknown one after every known one."""
    return math.inf if value is None else value


def own_part(r: Row) -> float | None:
    """A row's own part of its error: its model part and its time part, which a static scene or a
    quasi-static model does not have (None there: no step to err by). None when the model part is
    unknown (no P1 solution on the mesh): never read as zero."""
    b = r.error_budget or {}
    if b.get("model") is None:
        return None
    return b["model"] + (b.get("time") or 0.0)


def run_plans(
    scene: Scene, proposal: dict, metric: str, tol: float, rate: float, use_cache: bool, ref_opts=None, haptic=None
):
    """Run the proposal's candidates on their refined meshes, cheapest predicted first, the ones
    predicted to hold the rate and fit in memory only, at most MAX_TRIALS; the first that meets both is
    the answer (judged against the reference of ``ref_opts``). Returns (row or None, what was tried)."""
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    if not proposal or proposal.get("level") is None:
        return None, []
    dynamic = scene.time.mode == "dynamic"
    # a plan whose time to its first answer is unknown is not run: nothing bounds its wait
    plans = [p for p in proposal["plans"] if p["hopeful"] and p["fits_memory"] and p["builds_in_time"] is True]
    # two level-0 steps of one model become one refined run (its fraction clamped): each is run once, and
    # MAX_TRIALS counts distinct runs
    runs, seen = [], set()
    for p in plans:
        r0 = p["row"]
        fraction = None if r0.dt is None or r0.integrator == "implicit-euler" else min(r0.fraction or 0.9, 0.9)
        dt = r0.dt if dynamic and r0.integrator == "implicit-euler" else None  # its steps a frame, kept
        if (key := (r0.model, r0.integrator, p["level"], fraction, dt)) not in seen:
            seen.add(key)
            runs.append((p, fraction, dt))
    runs = runs[:MAX_TRIALS]
    tried = []
    progress = Bar(len(runs), f"advise {scene.name} refined")
    for p, fraction, dt in runs:
        r0 = p["row"]
        level_scene = scene.refined(p["level"])
        row = compare_or_unsettled(
            level_scene, r0.model, r0.integrator, dt, fraction, ref_opts=ref_opts, use_cache=use_cache
        )
        progress.step(f"{r0.model} level {p['level']}")
        row = row.replace(frame=frame_budget(row, rate, dynamic, haptic=haptic) if row.ok else None, level=p["level"])
        state, line = judgement(row, metric, tol)
        ok = state == QUALIFIES
        tried.append(
            {"level": p["level"], "model": row.model, "integrator": row.integrator, "ok": ok,
             "undecided": state == UNDECIDED, "why": line}
        )  # fmt: skip
        if ok:
            return row, tried
    return None, tried


def proposal_summary(proposal: dict | None, tried: list) -> dict | None:
    if proposal is None:
        return None
    out = {k: v for k, v in proposal.items() if k != "plans"}
    out["tried"] = tried
    out["predicted"] = [
        {
            "model": p["row"].model,
            "integrator": p["row"].integrator,
            "level": p["level"],
            "predicted_error": p["predicted_error"],
            "error_bound": p["error_bound"],
            "predicted_frame": p["predicted"]["why"],
            "holds": p["predicted"]["holds"],
            "hopeful": p["hopeful"],
            "memory_gb": p["memory_bytes"] / 1e9,
            "fits_memory": p["fits_memory"],
            "predicted_build_s": p["predicted_build_s"],
            "builds_in_time": p["builds_in_time"],
        }
        for p in proposal.get("plans", [])
    ]
    return out


def refined_times(level: int) -> str:
    return {1: "once", 2: "twice"}.get(level, f"{level} times")
