"""Runs and references of a scene with events (``verification.events``): one static solve per state,
kept on the union of the states' vertices (docs/data-flow.md).

Each state is a static scene of its own, so it is solved, cached and settled as any other: the
reference by ``reference_result`` on the state's mesh, evaluated at its vertices nudged into their own
side's tetrahedra (``events.nudged``: a vertex on a cut lies on both lips); a model through the engine
seam (``run_model``), so that every engine, built-in or not, runs a cut. The states' results become one
Result whose output times are the states' times and whose vertices are the union's.
"""

from __future__ import annotations

import numpy as np

from ..events import State, nudged, states, union_points, union_tets
from ..progress import log
from .results import Result

#: The meta of a state's run or reference kept in the staged result's ``states``.
STATE_KEYS = (
    "ref_err_estimate",
    "ref_reaction_err_estimate",
    "cache_key",
    "wall_s",
    "step_us",
    "dt",
    "dt_crit",
    "build_s",
    "settle_ms",
)


def stitched(scene, parts: list[tuple[State, Result]]) -> Result:
    """One Result on the union of the states' vertices from each state's Result (T = 1 each): times the
    states' times, displacement (S, U, 3) m, reaction (S, 3) N. Its meta is the last state's, with
    ``states`` (each one's time, label, vertices and STATE_KEYS), the largest of the states' error bars
    and step times (the conservative ones), and the sum of their solves' wall times."""
    points = union_points([s for s, _ in parts])
    tets = union_tets([s for s, _ in parts])
    times = np.array([s.time for s, _ in parts])
    u = np.stack([r.displacement[0][s.of_union] for s, r in parts])
    reaction = np.stack([r.reaction[0] for s, r in parts])
    meta = dict(parts[-1][1].meta)
    meta["states"] = [
        {
            "time": s.time,
            "label": s.label,
            "n_vertices": s.scene.mesh.n_vertices,
            **{k: r.meta.get(k) for k in STATE_KEYS if k in r.meta},
        }
        for s, r in parts
    ]
    for key in ("ref_err_estimate", "ref_reaction_err_estimate", "step_us", "step_us_max"):
        values = [r.meta.get(key) for _, r in parts]
        if all(v is not None for v in values) and values:
            meta[key] = max(values)
    if meta.get("step_us"):
        meta["rate_hz"] = 1e6 / meta["step_us"]
        meta["realtime_factor"] = None if meta.get("dt") is None else meta["dt"] / (meta["step_us"] * 1e-6)
    if all("wall_s" in r.meta for _, r in parts):  # a state solved once counts once (the sutured body)
        meta["wall_s"] = sum({r.meta.get("cache_key", k): r.meta["wall_s"] for k, (_, r) in enumerate(parts)}.values())
    meta.update(scene=scene.name, scene_sha256=scene.sha256(), mesh_sha256=scene.mesh.sha256(), mode="events")
    return Result(points, tets, times, u, reaction, meta)


def staged_reference(scene, at) -> Result:
    """The reference of every state at its nudged vertices: ``at(state_scene, points)`` returns it
    (``runs.reference.reference_at`` with the options asked)."""
    parts, every = [], states(scene)
    for k, s in enumerate(every):
        log(f"reference: {scene.name}, state {k + 1} of {len(every)}: {s.label}")
        parts.append((s, at(s.scene, nudged(s))))
    return stitched(scene, parts)


def staged_run(scene, run) -> Result:
    """A model's run on every state: ``run(state_scene)`` returns its Result (a static run)."""
    parts, every = [], states(scene)
    for k, s in enumerate(every):
        log(f"run: {scene.name}, state {k + 1} of {len(every)}: {s.label}")
        parts.append((s, run(s.scene)))
    return stitched(scene, parts)
