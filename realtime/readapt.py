"""adaptive-tm re-adapted as the deformation moves (Wu, Downes, Goktekin & Tendick 2001).

Every so often a run asks each active tetrahedron of its mixed mesh (``hierarchy``) for an indicator
of the error it makes, from the state it has reached; those at ``threshold`` times the largest or
above are refined one level (up to the hierarchy's finest), and a refined tetrahedron whose eight
children all fall below ``COARSEN`` times that bar is merged back, unless that would move its
midpoints (``MERGE_JUMP``); the levels are then balanced
(``hierarchy.balance``). The indicators, by the criteria Wu et al. name (one function each, chosen
through ``INDICATORS``):

- ``displacement``: the largest displacement of the tetrahedron's vertices, m;
- ``stress``: the Frobenius norm of its second Piola-Kirchhoff stress S = lambda tr(E) I + 2 mu E
  (Saint Venant-Kirchhoff, E the Green-Lagrange strain), Pa: stress concentration;
- ``estimator``: Zienkiewicz and Zhu's (1987) a-posteriori estimate, the distance of its stress from
  the stress recovered at its vertices (the volume-weighted mean of the stresses of the tetrahedra
  around each), in the energy-like norm |S_e - S*_e| sqrt(V_e), Pa m^(3/2).

The state moves to the new mesh (``carried``): a vertex of both keeps its displacement and velocity,
a new midpoint takes the mean of its edge's ends, and a vertex that now hangs follows its edge.
"""

from __future__ import annotations

import numpy as np

from .geometry import shape_gradients, signed_volumes
from .hierarchy import balance, carry_values, exists
from .tensor_mass import LOCAL_EDGES

#: A refined tetrahedron is merged back when all its children's indicators fall below this fraction of
#: the refining bar: the band between keeps a tetrahedron near the bar from flipping at every check.
COARSEN = 0.5
#: ... and when merging moves none of its edges' midpoints by more than this fraction of its shortest
#: edge (a strain-sized jump): a merge under a large local deformation would snap the midpoints onto the
#: merged tetrahedron's linear field at once, which can turn the small tetrahedra around them inside out.
MERGE_JUMP = 1e-3


def _green_and_stress(points, tets, lam, mu, u):
    """The Green-Lagrange strain E (K, 3, 3) and the StVK stress S (K, 3, 3) Pa of each tetrahedron."""
    g, _ = shape_gradients(points, tets)
    H = np.einsum("eai,eac->eic", u[tets], g)  # grad u
    E = 0.5 * (H + H.transpose(0, 2, 1) + np.einsum("eki,ekj->eij", H, H))
    tr = np.trace(E, axis1=1, axis2=2)
    S = lam[:, None, None] * tr[:, None, None] * np.eye(3) + 2.0 * mu[:, None, None] * E
    return E, S


def displacement_indicator(points, tets, lam, mu, u) -> np.ndarray:
    """(K,) the largest |u| (m) at each tetrahedron's vertices. points (V, 3) m, tets (K, 4), lam and
    mu (K,) Pa, u (V, 3) m: the mixed mesh with its hanging vertices."""
    return np.linalg.norm(u[tets], axis=2).max(axis=1)


def stress_indicator(points, tets, lam, mu, u) -> np.ndarray:
    """(K,) |S|_F (Pa) of each tetrahedron (arguments as ``displacement_indicator``)."""
    _, S = _green_and_stress(points, tets, lam, mu, u)
    return np.sqrt(np.einsum("eij,eij->e", S, S))


def estimator_indicator(points, tets, lam, mu, u) -> np.ndarray:
    """(K,) Zienkiewicz-Zhu's |S_e - S*_e| sqrt(V_e) (arguments as ``displacement_indicator``): S* is
    each vertex's volume-weighted mean stress, averaged over the tetrahedron's four vertices."""
    _, S = _green_and_stress(points, tets, lam, mu, u)
    vol = np.abs(signed_volumes(points, tets))
    acc = np.zeros((len(points), 3, 3))
    weight = np.zeros(len(points))
    for a in range(4):
        np.add.at(acc, tets[:, a], vol[:, None, None] * S)
        np.add.at(weight, tets[:, a], vol)
    recovered = acc / np.maximum(weight, 1e-300)[:, None, None]
    diff = S - recovered[tets].mean(axis=1)
    return np.sqrt(np.einsum("eij,eij->e", diff, diff) * vol)


#: The criteria by name.
INDICATORS = {
    "displacement": displacement_indicator,
    "stress": stress_indicator,
    "estimator": estimator_indicator,
}


def indicator(plan, materials, u_full: np.ndarray, criterion: str) -> np.ndarray:
    """(K,) the ``criterion``'s indicator of each tetrahedron of ``plan`` (an AdaptivePlan) at u_full
    (V, 3) m (with the hanging vertices), ``materials`` the level-0 Materials."""
    mats = materials.subset(plan.parent)
    return INDICATORS[criterion](plan.points, plan.tets, mats.per_tet("lam"), mats.per_tet("mu"), u_full)


def adapted_sets(plan, eta: np.ndarray, threshold: float, u_full: np.ndarray) -> list | None:
    """The refined sets after one re-adaptation by indicators ``eta`` (K,) of ``plan``'s tetrahedra
    (module docstring), balanced; None when nothing changes. ``u_full`` (V, 3) m, the displacement with
    its hanging vertices: a merge may not move a vertex (``merge_jumps``)."""
    h, sets = plan.hierarchy, [s.copy() for s in plan.sets]
    top = float(eta.max()) if len(eta) else 0.0
    if not top > 0.0:
        return None
    bar = threshold * top
    for k in range(h.levels):  # refine the active tetrahedra of level k over the bar
        mine = (plan.level == k) & (eta >= bar)
        sets[k][plan.index[mine]] = True
    for k in range(h.levels):  # merge back the refined ones whose eight children are active and below
        child = plan.level == k + 1
        parent = plan.index[child] % h.count(k)
        calm = np.zeros(h.count(k), dtype=np.int64)
        np.add.at(calm, parent, (eta[child] < COARSEN * bar).astype(np.int64))
        merge = (calm == 8) & sets[k]  # a child refined itself is not active: not counted
        merge[merge] = merge_jumps(plan, k, np.flatnonzero(merge), u_full) <= MERGE_JUMP
        sets[k][merge] = False
    for k in range(1, h.levels):
        sets[k] &= exists(h, sets, k)
    sets = balance(h, sets)
    if all(np.array_equal(a, b) for a, b in zip(sets, plan.sets, strict=True)):
        return None
    return sets


def merge_jumps(plan, k: int, which: np.ndarray, u_full: np.ndarray) -> np.ndarray:
    """(W,) how far merging each refined tetrahedron ``which`` of level k would move a vertex: the
    largest |u_m - (u_a + u_b) / 2| over its edges' midpoints m (their displacement against the merged
    tetrahedron's linear field), over its shortest edge."""
    h = plan.hierarchy
    tets = h.tets[k][which]
    where = np.full(len(h.points), -1, dtype=np.int64)
    where[plan.ids] = np.arange(len(plan.ids))
    n = h.n[k]
    keys = h.edges[k][:, 0] * n + h.edges[k][:, 1]
    out = np.zeros(len(which))
    shortest = np.full(len(which), np.inf)
    for a, b in LOCAL_EDGES:
        lo, hi = np.minimum(tets[:, a], tets[:, b]), np.maximum(tets[:, a], tets[:, b])
        mid = where[n + np.searchsorted(keys, lo * n + hi)]
        ua, ub = u_full[where[tets[:, a]]], u_full[where[tets[:, b]]]
        out = np.maximum(out, np.linalg.norm(u_full[mid] - 0.5 * (ua + ub), axis=1))
        shortest = np.minimum(shortest, np.linalg.norm(h.points[tets[:, a]] - h.points[tets[:, b]], axis=1))
    return out / shortest


def carried(old_plan, new_plan, values: np.ndarray, expand) -> np.ndarray:
    """A model's per-vertex ``values`` (n_model_old, 3) on the new plan's model vertices
    (n_model_new, 3): expanded to the old hanging vertices by ``expand`` (values, hanging), then carried
    (``hierarchy.carry_values``)."""
    full = expand(values, old_plan.hanging)
    return carry_values(old_plan.hierarchy, old_plan, full, new_plan)[: new_plan.n_model]
