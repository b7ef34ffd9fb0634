"""Adaptive resolution (Wu, Downes, Goktekin & Tendick 2001): fine where the body deforms, coarse elsewhere.

The hierarchy has two levels of one body: the scene's mesh and its red refinement (each tetrahedron
into eight, ``geometry.red_refinement``; the coarse vertices come first). A linear predictor, the
static linear response of the coarse mesh to the model's loads with the tools at their final place,
gives each coarse tetrahedron its strain; the tetrahedra whose strain norm |eps|_F reaches
``threshold`` times the largest are replaced by their eight children, the others kept whole. The
threshold is the model's knob: 0 refines everything (the StVK tensor-mass of the refined mesh), above 1
nothing (that of the coarse mesh).

Where a refined tetrahedron meets a kept one, the midpoint of their common edge belongs to the fine
side only: it *hangs*, and its displacement is the mean of its edge's ends, u_m = (u_a + u_b) / 2, so
that the field stays continuous (the usual constraint of non-conforming refinement). The model's
vertices are the coarse ones (first, in their order) and the midpoints that do not hang; the force
kernel expands u to the hanging midpoints, runs the StVK element kernel on the mixed mesh, and gives
each hanging midpoint's force half to each end (the transpose of the expansion, so the force is still
minus the gradient of the energy). Masses and loads fold the same way.

What this does not do (yet): re-adapt during a run. The refinement is decided once, from the predictor,
when the model is built; Wu et al. refine and coarsen as the deformation moves.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .blocks import BLOCK, HOT, JIT, BlockData, block_data
from .errors import InputError
from .geometry import red_refinement, shape_gradients, unique_edges
from .material import Material, Materials
from .model import Loading, Model, lumped_masses, prepare_mesh
from .stvk import stvk_energy, stvk_force
from .tensor_mass import TensorMass

#: The default threshold: refine the tetrahedra strained at least 30% as much as the most strained.
DEFAULT_THRESHOLD = 0.3


class AdaptivePlan(NamedTuple):
    """The mixed mesh of an adaptive model.

    points: (V, 3) float64 m, the model's vertices (coarse ones first, then the midpoints that do not
        hang), then the H hanging midpoints; n_model = V - H.
    tets: (K, 4) int64 into points, positively oriented: the kept coarse tetrahedra, then the children.
    parent: (K,) int64 the coarse tetrahedron each one is or comes from.
    hanging: (H, 2) int64 the two model vertices whose mean each hanging midpoint follows.
    ends: (n_model - N, 2) int64 the two coarse vertices at the ends of each non-hanging midpoint's edge.
    refined: (M,) bool which coarse tetrahedra were refined.
    strain: (M,) float64 the predictor's strain norm of each coarse tetrahedron.
    """

    points: np.ndarray
    tets: np.ndarray
    parent: np.ndarray
    hanging: np.ndarray
    ends: np.ndarray
    n_model: int
    refined: np.ndarray
    strain: np.ndarray


class AdaptiveData(NamedTuple):
    """adaptive_force's data: inner (BlockData) the StVK kernel's on the mixed mesh, hanging (H, 2) int64."""

    inner: BlockData
    hanging: np.ndarray


def predictor_strain(points, tets, material, loading: Loading) -> np.ndarray:
    """|eps|_F (M,) of each tetrahedron under the static linear response to ``loading`` with the tools
    at their final place (the predictor): K_ff u_f = f_f - K_fc u_c on the coarse mesh. Zeros for a body
    that nothing holds (it has no static response; only threshold 0 then refines)."""
    n = len(points)
    K = TensorMass(points, tets, material).matrix().tocsr()
    u = np.zeros(3 * n)
    held = (loading.free.reshape(-1) == 0.0).copy()
    if len(loading.tool_vertex):
        from .model import _tool_displacements

        disp = np.zeros((len(loading.tool_vertex), 3))
        _tool_displacements(points, loading.tools_tuple(), np.inf, disp)
        dofs = (3 * loading.tool_vertex[:, None] + np.arange(3))[loading.tool_mask != 0.0]
        u[dofs] = disp[loading.tool_mask != 0.0]
        held[dofs] = True
    if not held.any():  # a free body has no static response: no strain to refine by
        return np.zeros(len(tets))
    free = np.flatnonzero(~held)
    rhs = loading.external_force.reshape(-1)[free] - K[free][:, np.flatnonzero(held)] @ u[held]
    if len(free):
        u[free] = spla.spsolve(K[free][:, free].tocsc(), rhs)
    g, _ = shape_gradients(points, tets)
    H = np.einsum("eai,eac->eic", u.reshape(-1, 3)[tets], g)  # grad u (M, 3, 3)
    eps = 0.5 * (H + H.transpose(0, 2, 1))
    return np.sqrt(np.einsum("eij,eij->e", eps, eps))


def adaptive_plan(points, tets, material, loading: Loading, threshold: float = DEFAULT_THRESHOLD) -> AdaptivePlan:
    """The mixed mesh for ``threshold`` (module docstring): points (N, 3) m and tets (M, 4) the coarse
    mesh, ``loading`` on it."""
    if not (isinstance(threshold, (int, float)) and threshold >= 0.0):
        raise InputError(f"adaptive-tm: threshold = {threshold!r}: a number >= 0 (a fraction of the largest strain)")
    points, tets = prepare_mesh(points, tets)
    strain = predictor_strain(points, tets, material, loading)
    top = float(strain.max()) if len(strain) else 0.0
    refined = strain >= threshold * top if top > 0.0 else np.full(len(tets), threshold == 0.0)
    n, m = len(points), len(tets)
    fine_points, fine_tets = red_refinement(points, tets)
    children = fine_tets[np.tile(refined, 8)]
    mixed = np.concatenate([tets[~refined], children])
    parent = np.concatenate([np.flatnonzero(~refined), np.tile(np.arange(m), 8)[np.tile(refined, 8)]])
    edges = unique_edges(tets)  # midpoint n + k sits on edges[k]
    used = np.unique(mixed)
    mids = used[used >= n]
    kept_edges = unique_edges(tets[~refined]) if (~refined).any() else np.zeros((0, 2), dtype=np.int64)
    kept_keys = kept_edges[:, 0] * n + kept_edges[:, 1]
    ends = edges[mids - n]
    hangs = np.isin(ends[:, 0] * n + ends[:, 1], kept_keys)
    order = np.concatenate([np.arange(n), mids[~hangs], mids[hangs]])
    number = np.full(len(fine_points), -1, dtype=np.int64)
    number[order] = np.arange(len(order))
    n_model = n + int(np.count_nonzero(~hangs))
    return AdaptivePlan(
        points=fine_points[order],
        tets=number[mixed],
        parent=parent,
        hanging=ends[hangs].astype(np.int64),
        ends=ends[~hangs].astype(np.int64),
        n_model=n_model,
        refined=refined,
        strain=strain,
    )


def fold(values: np.ndarray, hanging: np.ndarray, n_model: int) -> np.ndarray:
    """P^T values: per-vertex values (V, ...) of the mixed mesh onto the model's vertices (n_model, ...),
    each hanging midpoint's half to each end of its edge."""
    out = values[:n_model].copy()
    h = values[n_model:]
    np.add.at(out, hanging[:, 0], 0.5 * h)
    np.add.at(out, hanging[:, 1], 0.5 * h)
    return out


def expand(u: np.ndarray, hanging: np.ndarray) -> np.ndarray:
    """P u: the model's displacements (n_model, 3) and the hanging midpoints' means, (V, 3)."""
    return np.concatenate([u, 0.5 * (u[hanging[:, 0]] + u[hanging[:, 1]])])


def carried_loading(plan: AdaptivePlan, loading: Loading) -> Loading:
    """The coarse ``loading`` on the model's vertices: a midpoint is held (per component) or driven by a
    tool when both ends of its edge are (the rule the reference applies to its refined meshes); the
    external forces stay on the coarse vertices (the coarse load vector: its total force and moment,
    not its finer distribution; verification passes the mixed mesh's own loading instead)."""
    n = len(loading.free)
    ends = plan.ends
    free = np.concatenate([loading.free, np.maximum(loading.free[ends[:, 0]], loading.free[ends[:, 1]])])
    tv, tm, tid = [loading.tool_vertex], [loading.tool_mask], [loading.tool_id]
    where = {int(v): k for k, v in enumerate(loading.tool_vertex)}
    for j, (a, b) in enumerate(ends):
        ka, kb = where.get(int(a)), where.get(int(b))
        if ka is None or kb is None or loading.tool_id[ka] != loading.tool_id[kb]:
            continue
        mask = np.minimum(loading.tool_mask[ka], loading.tool_mask[kb])
        if mask.any():
            tv.append(np.array([n + j]))
            tm.append(mask[None, :])
            tid.append(np.array([loading.tool_id[ka]]))
    fext = np.concatenate([loading.external_force, np.zeros((plan.n_model - n, 3))])
    return Loading(
        **{
            **loading.__dict__,
            "free": free,
            "external_force": fext,
            "tool_vertex": np.concatenate(tv).astype(np.int64),
            "tool_mask": np.concatenate(tm).astype(np.float64),
            "tool_id": np.concatenate(tid).astype(np.int64),
        }
    )


@nb.njit(**HOT)
def adaptive_force(data, scratch, u, f):
    """The StVK force of the mixed mesh on the model's vertices: P^T f_stvk(P u) (module docstring).

    data: AdaptiveData.   scratch: (uf (V, 3), ff (V, 3), W (9 BLOCK,)) float64.
    u: (n_model, 3) float64 displacement, m.   f: (n_model, 3) float64 force, N (overwritten).
    """
    inner, hanging = data
    uf, ff, W = scratch
    nm = u.shape[0]
    uf[:nm] = u
    for h in range(hanging.shape[0]):
        a, b = hanging[h, 0], hanging[h, 1]
        for c in range(3):
            uf[nm + h, c] = 0.5 * (u[a, c] + u[b, c])
    stvk_force(inner, (W,), uf, ff)
    f[:] = ff[:nm]
    for h in range(hanging.shape[0]):
        a, b = hanging[h, 0], hanging[h, 1]
        for c in range(3):
            f[a, c] += 0.5 * ff[nm + h, c]
            f[b, c] += 0.5 * ff[nm + h, c]


@nb.njit(**JIT)
def adaptive_energy(data, u):
    """The StVK energy of the mixed mesh at P u, J."""
    inner, hanging = data
    nm = u.shape[0]
    uf = np.empty((nm + hanging.shape[0], 3))
    uf[:nm] = u
    for h in range(hanging.shape[0]):
        for c in range(3):
            uf[nm + h, c] = 0.5 * (u[hanging[h, 0], c] + u[hanging[h, 1], c])
    return stvk_energy(inner, uf)


def build_adaptive_tm(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    plan: AdaptivePlan | None = None,
    mixed_loading: Loading | None = None,
) -> Model:
    """StVK tensor-mass on the mesh refined where the predictor's strain reaches ``threshold`` times its
    largest (module docstring). ``points``, ``tets``, ``material`` and ``loading`` describe the coarse
    mesh; ``plan`` (from ``adaptive_plan``) and ``mixed_loading`` (a Loading on ``plan.points``, as
    exact a load vector as the caller has) may be given, else they are made here (``carried_loading``).
    The Model's vertices are the coarse ones first, then the midpoints that do not hang; its ``tets``
    are the mixed mesh's tetrahedra with no hanging vertex. The first N vertices are the scene's."""
    points, tets = prepare_mesh(points, tets)
    loading = loading if loading is not None else Loading.free_body(len(points))
    loading.check(len(points))
    if plan is None:
        plan = adaptive_plan(points, tets, material, loading, threshold)
    mats = Materials.of(material, len(tets)).subset(plan.parent)
    nm, hanging = plan.n_model, plan.hanging
    btets, geo, prm = block_data(plan.points, plan.tets, mats)
    data = AdaptiveData(BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_)), hanging)
    mass = fold(lumped_masses(plan.points, plan.tets, mats.per_tet("density")), hanging, nm)
    if mixed_loading is None:
        model_loading = carried_loading(plan, loading)
    else:
        mixed_loading.check(len(plan.points))
        keep = mixed_loading.tool_vertex < nm  # a hanging midpoint follows its edge: the ends carry the tool
        model_loading = Loading(
            **{
                **mixed_loading.__dict__,
                "free": mixed_loading.free[:nm].copy(),
                "external_force": fold(mixed_loading.external_force, hanging, nm),
                "tool_vertex": mixed_loading.tool_vertex[keep],
                "tool_mask": mixed_loading.tool_mask[keep],
                "tool_id": mixed_loading.tool_id[keep],
            }
        )
    n_full = len(plan.points)

    def scratch():
        return (np.zeros((n_full, 3)), np.zeros((n_full, 3)), np.zeros(9 * BLOCK))

    def rest(model):
        P = _prolongation(hanging, nm, n_full)
        return (P.T @ TensorMass(plan.points, plan.tets, mats).matrix() @ P).tocsr()

    def bound(model):
        """Gershgorin on M^-1 K at rest: max_i sum_j |K_ij| / m_i, an upper bound on omega_max^2."""
        K = abs(rest(model))
        return float(np.max(np.asarray(K.sum(axis=1)).ravel() / np.repeat(model.mass, 3)))

    whole = np.all(plan.tets < nm, axis=1)  # the tetrahedra with no hanging vertex
    return Model(
        name="adaptive-tm",
        points=plan.points[:nm],
        tets=plan.tets[whole],
        material=mats.subset(whole),
        mass=mass,
        loading=model_loading,
        force_kernel=adaptive_force,
        energy_kernel=adaptive_energy,
        data=data,
        new_scratch=scratch,
        rest_stiffness_of=rest,
        eigenvalue_bound_of=bound,
        linear=False,
        extra={"plan": plan, "observed": len(points)},
    )


def _prolongation(hanging: np.ndarray, n_model: int, n_full: int) -> sp.csr_matrix:
    """P (3 V, 3 n_model): u_full = P u, dof 3 i + c."""
    rows = [np.arange(3 * n_model)]
    cols = [np.arange(3 * n_model)]
    vals = [np.ones(3 * n_model)]
    for end in (0, 1):
        h = np.arange(len(hanging))
        r = (3 * (n_model + h)[:, None] + np.arange(3)).ravel()
        c = (3 * hanging[:, end][:, None] + np.arange(3)).ravel()
        rows.append(r)
        cols.append(c)
        vals.append(np.full(len(r), 0.5))
    return sp.csr_matrix(
        (np.concatenate(vals), (np.concatenate(rows), np.concatenate(cols))), shape=(3 * n_full, 3 * n_model)
    )
