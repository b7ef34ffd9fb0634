"""A hierarchy of nested meshes and the mixed meshes drawn from it (Wu, Downes, Goktekin & Tendick 2001).

Level 0 is the scene's mesh; level k + 1 is level k's red refinement (``geometry.red_refinement``: each
tetrahedron into eight, child i of tetrahedron e being number e + i M_k; the vertices of level k keep
their numbers, and the midpoint of level k's edge j is vertex n_k + j). So one numbering, the finest
level's, serves every level: a vertex's global number never changes.

A mixed mesh is described by which tetrahedra of each level are *refined* (R_k, (M_k,) bool, k < L):
a tetrahedron exists when its parent is refined (level 0 always), and is *active* (a tetrahedron of the
mixed mesh) when it exists and is not refined. ``balance`` keeps neighbours within one level of each
other: a tetrahedron of level k + 1 may be refined only when every tetrahedron of level k that shares a
vertex with its parent is refined. Then the only non-conforming vertices (*hanging*) are midpoints of
an active tetrahedron's edges used by its finer neighbours; each follows the mean of its edge's ends.
Balanced, an end never hangs itself (tested); ``mixed`` orders the hanging vertices coarse first all the
same, so that one pass in that order would expand a displacement through a chain and one pass in the
reverse order fold a force back.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import numpy as np
import scipy.sparse as sp

from .geometry import red_refinement, unique_edges


@dataclass(frozen=True)
class Hierarchy:
    """Nested levels 0 .. L of one mesh.

    points: (n_L, 3) float64 m, every level's vertices (level k's are the first n[k]).
    tets: level k's tetrahedra (M_k, 4) int64 into points, for k = 0 .. L.
    n: (L + 1,) vertices per level.
    edges: level k's unique edges (E_k, 2) int64, for k < L; the midpoint of edges[k][j] is n[k + 1]'s
        vertex n[k] + j.
    incidence: level k's (M_k, n[k]) CSR tetrahedron-vertex incidence, for k < L.
    """

    points: np.ndarray
    tets: tuple
    n: tuple
    edges: tuple
    incidence: tuple

    @property
    def levels(self) -> int:
        return len(self.tets) - 1

    def count(self, k: int) -> int:
        return len(self.tets[k])


def hierarchy(points: np.ndarray, tets: np.ndarray, levels: int) -> Hierarchy:
    """Levels 0 .. ``levels`` of the mesh points (N, 3) m, tets (M, 4) int64."""
    pts, all_tets, n, edges, inc = points, [tets], [len(points)], [], []
    for _ in range(levels):
        t = all_tets[-1]
        edges.append(unique_edges(t))
        inc.append(_incidence(t, len(pts)))
        pts, fine = red_refinement(pts, t)
        all_tets.append(fine)
        n.append(len(pts))
    return Hierarchy(pts, tuple(all_tets), tuple(n), tuple(edges), tuple(inc))


def _incidence(tets: np.ndarray, n: int) -> sp.csr_matrix:
    m = len(tets)
    return sp.csr_matrix((np.ones(4 * m), (np.repeat(np.arange(m), 4), tets.ravel())), shape=(m, n))


def none_refined(h: Hierarchy) -> list[np.ndarray]:
    """R_k for the level-0 mesh alone: nothing refined."""
    return [np.zeros(h.count(k), dtype=bool) for k in range(h.levels)]


def balance(h: Hierarchy, refined: list[np.ndarray]) -> list[np.ndarray]:
    """The smallest refined sets containing ``refined`` (R_k (M_k,) bool, k < L) in which every refined
    tetrahedron exists and neighbours differ by at most one level (module docstring)."""
    out = [r.copy() for r in refined]
    for k in range(h.levels - 1, 0, -1):  # top down: a level's needs add to the coarser one only
        parents = np.zeros(h.count(k - 1), dtype=bool)
        parents[np.flatnonzero(out[k]) % h.count(k - 1)] = True
        inc = h.incidence[k - 1]
        touched = inc.T @ parents.astype(float) > 0.0
        out[k - 1] |= (inc @ touched.astype(float)) > 0.0
    return out


def exists(h: Hierarchy, refined: list[np.ndarray], k: int) -> np.ndarray:
    """(M_k,) bool: the tetrahedra of level k whose parent is refined (all of level 0)."""
    if k == 0:
        return np.ones(h.count(0), dtype=bool)
    return refined[k - 1][np.arange(h.count(k)) % h.count(k - 1)]


def active(h: Hierarchy, refined: list[np.ndarray], k: int) -> np.ndarray:
    """(M_k,) bool: the tetrahedra of level k in the mixed mesh."""
    here = exists(h, refined, k)
    return here if k == h.levels else here & ~refined[k]


class Mixed(NamedTuple):
    """A mixed mesh of a hierarchy, numbered for a model.

    points: (V, 3) float64 m: the level-0 vertices first (all of them, in their order), then the other
        vertices that do not hang (n_model in all), then the H hanging ones, coarse first.
    tets: (K, 4) int64 into points, positively oriented.  level: (K,) int64 each one's level.
    parent: (K,) int64 the level-0 tetrahedron each one is or comes from.
    index: (K,) int64 each one's number in its level.
    hanging: (H, 2) int64 the two vertices (into points) whose mean each hanging vertex follows; an end
        may hang itself, and then comes earlier.
    ends: (n_model - n_0, 2) int64 the two vertices (into points) at the ends of the edge each
        non-level-0 model vertex is the midpoint of.
    ids: (V,) int64 each vertex's global number (the finest level's).
    n_model: the vertices that do not hang.
    """

    points: np.ndarray
    tets: np.ndarray
    level: np.ndarray
    parent: np.ndarray
    index: np.ndarray
    hanging: np.ndarray
    ends: np.ndarray
    ids: np.ndarray
    n_model: int


def edge_of(h: Hierarchy, g: np.ndarray) -> np.ndarray:
    """(G, 2) the global numbers of the ends of the edge whose midpoint is each vertex g (G,) >= n_0."""
    g = np.asarray(g, dtype=np.int64)
    out = np.empty((len(g), 2), dtype=np.int64)
    for k in range(h.levels):
        here = (g >= h.n[k]) & (g < h.n[k + 1])
        out[here] = h.edges[k][g[here] - h.n[k]]
    return out


def mixed(h: Hierarchy, refined: list[np.ndarray]) -> Mixed:
    """The mixed mesh of balanced refined sets (``balance``), numbered as ``Mixed`` says."""
    tets, level, index = [], [], []
    for k in range(h.levels + 1):
        which = np.flatnonzero(active(h, refined, k))
        tets.append(h.tets[k][which])
        level.append(np.full(len(which), k, dtype=np.int64))
        index.append(which)
    tets, level, index = np.concatenate(tets), np.concatenate(level), np.concatenate(index)
    used = np.zeros(len(h.points), dtype=bool)
    used[tets.ravel()] = True
    hang, hang_ends = [], []
    for k in range(h.levels):  # the used midpoints of active edges of level k hang on them, coarse first
        mine = tets[level == k]
        if not len(mine):
            continue
        e = unique_edges(mine)
        n = h.n[k]
        keys = h.edges[k][:, 0] * n + h.edges[k][:, 1]
        mid = h.n[k] + np.searchsorted(keys, e[:, 0] * n + e[:, 1])
        on = used[mid]
        hang.append(mid[on])
        hang_ends.append(e[on])
    hang = np.concatenate(hang) if hang else np.zeros(0, dtype=np.int64)
    hang_ends = np.concatenate(hang_ends) if hang_ends else np.zeros((0, 2), dtype=np.int64)
    free = used.copy()
    free[hang] = False
    free[: h.n[0]] = True
    others = np.flatnonzero(free[h.n[0] :]) + h.n[0]
    ids = np.concatenate([np.arange(h.n[0]), others, hang])
    number = np.full(len(h.points), -1, dtype=np.int64)
    number[ids] = np.arange(len(ids))
    return Mixed(
        points=h.points[ids],
        tets=number[tets],
        level=level,
        parent=index % h.count(0),
        index=index,
        hanging=number[hang_ends],
        ends=number[edge_of(h, others)],
        ids=ids,
        n_model=h.n[0] + len(others),
    )


def scalar_prolongation(hanging: np.ndarray, n_model: int) -> sp.csr_matrix:
    """P (V, n_model): the values of a mixed mesh's vertices from its model vertices' (module docstring).
    The hanging rows are u_h = A u + B u_h, B strictly lower triangular (an end that hangs comes
    earlier) and nilpotent, so P_h = (A + B A + B^2 A + ...) with as many terms as the chains are long."""
    nh = len(hanging)
    rows = np.repeat(np.arange(nh), 2)
    ends = hanging.ravel()
    model = ends < n_model
    A = sp.csr_matrix((np.full(model.sum(), 0.5), (rows[model], ends[model])), shape=(nh, n_model))
    B = sp.csr_matrix((np.full((~model).sum(), 0.5), (rows[~model], ends[~model] - n_model)), shape=(nh, nh))
    Ph, term = A.copy(), A
    while term.nnz:
        term = B @ term
        Ph = Ph + term
    return sp.vstack([sp.identity(n_model, format="csr"), Ph]).tocsr()


def prolongation(hanging: np.ndarray, n_model: int) -> sp.csr_matrix:
    """P (3 V, 3 n_model): u_full = P u, dof 3 i + c."""
    return sp.kron(scalar_prolongation(hanging, n_model), sp.identity(3), format="csr")


def carry_values(h: Hierarchy, old: Mixed, values: np.ndarray, new: Mixed) -> np.ndarray:
    """Per-vertex ``values`` (V_old, ...) of a mixed mesh, expanded to its hanging vertices, on another
    mixed mesh's vertices (V_new, ...): a vertex of both keeps its value, a new midpoint takes the mean
    of its edge's ends (themselves carried first: coarse levels first)."""
    known = np.zeros(len(h.points), dtype=bool)
    full = np.zeros((len(h.points), *values.shape[1:]))
    full[old.ids] = values
    known[old.ids] = True
    need = np.sort(new.ids[~known[new.ids]])  # global numbers grow with the level
    stack = list(need)
    while stack:
        g = stack[-1]
        a, b = edge_of(h, np.array([g]))[0]
        missing = [x for x in (a, b) if not known[x]]
        if missing:
            stack.extend(missing)
            continue
        stack.pop()
        if not known[g]:
            full[g] = 0.5 * (full[a] + full[b])
            known[g] = True
    return full[new.ids]
