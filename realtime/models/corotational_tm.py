"""corotational-tm: corotational linear elasticity, a polar rotation per tetrahedron (SOFA's "polar"
method)."""

from __future__ import annotations

import numpy as np

from ..blocks import BlockData, block_data
from ..corotational import corotational_energy, corotational_force, corotational_scratch
from ..errors import InputError
from ..material import Material, Materials
from ..model import Loading, Model, prepare_mesh
from ..threaded import block_kernel, check_threads
from .base import ModelSpec, assemble

NAME = "corotational-tm"


def build(points, tets, material: Material | Materials, loading: Loading | None = None, threads: int = 1) -> Model:
    """Corotational linear elasticity, polar rotation per tetrahedron (SOFA's "polar" method).

    Isotropic only: for an anisotropic law the rotated-frame force is not the gradient of an energy.
    ``threads`` > 1: the force on that many threads (realtime.threaded).
    """
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    if Materials.of(material, len(tets)).transverse:
        raise InputError(
            f"{NAME}: isotropic materials only (the rotated-frame force of an anisotropic "
            "law is not the gradient of an energy); use stvk-tm for fibres"
        )
    btets, geo, prm = block_data(points, tets, material)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    kernel = block_kernel(corotational_force, corotational_energy, corotational_scratch, data, len(points), threads)
    return assemble(NAME, points, tets, material, loading, *kernel[:3], False, kernel[3], threads=threads)


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="linear elasticity in each tetrahedron's rotated frame (polar decomposition; Felippa, SOFA)",
    drops="the strain's non-linearity: exact under rigid rotations, linear in the stretch",
    integrators=("symplectic-euler", "implicit-euler"),
    cost=4,
    rank=1,
)
