"""What any engine wrote, judged against the scene's reference (``tissuebench judge SCENE RESULT``).

The result's points need not be the scene mesh's: the reference is evaluated at each of them
(``runs.reference.reference_at``). A point outside the body by less than ``outside`` (relative to the
body's size: a tessellation of a curved surface lies a hair off another's) is judged at the nearest
point of the body's surface; one farther is an error naming it. A dynamic result's times must be the
scene's output instants (the reference is known there). The metrics are ``compare``'s: rel_l2 over all
points and times, max_err, and with the result's tetrahedra surface_rel_l2, volume_err and the error
budget's mesh part on the engine's own mesh (``_mesh_part``); the tool force's error when the result
carries it. A step time the user gives (``step_us``) is the engine's own,
labelled so. Before any number, the result is checked against the scene (``consistency``): its units,
its held vertices, its tools' place, its tool force's sign.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from meshes import TetMesh
from meshes.regions import locate
from realtime.errors import InputError
from realtime.geometry import signed_volumes
from verification.engines.foreign import EngineResultError, read_result
from verification.metrics import compute, error_interval, rel_l2
from verification.runs.reference import REFERENCE_DEFAULTS, reference_at
from verification.runs.simulate import output_times
from verification.scene import Scene
from verification.studies.consistency import COINCIDE, check_held_and_tools, check_units, flipped_force

#: What a judgement says of its reference.
REFERENCE_KEYS = ("law", "degree", "refine", "ref_err_estimate", "ref_reaction_err_estimate", "cache_key")
#: How far outside the body (relative to its largest extent) a result's point may lie and be judged at
#: the nearest point of the body's surface.
OUTSIDE = 1e-3
#: Result times within this (relative to the output interval) are the scene's output instants.
TIME_MATCH = 1e-6


def _closest_on_triangles(p: np.ndarray, a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """The closest point (K, 3) of each triangle (a, b, c) (K, 3) to p (K, 3) (Ericson, Real-Time
    Collision Detection, 5.1.5): the region of the triangle's plane p projects into decides."""
    ab, ac, ap = b - a, c - a, p - a
    d1, d2 = np.einsum("ij,ij->i", ab, ap), np.einsum("ij,ij->i", ac, ap)
    bp, cp = p - b, p - c
    d3, d4 = np.einsum("ij,ij->i", ab, bp), np.einsum("ij,ij->i", ac, bp)
    d5, d6 = np.einsum("ij,ij->i", ab, cp), np.einsum("ij,ij->i", ac, cp)
    va, vb, vc = d3 * d6 - d5 * d4, d5 * d2 - d1 * d6, d1 * d4 - d3 * d2
    with np.errstate(divide="ignore", invalid="ignore"):
        denom = 1.0 / (va + vb + vc)
        v, w = vb * denom, vc * denom
        out = a + ab * v[:, None] + ac * w[:, None]  # inside the face
        edges = (
            (vc <= 0) & (d1 >= 0) & (d3 <= 0),  # edge ab
            (vb <= 0) & (d2 >= 0) & (d6 <= 0),  # edge ac
            (va <= 0) & (d4 - d3 >= 0) & (d5 - d6 >= 0),  # edge bc
        )
        t_ab, t_ac = d1 / (d1 - d3), d2 / (d2 - d6)
        t_bc = (d4 - d3) / ((d4 - d3) + (d5 - d6))
    out = np.where(edges[0][:, None], a + ab * t_ab[:, None], out)
    out = np.where(edges[1][:, None], a + ac * t_ac[:, None], out)
    out = np.where(edges[2][:, None], b + (c - b) * t_bc[:, None], out)
    for corner, test in ((a, (d1 <= 0) & (d2 <= 0)), (b, (d3 >= 0) & (d4 <= d3)), (c, (d6 >= 0) & (d5 <= d6))):
        out = np.where(test[:, None], corner, out)
    return out


def onto_body(mesh: TetMesh, points: np.ndarray, outside: float, source: str) -> tuple[np.ndarray, int]:
    """``points`` (K, 3) m with each one outside the body moved to the nearest point of its surface
    (the nearest of its 8 nearest boundary triangles by centroid), and how many moved; EngineResultError
    naming the first point farther than ``outside`` times the body's size."""
    inside = locate(mesh, points) >= 0
    if inside.all():
        return points, 0
    out = np.flatnonzero(~inside)
    tri = mesh.points[mesh.boundary]
    k = min(8, len(tri))
    _, near = cKDTree(tri.mean(axis=1)).query(points[out], k=k)
    near = near.reshape(len(out), k)
    best, dist = np.zeros((len(out), 3)), np.full(len(out), np.inf)
    for j in range(k):
        t = tri[near[:, j]]
        q = _closest_on_triangles(points[out], t[:, 0], t[:, 1], t[:, 2])
        d = np.linalg.norm(q - points[out], axis=1)
        better = d < dist
        best[better], dist[better] = q[better], d[better]
    size = float(np.ptp(mesh.points, axis=0).max())
    far = np.flatnonzero(dist > outside * size)
    if len(far):
        i = out[far[0]]
        raise EngineResultError(
            f"{source}: point {i} {points[i].tolist()} m lies {dist[far[0]]:.3g} m outside the body (more than "
            f"{outside:g} of its {size:.3g} m): is the result in the scene's units (--scale) and frame?"
        )
    moved = points.copy()
    moved[out] = best
    return moved, len(out)


def _own_mesh(points: np.ndarray, tets):
    """The result's tetrahedra, each turned positive (another code's convention may be the other), and
    its surface vertices; (None, None) where it has none or they are degenerate (then no surface or
    volume metric: the displacement is still judged at every point)."""
    if tets is None:
        return None, None
    tets = np.array(tets, dtype=np.int64)
    negative = signed_volumes(points, tets) < 0.0
    tets[negative] = tets[negative][:, [0, 1, 3, 2]]
    try:
        return tets, np.unique(TetMesh(points, tets).boundary)
    except InputError:
        return None, None


def _on_scene_vertices(scene: Scene, points: np.ndarray) -> bool:
    """Whether ``points`` (K, 3) m are the scene mesh's vertices, in order, to COINCIDE of its size: a
    result in mm read with --scale 0.001 has them to round-off, and keeps its surface and volume metrics."""
    own = scene.mesh.points
    size = float(np.ptp(own, axis=0).max())
    return points.shape == own.shape and float(np.abs(points - own).max()) <= COINCIDE * size


def _times(scene: Scene, result) -> np.ndarray:
    """Which of the reference's output instants each result field is at (indices (T,))."""
    if scene.time.mode == "static":
        if len(result.displacement) != 1:
            raise EngineResultError(
                f"{result.source}: a static scene's result is one field, got {len(result.displacement)}"
            )
        return np.zeros(1, dtype=np.int64)
    instants = output_times(scene)
    times = (
        result.times if result.times is not None else (instants if len(result.displacement) == len(instants) else None)
    )
    if times is None:
        raise EngineResultError(
            f"{result.source}: {len(result.displacement)} fields without their times, and the scene has "
            f"{len(instants)} output instants: give the times (a .pvd's timestep, an .npz's times)"
        )
    step = scene.time.output_every
    index = np.rint(np.asarray(times) / step).astype(np.int64)
    bad = np.flatnonzero((np.abs(index * step - times) > TIME_MATCH * step) | (index < 0) | (index >= len(instants)))
    if len(bad):
        raise EngineResultError(
            f"{result.source}: time {times[bad[0]]:.6g} s is not one of the scene's output instants (every "
            f"{step:g} s from 0 to {scene.time.end:g} s), where the reference is known"
        )
    return index


def judge(
    scene: Scene,
    path: str,
    scale: float = 1.0,
    outside: float = OUTSIDE,
    step_us: float | None = None,
    state: int | None = None,
) -> dict:
    """The metrics of the result in ``path`` (``engines.foreign.read_result``, its lengths times
    ``scale``) against the scene's reference, with the reference's own estimate (module docstring).
    A scene with events (a cut) is judged state by state (``state``: its index, 0 the body as meshed,
    against that state's own body as ``tissuebench export`` writes it), or whole (``_staged``)."""
    if scene.events:
        if state is None:
            return _staged(scene, path, scale, step_us)
        scene = _state_scene(scene, state)
    elif state is not None:
        raise EngineResultError(f"{scene.path}: --state {state}: the scene has no events, so it has one state")
    result = read_result(path, scene.mesh.points, scale)
    at, moved = onto_body(scene.mesh, result.points, outside, result.source)
    which = _times(scene, result)
    ref = reference_at(scene, at, **REFERENCE_DEFAULTS)
    ref_u = ref.displacement[which]
    check_units(result.source, result.displacement, ref_u)  # before any number: one line, the likely cause
    check_held_and_tools(scene, result.source, result.points, result.displacement, ref_u, which)
    tools = scene.problem.held_by_tools and result.reaction is not None
    flipped = flipped_force(result.reaction, ref.reaction[which]) if tools else None
    est = ref.meta.get("ref_err_estimate")
    tets = result.tets
    if tets is None and _on_scene_vertices(scene, result.points):
        tets = scene.mesh.tets  # an .npz on the scene mesh's own vertices (scaled: to round-off)
    tets, surface = _own_mesh(result.points, tets)
    if tets is not None:
        reactions = (result.reaction, ref.reaction[which]) if tools else (None, None)
        metrics = compute(result.points, tets, surface, result.displacement, ref_u, *reactions, est)
    else:  # points alone: no surface, no volume
        metrics = {
            "rel_l2": rel_l2(result.displacement, ref_u),
            "surface_rel_l2": None,
            "max_err": float(np.linalg.norm(result.displacement - ref_u, axis=2).max()),
            "volume_err": None,
            "reaction_rel_err": None,
            "ref_err_estimate": est,
        }
        if tools:
            rr = ref.reaction[which]
            metrics["reaction_rel_err"] = float(np.linalg.norm(result.reaction - rr) / max(np.linalg.norm(rr), 1e-300))
        metrics["rel_l2_interval"] = error_interval(metrics["rel_l2"], est)
    budget = _mesh_part(scene, result, tets, which, ref_u) if tets is not None else None
    return {
        "scene": scene.name,
        "result": result.source,
        "scale": scale,
        "error_budget": budget,
        "n_points": len(result.points),
        "n_times": len(which),
        "moved_onto_surface": moved,
        **metrics,
        "engine_step_us": step_us,
        "warnings": [flipped] if flipped else [],
        "reference": {k: ref.meta.get(k) for k in REFERENCE_KEYS},
    }


def _state_scene(scene: Scene, state: int) -> Scene:
    """State ``state`` of a scene with events, or EngineResultError naming the states there are."""
    from verification.events import states

    every = states(scene)
    if not 0 <= state < len(every):
        said = "; ".join(f"{k}: {s.label} (t = {s.time:g} s)" for k, s in enumerate(every))
        raise EngineResultError(f"{scene.path}: --state {state}: the scene's states are {said}")
    return every[state].scene


def _staged(scene: Scene, path: str, scale: float, step_us: float | None) -> dict:
    """A whole result of a scene with events: one field per state, at the union of the states' vertices
    in order (``runs.staged``; what ``tissuebench run --out`` writes), judged as ``compare`` judges a run
    (``runs.compare.run_metrics``). A field's values at union vertices its state does not have (a cut's
    lips before the cut) are taken from the vertex standing for each. Anything else: one line naming
    both ways to give it."""
    from verification.events import states, union_points, union_tets
    from verification.runs.compare import run_metrics
    from verification.runs.reference import reference_result
    from verification.runs.results import Result

    every = states(scene)
    points = union_points(every)
    result = read_result(path, points, scale)
    size = float(np.ptp(points, axis=0).max())
    same = result.points.shape == points.shape and float(np.abs(result.points - points).max()) <= COINCIDE * size
    if len(result.displacement) != len(every) or not same:
        said = ", ".join(f"{k}: {s.label}" for k, s in enumerate(every))
        raise EngineResultError(
            f"{result.source}: {scene.name} has {len(every)} states ({said}); give one field per state at the "
            f"{len(points)} vertices of their union (as `tissuebench run --out` writes), or judge one state's "
            f"result with --state K on that state's mesh (`tissuebench export` writes each state's); got "
            f"{len(result.displacement)} field(s) at {len(result.points)} points"
        )
    u = np.stack([result.displacement[k][s.union[s.of_union]] for k, s in enumerate(every)])
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    check_units(result.source, u, ref.displacement)
    check_held_and_tools(scene, result.source, points, u, ref.displacement, np.arange(len(every)))
    reaction = result.reaction if result.reaction is not None else np.full((len(every), 3), np.nan)
    res = Result(points, union_tets(every), ref.times, u, reaction, {})
    metrics = run_metrics(scene, res, ref)
    return {
        "scene": scene.name,
        "result": result.source,
        "scale": scale,
        "error_budget": None,
        "n_points": len(points),
        "n_times": len(every),
        "moved_onto_surface": 0,
        **metrics,
        "engine_step_us": step_us,
        "warnings": [],
        "reference": {k: ref.meta.get(k) for k in REFERENCE_KEYS},
    }


def _mesh_part(scene: Scene, result, tets: np.ndarray, which: np.ndarray, ref_u: np.ndarray) -> dict:
    """The error budget of a result that carries its tetrahedra (``runs.compare.error_budget``'s parts):
    ``mesh``, the P1 solution of the scene's problem on the engine's own mesh against the reference (what
    any P1 engine on that mesh pays), and ``model``, the result against that P1 solution (what the engine's
    own shortcuts cost), each relative to the reference's norm at the result's points and times. The P1
    solution takes the scene's regions by their rule (a box, a plane, a field), as a refined scene does;
    a region drawn by the scene mesh's own tags selects nothing on another mesh, and the budget says so."""
    import dataclasses

    from reference.errors import ReferenceSolveError
    from verification.runs.reference import P1_OWN_MESH, reference_result
    from verification.scene import check_regions

    if scene.time.mode == "dynamic":
        return {"mesh": None, "model": None, "why": "the mesh part of a dynamic result is not computed"}
    try:
        own = dataclasses.replace(scene, _mesh=TetMesh(result.points, tets))
        check_regions(own, own.mesh)
        p1 = reference_result(own, **P1_OWN_MESH).displacement[which]
    except (InputError, ReferenceSolveError) as exc:
        return {
            "mesh": None,
            "model": None,
            "why": f"no P1 solution on the engine's mesh: {' '.join(str(exc).split())}",
        }
    scale = max(float(np.linalg.norm(ref_u)), 1e-300)
    mesh, model = float(np.linalg.norm(p1 - ref_u)) / scale, float(np.linalg.norm(result.displacement - p1)) / scale
    return {"mesh": mesh, "model": model, "dominant": "mesh" if mesh >= model else "model"}


def format_judgement(out: dict) -> str:
    est = out["reference"].get("ref_err_estimate")
    lines = [f"{out['scene']}: {out['result']} ({out['n_points']} points, {out['n_times']} time(s))"]
    for k in ("rel_l2", "surface_rel_l2", "max_err", "reaction_rel_err", "volume_err"):
        v = out[k]
        lines.append(f"  {k:<18} {'-' if v is None else f'{v:.4g}'}")
    lines.append(f"  {'reference':<18} P{out['reference']['degree']}, estimate {'-' if est is None else f'{est:.2g}'}")
    b = out.get("error_budget") or {}
    if b.get("mesh") is not None:
        lines.append(f"  {'error budget':<18} mesh {b['mesh']:.3g} (P1 on the engine's mesh), model {b['model']:.3g}")
    elif b.get("why"):
        lines.append(f"  {'error budget':<18} {b['why']}")
    if out["moved_onto_surface"]:
        lines.append(f"  {out['moved_onto_surface']} points a hair outside the body were judged at its surface")
    if out["engine_step_us"] is not None:
        lines.append(f"  {'step (engine)':<18} {out['engine_step_us']:.4g} us, as the engine reports it")
    for k, st in enumerate(out.get("states") or ()):
        lines.append(f"  state {k} ({st['label']}): rel_l2 {st['rel_l2']:.4g}")
    lines += [f"  warning: {w}" for w in out.get("warnings") or []]
    return "\n".join(lines)
