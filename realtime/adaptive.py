"""Adaptive resolution (Wu, Downes, Goktekin & Tendick 2001): fine where the body deforms, coarse elsewhere.

The hierarchy (``realtime.hierarchy``) holds ``levels`` nested red refinements of the scene's mesh
(each tetrahedron into eight; the coarser vertices come first). Built alone (a static scene), the model
refines by a linear predictor, the static linear response of the scene's mesh to the model's loads with
the tools at their final place: a level-0 tetrahedron whose strain norm |eps|_F reaches ``threshold``
(k + 1) times the largest is refined down to level k + 1, and the levels are balanced (neighbours
within one level). The threshold is the knob: 0 refines everything (the StVK tensor-mass of the mesh
refined ``levels`` times), above 1 nothing (that of the scene's mesh). On a dynamic scene the run
re-adapts as the deformation moves (``realtime.readapt``, driven by ``verification.engines.readapting``).

Where a refined tetrahedron meets a kept one, the midpoint of their common edge belongs to the fine
side only: it *hangs*, and its displacement is the mean of its edge's ends, u_m = (u_a + u_b) / 2, so
that the field stays continuous (the usual constraint of non-conforming refinement). The model's
vertices are the scene's (first, in their order) and the midpoints that do not hang; the force kernel
expands u to the hanging midpoints, runs the StVK element kernel on the mixed mesh, and gives each
hanging midpoint's force half to each end (the transpose of the expansion, so the force is still minus
the gradient of the energy). Masses and loads fold the same way.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import scipy.sparse.linalg as spla

from .blocks import BLOCK, HOT, JIT, BlockData, block_data
from .contact import below
from .errors import InputError
from .geometry import shape_gradients
from .hierarchy import (
    Hierarchy,
    Mixed,
    balance,
    exists,
    hierarchy,
    mixed,
    none_refined,
    prolongation,
    scalar_prolongation,
)
from .material import Material, Materials
from .model import Loading, Model, lumped_masses, prepare_mesh
from .stvk import stvk_energy, stvk_force
from .tensor_mass import TensorMass

#: The default threshold: refine the tetrahedra strained at least 30% as much as the most strained.
DEFAULT_THRESHOLD = 0.3
#: The most levels of refinement (8^levels times the tetrahedra where all are refined).
MAX_LEVELS = 3


_PLAN_FIELDS = [*Mixed.__annotations__.items(), ("refined", "np.ndarray"), ("strain", "np.ndarray")]


class AdaptivePlan(NamedTuple("_Plan", [*_PLAN_FIELDS, ("hierarchy", "Hierarchy"), ("sets", "tuple")])):
    """The mixed mesh of an adaptive model: a ``hierarchy.Mixed``'s fields (points, tets, level,
    parent, index, hanging, ends, ids, n_model; see there), then what chose it.

    refined: (M,) bool which level-0 tetrahedra are refined.
    strain: (M,) float64 the predictor's strain norm of each level-0 tetrahedron.
    hierarchy: the levels it is drawn from (``hierarchy.Hierarchy``).
    sets: the refined sets R_k, (M_k,) bool for each level k below the finest.
    """

    __slots__ = ()


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


def adaptive_plan(
    points, tets, material, loading: Loading, threshold: float = DEFAULT_THRESHOLD, levels: int = 1
) -> AdaptivePlan:
    """The mixed mesh for ``threshold`` (module docstring) over ``levels`` refinements: points (N, 3) m
    and tets (M, 4) the level-0 mesh, ``loading`` on it. A level-0 tetrahedron whose predictor strain
    reaches threshold (k + 1) times the largest is refined down to level k + 1 (a graded rule: the
    most strained finest), then the levels are balanced (``hierarchy.balance``)."""
    if not (isinstance(threshold, (int, float)) and threshold >= 0.0):
        raise InputError(f"adaptive-tm: threshold = {threshold!r}: a number >= 0 (a fraction of the largest strain)")
    _check_levels(levels)
    points, tets = prepare_mesh(points, tets)
    strain = predictor_strain(points, tets, material, loading)
    top = float(strain.max()) if len(strain) else 0.0
    h = hierarchy(points, tets, levels)
    sets = []
    for k in range(levels):
        bar = threshold * (k + 1)
        deep = strain >= bar * top if top > 0.0 else np.full(len(tets), threshold == 0.0)
        sets.append(deep[np.arange(h.count(k)) % len(tets)] & exists(h, sets, k))
    return plan_of(h, balance(h, sets), strain)


def coarse_plan(points, tets, levels: int) -> AdaptivePlan:
    """The plan of the level-0 mesh alone (points (N, 3) m, tets (M, 4)) in a hierarchy ``levels``
    deep: where a run that re-adapts starts."""
    _check_levels(levels)
    points, tets = prepare_mesh(points, tets)
    h = hierarchy(points, tets, levels)
    return plan_of(h, none_refined(h))


def _check_levels(levels) -> None:
    if not (isinstance(levels, int) and not isinstance(levels, bool) and 1 <= levels <= MAX_LEVELS):
        raise InputError(f"adaptive-tm: levels = {levels!r}: a whole number from 1 to {MAX_LEVELS}")


def plan_of(h: Hierarchy, sets: list, strain: np.ndarray | None = None) -> AdaptivePlan:
    """The AdaptivePlan of balanced refined sets of ``h``."""
    m = mixed(h, sets)
    strain = np.zeros(h.count(0)) if strain is None else strain
    return AdaptivePlan(*m, refined=sets[0].copy(), strain=strain, hierarchy=h, sets=tuple(s.copy() for s in sets))


def fold(values: np.ndarray, hanging: np.ndarray, n_model: int) -> np.ndarray:
    """P^T values: per-vertex values (V, ...) of the mixed mesh onto the model's vertices (n_model, ...),
    each hanging vertex's half to each end of its edge (``hierarchy.scalar_prolongation``)."""
    P = scalar_prolongation(hanging, n_model)
    return (P.T @ values.reshape(len(values), -1)).reshape(n_model, *values.shape[1:])


def expand(u: np.ndarray, hanging: np.ndarray) -> np.ndarray:
    """P u: the model's displacements (n_model, 3) and the hanging vertices' values, (V, 3)."""
    return scalar_prolongation(hanging, len(u)) @ u


def carried_loading(plan: AdaptivePlan, loading: Loading) -> Loading:
    """The coarse ``loading`` on the model's vertices: a midpoint is held (per component) or driven by a
    tool when both ends of its edge are (the rule the reference applies to its refined meshes; the ends
    of a finer midpoint are coarser vertices, carried first); the external forces stay on the coarse
    vertices (the coarse load vector: its total force and moment, not its finer distribution;
    verification passes the mixed mesh's own loading instead)."""
    n = len(loading.free)
    free = np.concatenate([loading.free, np.zeros((plan.n_model - n, 3))])
    tool = {int(v): (int(loading.tool_id[k]), loading.tool_mask[k]) for k, v in enumerate(loading.tool_vertex)}
    for j, (a, b) in enumerate(plan.ends):  # in the model's order: the ends come first
        free[n + j] = np.maximum(free[a], free[b])
        ta, tb = tool.get(int(a)), tool.get(int(b))
        if ta is not None and tb is not None and ta[0] == tb[0] and np.minimum(ta[1], tb[1]).any():
            tool[n + j] = (ta[0], np.minimum(ta[1], tb[1]))
    driven = np.array(sorted(tool), dtype=np.int64)
    fext = np.concatenate([loading.external_force, np.zeros((plan.n_model - n, 3))])
    return Loading(
        **{
            **loading.__dict__,
            "free": free,
            "external_force": fext,
            "tool_vertex": driven,
            "tool_mask": np.array([tool[int(v)][1] for v in driven], dtype=np.float64).reshape(-1, 3),
            "tool_id": np.array([tool[int(v)][0] for v in driven], dtype=np.int64),
        }
    )


@nb.njit(**HOT)
def adaptive_force(data, scratch, u, f):
    """The StVK force of the mixed mesh on the model's vertices: P^T f_stvk(P u) (module docstring).
    Hanging vertices are expanded in order and folded back in reverse order (an end may hang itself).

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
            uf[nm + h, c] = 0.5 * (uf[a, c] + uf[b, c])
    stvk_force(inner, (W,), uf, ff)
    for h in range(hanging.shape[0] - 1, -1, -1):
        a, b = hanging[h, 0], hanging[h, 1]
        for c in range(3):
            ff[a, c] += 0.5 * ff[nm + h, c]
            ff[b, c] += 0.5 * ff[nm + h, c]
    f[:] = ff[:nm]


@nb.njit(**JIT)
def adaptive_energy(data, u):
    """The StVK energy of the mixed mesh at P u, J."""
    inner, hanging = data
    nm = u.shape[0]
    uf = np.empty((nm + hanging.shape[0], 3))
    uf[:nm] = u
    for h in range(hanging.shape[0]):
        for c in range(3):
            uf[nm + h, c] = 0.5 * (uf[hanging[h, 0], c] + uf[hanging[h, 1], c])
    return stvk_energy(inner, uf)


def adaptive_model(
    name: str,
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    plan: AdaptivePlan | None = None,
    mixed_loading: Loading | None = None,
    levels: int = 1,
) -> Model:
    """The model ``name``: StVK tensor-mass on the mesh refined where the predictor's strain reaches
    ``threshold`` times its largest (module docstring). ``points``, ``tets``, ``material`` and ``loading`` describe the coarse
    mesh; ``plan`` (from ``adaptive_plan``) and ``mixed_loading`` (a Loading on ``plan.points``, as
    exact a load vector as the caller has) may be given, else they are made here (``carried_loading``).
    The Model's vertices are the coarse ones first, then the midpoints that do not hang; its ``tets``
    are the mixed mesh's tetrahedra with no hanging vertex. The first N vertices are the scene's."""
    points, tets = prepare_mesh(points, tets)
    loading = loading if loading is not None else Loading.free_body(len(points))
    loading.check(len(points))
    if plan is None:
        plan = adaptive_plan(points, tets, material, loading, threshold, levels)
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
                "contacts": below(mixed_loading.contacts, nm),
            }
        )
    n_full = len(plan.points)

    def scratch():
        return (np.zeros((n_full, 3)), np.zeros((n_full, 3)), np.zeros(9 * BLOCK))

    def rest(model):
        P = prolongation(hanging, nm)
        return (P.T @ TensorMass(plan.points, plan.tets, mats).matrix() @ P).tocsr()

    def bound(model):
        """Gershgorin on M^-1 K at rest: max_i sum_j |K_ij| / m_i, an upper bound on omega_max^2."""
        K = abs(rest(model))
        return float(np.max(np.asarray(K.sum(axis=1)).ravel() / np.repeat(model.mass, 3)))

    whole = np.all(plan.tets < nm, axis=1)  # the tetrahedra with no hanging vertex
    return Model(
        name=name,
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
