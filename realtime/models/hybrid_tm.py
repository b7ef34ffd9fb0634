"""hybrid-tm: linear tensor-mass, StVK where the body moved (Picinbono et al. 2003, section 5)."""

from __future__ import annotations

import numpy as np

from ..blocks import block_data
from ..errors import InputError, is_real
from ..geometry import unique_edges
from ..hybrid import RELEASE, HybridData, hybrid_energy, hybrid_force, hybrid_scratch
from ..material import Material, Materials
from ..model import Loading, Model, prepare_mesh
from ..tensor_mass import TensorMass
from .base import ModelSpec, assemble

NAME = "hybrid-tm"


def build(
    points, tets, material: Material | Materials, loading: Loading | None = None, threshold: float | None = None
) -> Model:
    """Linear tensor-mass, StVK on the tetrahedra with a vertex displaced more than ``threshold`` (m); a
    vertex returns to linear within hybrid.RELEASE times it (hysteresis: the force does not switch back
    and forth at the threshold, and damped dynamics settles).

    Default threshold: 10% of the mean edge length, the small-displacement limit of linear elasticity
    quoted by Delingette & Ayache (2004).
    """
    points, tets = prepare_mesh(points, tets)
    tm = TensorMass(points, tets, material)
    if threshold is None:
        e = unique_edges(tets)
        threshold = 0.1 * float(np.linalg.norm(points[e[:, 0]] - points[e[:, 1]], axis=1).mean())
    if not (is_real(threshold) and threshold >= 0.0):
        raise InputError(f"{NAME}: threshold = {threshold!r} must be a number >= 0 m")
    btets, geo, prm = block_data(points, tets, material)
    data = HybridData(tm.kernel_data(), btets, geo, prm, np.array([float(threshold), RELEASE * float(threshold)]))
    n_points, n_padded = len(points), len(btets)
    return assemble(
        NAME,
        points,
        tets,
        material,
        loading,
        hybrid_force,
        hybrid_energy,
        data,
        False,
        lambda: hybrid_scratch(n_points, n_padded),
        tensors=tm,
        threshold=float(threshold),
    )


def nonlinear_fraction(tets: np.ndarray, u: np.ndarray, threshold: float) -> float:
    """Fraction of the tetrahedra (M, 4) int64 that hybrid-tm treats as StVK at displacement u (N, 3) m
    from a fresh start: those with a vertex displaced more than ``threshold`` m (``hybrid_force``'s rule;
    a run that came there may keep more, those within the hysteresis band of hybrid.RELEASE)."""
    moved = np.linalg.norm(u, axis=1) > threshold
    return float(moved[tets].any(axis=1).mean())


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="linear tensor-mass, St Venant-Kirchhoff on the tetrahedra that moved past a threshold (Picinbono et al. 2003)",
    drops="the non-linearity of what moved less than the threshold; the volume penalty of its linear part",
    represents=("fibres",),
    cost=3,
    rank=3,
)
