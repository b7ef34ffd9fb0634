"""What ``judge`` checks of a result against its scene before scoring it: a result in other units, in
another frame, or exported before the tool moved scores as an engine error of 100 to 1000 times the
truth, and a newcomer read those numbers as their engine's (rel_l2 1134 for a result in millimetres).

- units: displacements a power of ten (100: cm, 1000: mm) times the reference's whose rescaled shape
  matches it: EngineResultError naming the factor and the ``--scale`` that judges it, with the rel_l2
  it then has;
- held: a vertex the scene holds (its fixed components) that moved;
- tools: a tool's vertices away from where the scene puts them at that time (a stale export);
- the tool force's sign: a force that matches far better negated is a warning with both numbers (the
  convention is the tools' total force on the body).

The held and tool checks read the result's points that lie on the scene's vertices (within
``COINCIDE`` of the body's size); a result on a mesh of its own has none there and is not checked so.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from verification.engines.foreign import GAP, POSITION_ROUNDOFF, SHAPE_MATCH, UNITS, EngineResultError
from verification.metrics import rel_l2
from verification.scene import Scene

#: A result's point within this of a scene vertex (relative to the body's size) is that vertex.
COINCIDE = 1e-9
#: A tool force that matches the reference's at most this share of its error when negated has the
#: opposite sign.
FLIPPED = 0.5


def check_units(source: str, u: np.ndarray, ref_u: np.ndarray) -> None:
    """EngineResultError where ``u`` (T, K, 3) is ``ref_u`` (T, K, 3) m in other length units."""
    for k, unit in UNITS.items():
        rescaled = rel_l2(u / 10.0**k, ref_u)
        if rescaled <= SHAPE_MATCH:
            raise EngineResultError(
                f"{source}: its displacements are {10**k} times the reference's (rel_l2 {rel_l2(u, ref_u):.4g}; "
                f"{rescaled:.3g} divided by {10**k}): lengths in {unit}? judge it with --scale {10.0**-k:g}"
            )


def _on_vertices(scene: Scene, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(scene vertices, result points) pairs that coincide (``COINCIDE``)."""
    size = float(np.ptp(scene.mesh.points, axis=0).max())
    d, idx = cKDTree(points).query(scene.mesh.points)
    on = np.flatnonzero(d <= COINCIDE * size)
    return on, idx[on]


def check_held_and_tools(scene: Scene, source: str, points, u, ref_u, which) -> None:
    """EngineResultError where a held component moved or a tool's vertex is away from its place: ``points``
    (K, 3) m and ``u`` (T, K, 3) m the result's, ``ref_u`` (T, K, 3) m the reference at its points, which
    holds the scene's constraints exactly; ``which`` (T,) the output instants."""
    from verification.inputs import scene_loading

    vertices, at = _on_vertices(scene, points)
    if not len(vertices):
        return
    lo = scene_loading(scene)
    tool = np.zeros((scene.mesh.n_vertices, 3), dtype=bool)
    tool[lo.tool_vertex] = lo.tool_mask != 0.0
    held = (lo.free == 0.0) & ~tool
    limit = max(GAP * float(np.abs(ref_u).max()), POSITION_ROUNDOFF * float(np.abs(scene.mesh.points).max()))
    for mask, what in ((held, "held"), (tool, "tool")):
        rows = np.flatnonzero(mask[vertices].any(axis=1))
        if not len(rows):
            continue
        comp = mask[vertices[rows]]  # (R, 3) the constrained components
        gap = np.abs(u[:, at[rows]] - ref_u[:, at[rows]]) * comp  # the reference holds them exactly
        if gap.max() > limit:
            t, r, c = np.unravel_index(int(np.argmax(gap)), gap.shape)
            v = int(vertices[rows[r]])
            raise EngineResultError(
                _moved(scene, source, what, v, "xyz"[c], gap[t, r, c], ref_u[t, at[rows[r]], c], which[t])
            )


def _moved(scene: Scene, source: str, what: str, v: int, axis: str, gap: float, wanted: float, t: int) -> str:
    """The one line of a held component that moved or a tool vertex off its place."""
    where = f"vertex {v} {np.round(scene.mesh.points[v], 6).tolist()}"
    if what == "held":
        return (
            f"{source}: {where} moved {gap:.3g} m in {axis}, which the scene holds at 0: a result in another "
            "frame (shifted or turned), or an engine that held other vertices"
        )
    return (
        f"{source}: the tool's {where} is {gap:.3g} m off in {axis} from where the scene puts it ({wanted:.4g} m"
        f"{'' if scene.time.mode == 'static' else f' at output {t}'}): a result exported before the tool moved "
        "(run the export again), or another tool path"
    )


def flipped_force(reaction: np.ndarray | None, ref_reaction: np.ndarray) -> str | None:
    """A warning where the tool force ``reaction`` (T, 3) N matches ``ref_reaction`` far better negated."""
    if reaction is None:
        return None
    scale = max(float(np.linalg.norm(ref_reaction)), 1e-300)
    err = float(np.linalg.norm(reaction - ref_reaction)) / scale
    flip = float(np.linalg.norm(-reaction - ref_reaction)) / scale
    if flip <= FLIPPED * err:
        return (
            f"its tool force matches the reference's far better with the opposite sign (reaction_rel_err "
            f"{err:.3g}, {flip:.3g} negated): the force judged is the tools' total force on the body"
        )
    return None
