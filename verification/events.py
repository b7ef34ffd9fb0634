"""Cuts and sutures as scene events (docs/data-flow.md): a static scene in states.

A scene's ``[[event]]`` tables cut the body along a plane, or suture what a cut opened, at a time. A
static scene with events is a sequence of states: the body as meshed (time 0), then the body after the
events of each later time, each an equilibrium of its own under the scene's loads. Every state is a
scene of its own (``State.scene``): the mesh as it is then, the regions carried to it, so that the
reference, the built-in models and any other engine solve each state as they solve any static scene.

A cut separates the mesh along the interior triangles between tetrahedra whose centroids lie on
opposite sides of its plane, those whose centroid lies in the event's box (the part of the plane cut):
on a mesh with faces in the plane the cut is the plane; elsewhere it follows the faces nearest to it
(a staircase). Each vertex on the cut splits into one copy per side (``realtime.topology.slit_tets``:
the copies appended after the mesh's vertices). A suture joins the lips back: each copy whose original
lies in its box (every copy, without one) becomes its original again.

The states' vertices differ, so results are kept on the union of every state's vertices: the scene's
mesh's, then each cut's copies in order (``union_points``). Where a copy is not a vertex of a state
(before its cut, after its suture) its value is its original's, the same material point of a whole body.
A copy is in a region exactly when its original is. Not modelled: contact between the lips (a cut
that closes under the load lets them pass through each other) and events in a dynamic scene.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from meshes import TetMesh
from meshes.regions import VertexRegion
from realtime.geometry import TET_FACES
from realtime.topology import slit_tets

#: The event kinds of a scene file.
EVENT_KINDS = ("cut", "suture")
#: How far a state's vertex is moved toward the centroid of one of its tetrahedra before a field
#: solved on that state's mesh is evaluated there, as a fraction of the way: a vertex on a cut lies on
#: both lips, and the nudge picks its own side's cell. The value moves by this fraction of the
#: tetrahedron's displacement variation, far below any error bar.
NUDGE = 1e-6


@dataclass(frozen=True)
class Event:
    """One [[event]] of a scene: at ``time`` (s), a cut of the plane through ``point`` (3,) m with
    normal ``normal`` (3,), or a suture; ``box`` ((3,), (3,)) m bounds the part of the plane cut (the
    cut faces' centroids) or the originals sutured, None for all."""

    time: float
    kind: str
    point: tuple | None = None
    normal: tuple | None = None
    box: tuple | None = None

    def describe(self) -> str:
        where = "" if self.box is None else f" within {[list(c) for c in self.box]}"
        if self.kind == "cut":
            return f"cut at t = {self.time:g} s along the plane through {list(self.point)} normal {list(self.normal)}{where}"
        return f"suture at t = {self.time:g} s{where}"


@dataclass(frozen=True)
class State:
    """The body between two event times.

    time: s, when it begins (0 for the body as meshed).  label: the events that made it.
    scene: the Scene of this state (its mesh and regions; no events).
    of_union: (U,) int64, the vertex of this state's mesh standing for each union vertex.
    union: (N_s,) int64, the union vertex of each of this state's vertices.
    """

    time: float
    label: str
    scene: object
    of_union: np.ndarray
    union: np.ndarray


def _inside(x: np.ndarray, box) -> np.ndarray:
    if box is None:
        return np.ones(len(x), dtype=bool)
    lo, hi = np.asarray(box[0]), np.asarray(box[1])
    return np.all((x >= lo) & (x <= hi), axis=1)


def cut_faces(points: np.ndarray, tets: np.ndarray, event: Event) -> np.ndarray:
    """The interior triangles (F, 3) int64 a cut separates: shared by two of ``tets`` (M, 4) whose
    centroids lie on opposite sides of the event's plane, with their centroid in its box. ``points``
    (N, 3) m."""
    n = len(points)
    side = (points[tets].mean(axis=1) - np.asarray(event.point)) @ np.asarray(event.normal) > 0.0
    faces = np.sort(tets[:, TET_FACES].reshape(-1, 3), axis=1)
    key = (faces[:, 0] * n + faces[:, 1]) * n + faces[:, 2]
    order = np.argsort(key, kind="stable")
    k, owner = key[order], np.repeat(np.arange(len(tets)), 4)[order]
    pair = np.flatnonzero(k[1:] == k[:-1])
    across = pair[side[owner[pair]] != side[owner[pair + 1]]]
    chosen = faces[order[across]]
    return chosen[_inside(points[chosen].mean(axis=1), event.box)]


def _state_scene(scene, mesh: TetMesh, origin: np.ndarray):
    """``scene`` (level 0 or refined, no events) on a state's ``mesh``, whose vertex i stands for the
    scene mesh's vertex origin[i]: each region holds a vertex when it holds its origin."""
    chosen = np.zeros(scene.mesh.n_vertices, dtype=bool)

    def carry(region):
        chosen[:] = False
        chosen[region.vertices(scene.mesh)] = True
        return VertexRegion(tuple(np.flatnonzero(chosen[origin]).tolist()))

    p = scene.problem
    problem = dataclasses.replace(
        p,
        fixed=tuple(dataclasses.replace(f, region=carry(f.region)) for f in p.fixed),
        loads=tuple(
            dataclasses.replace(ld, region=carry(ld.region)) if hasattr(ld, "region") else ld for ld in p.loads
        ),
    )
    return dataclasses.replace(scene, problem=problem, _mesh=mesh, events=(), base=None, level=0)


def _mesh(base: TetMesh, points, tets, origin, label: str) -> TetMesh:
    tags = {name: np.flatnonzero(np.isin(origin, v)) for name, v in base.vertex_tags.items()}
    return TetMesh(
        points,
        tets,
        vertex_tags=tags,
        cell_tags=base.cell_tags,
        cell_fields=base.cell_fields,
        source=f"{base.source}, {label}",
        notes=base.notes,
    )


def states(scene) -> list[State]:
    """The states of a static scene with events (module docstring), the first the body as meshed."""
    from verification.scene import SceneError

    mesh = scene.mesh
    # a refined scene's states are made on its own mesh, their base the base scene's states (its base has
    # no cut: the cut is in the states)
    whole = dataclasses.replace(scene, events=(), **({"base": None, "level": 0} if scene.level else {}))
    points, tets = mesh.points, mesh.tets
    union = np.arange(mesh.n_vertices)  # the union vertex of each current vertex
    parent = np.arange(mesh.n_vertices)  # the union vertex each union vertex was split from (itself)
    made = [(0.0, "as meshed", points, tets, union)]
    for t in sorted({e.time for e in scene.events}):
        done = []
        for e in (e for e in scene.events if e.time == t):
            what = f"{scene.path}: event: the {e.describe()}"
            if e.kind == "cut":
                faces = cut_faces(points, tets, e)
                if not len(faces):
                    raise SceneError(f"{what} meets no interior face of the mesh")
                changed, rows, pairs = slit_tets(tets, len(points), faces, what)
                tets = tets.copy()
                tets[changed] = rows
                points = np.concatenate([points, points[pairs[:, 0]]])
                parent = np.concatenate([parent, union[pairs[:, 0]]])
                union = np.concatenate([union, len(parent) - len(pairs) + np.arange(len(pairs))])
            else:
                join = (parent[union] != union) & _inside(points, e.box)
                if not join.any():
                    raise SceneError(f"{what} finds no lips of an earlier cut")
                tets = _stand_in(parent, union[~join])[union[tets]]
                points, union = points[~join], union[~join]
            done.append(e.describe())
        made.append((t, "; ".join(done), points, tets, union))
    origin = parent.copy()
    while np.any(parent[origin] != origin):
        origin = parent[origin]
    out = []
    for t, label, points, tets, union in made:
        same = len(points) == mesh.n_vertices and np.array_equal(tets, mesh.tets)  # sutured whole again
        state = whole if same else _state_scene(whole, _mesh(mesh, points, tets, origin[union], label), origin[union])
        out.append(State(t, label, state, _stand_in(parent, union), union))
    if scene.level:  # each state poses its base state's problem: its truth is that one's, evaluated here
        bases = states(scene.base)
        out = [dataclasses.replace(s, scene=dataclasses.replace(s.scene, base=b.scene, level=scene.level))
               for s, b in zip(out, bases, strict=True)]  # fmt: skip
    return out


def _stand_in(parent: np.ndarray, union: np.ndarray) -> np.ndarray:
    """(U,) the current vertex standing for each union vertex, when ``union`` (N_s,) are the current
    ones: itself where it is current, else (before its cut, after its suture) what it was split from,
    followed back until a current vertex."""
    where = np.full(len(parent), -1, dtype=np.int64)
    where[union] = np.arange(len(union))
    up = np.arange(len(parent))
    while np.any(where[up] < 0):
        missing = where[up] < 0
        up[missing] = parent[up[missing]]
    return where[up]


def union_points(parts: list[State]) -> np.ndarray:
    """(U, 3) m: the rest positions of the union of the vertices of ``parts`` (a scene's states: the
    scene mesh's, then each cut's copies in order)."""
    points = np.zeros((len(parts[0].of_union), 3))
    for s in parts:
        points[s.union] = s.scene.mesh.points
    return points


def union_tets(parts: list[State]) -> np.ndarray:
    """(M, 4) int64: the tetrahedra of the state with the most vertices (the body cut open), numbered on
    the union of ``parts``' vertices (``union_points``): the mesh every state's field is drawn and
    measured on (before a cut its lips coincide)."""
    cut = max(parts, key=lambda s: s.scene.mesh.n_vertices)
    return cut.union[cut.scene.mesh.tets]


def nudged(state: State) -> np.ndarray:
    """(N_s, 3) m: each vertex of the state's mesh moved NUDGE of the way toward the centroid of one of
    its tetrahedra, where a field solved on that mesh is evaluated for it (module docstring)."""
    mesh = state.scene.mesh
    owner = np.zeros(mesh.n_vertices, dtype=np.int64)
    owner[mesh.tets.ravel()] = np.repeat(np.arange(mesh.n_tets), 4)
    centroid = mesh.points[mesh.tets[owner]].mean(axis=1)
    return mesh.points + NUDGE * (centroid - mesh.points)
