"""neohookean-tm: compressible neo-Hookean tensor-mass (Bonet & Wood 2008, eq. 6.27), the law newton's,
Genesis', SOFA's and FEBio's soft bodies offer, which resists inversion where StVK softens."""

from __future__ import annotations

from functools import partial

import numpy as np

from ..blocks import BlockData, block_data, block_scratch
from ..errors import InputError
from ..material import Material, Materials
from ..model import PRECISIONS, Loading, Model, prepare_mesh
from ..neohookean import neohookean_energy, neohookean_force
from ..threaded import block_kernel, check_threads
from .base import ModelSpec, assemble

NAME = "neohookean-tm"


def build(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threads: int = 1,
    precision: str = "float64",
) -> Model:
    """Compressible neo-Hookean tensor-mass, isotropic, with the volume penalty when
    ``material.volume_penalty`` > 0 (realtime.neohookean). Rotation invariant; an inverted tetrahedron
    stops the run. ``threads`` > 1: the force on that many threads (realtime.threaded). ``precision``:
    Model.precision."""
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    if Materials.of(material, len(tets)).transverse:
        raise InputError(f"{NAME}: isotropic materials only (the neo-Hookean law has no fibre terms); use stvk-tm")
    dtype = PRECISIONS[precision]
    btets, geo, prm = block_data(points, tets, material, dtype)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    kernel = block_kernel(
        neohookean_force, neohookean_energy, partial(block_scratch, dtype), data, len(points), threads
    )
    return assemble(
        NAME, points, tets, material, loading, *kernel[:3], False, kernel[3], precision=precision, threads=threads
    )


SPEC = ModelSpec(
    name=NAME,
    build=build,
    own_law="neo-hookean",
    law="compressible neo-Hookean, W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2, P1 tetrahedra (Bonet & Wood 2008)",
    drops="nothing of its law; isotropic only",
    represents=("penalty",),
    integrators=("symplectic-euler", "implicit-euler"),
    float32=True,
    cost=2,
    rank=3,
)
