"""corotational-tm: corotational linear elasticity, a polar rotation per tetrahedron (SOFA's "polar"
method)."""

from __future__ import annotations

from ..corotational import corotational_energy, corotational_force, corotational_scratch
from ..material import Material, Materials
from ..model import Loading, Model
from .base import ModelSpec, block_model

NAME = "corotational-tm"


def build(points, tets, material: Material | Materials, loading: Loading | None = None, threads: int = 1) -> Model:
    """Corotational linear elasticity, polar rotation per tetrahedron (SOFA's "polar" method).

    Isotropic only: for an anisotropic law the rotated-frame force is not the gradient of an energy.
    ``threads`` > 1: the force on that many threads (realtime.threaded).
    """
    kernels = (corotational_force, corotational_energy, lambda dtype: corotational_scratch())
    why = "the rotated-frame force of an anisotropic law is not the gradient of an energy; use stvk-tm for fibres"
    return block_model(NAME, points, tets, material, loading, kernels, threads, isotropic=why)


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="linear elasticity in each tetrahedron's rotated frame (polar decomposition; Felippa, SOFA)",
    drops="the strain's non-linearity: exact under rigid rotations, linear in the stretch",
    integrators=("symplectic-euler", "implicit-euler"),
    cost=4,
    rank=1,
)
