"""stvk-tm: non-linear St Venant-Kirchhoff tensor-mass (Picinbono et al. 2003)."""

from __future__ import annotations

from functools import partial

import numpy as np

from ..blocks import GEO_ROWS, BlockData, block_data, block_scratch
from ..material import Material, Materials
from ..model import PRECISIONS, Loading, Model, prepare_mesh
from ..stvk import stvk_energy, stvk_force
from ..threaded import block_kernel, check_threads
from .base import ModelSpec, assemble

NAME = "stvk-tm"


def build(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threads: int = 1,
    precision: str = "float64",
) -> Model:
    """Non-linear StVK tensor-mass (Picinbono et al. 2003), isotropic or transversely isotropic, with
    the volume penalty when ``material.volume_penalty`` > 0. Rotation invariant. ``threads`` > 1: the
    force on that many threads (realtime.threaded). ``precision``: Model.precision."""
    threads = check_threads(threads)
    points, tets = prepare_mesh(points, tets)
    dtype = PRECISIONS[precision]
    btets, geo, prm = block_data(points, tets, material, dtype)
    data = BlockData(btets, geo, prm, np.ones(len(btets), dtype=np.bool_))
    kernel = block_kernel(stvk_force, stvk_energy, partial(block_scratch, dtype), data, len(points), threads)
    return assemble(
        NAME, points, tets, material, loading, *kernel[:3], False, kernel[3], precision=precision, threads=threads
    )


SPEC = ModelSpec(
    name=NAME,
    build=build,
    own_law="stvk",
    law="St Venant-Kirchhoff (Green-Lagrange strain, linear in it), P1 tetrahedra (Picinbono et al. 2003)",
    drops="nothing of its law; StVK itself softens and can invert under strong compression",
    represents=("fibres", "penalty"),
    integrators=("symplectic-euler", "implicit-euler"),
    float32=True,
    cost=2,
    # isotropic, no penalty: gather 9, H 45, Green-Lagrange strain 45, the second Piola-Kirchhoff stress
    # times the volume 14, P = (I + H) S 54, P g 45, scatter 18 flops = 230; bytes: the rows of geometry
    # the isotropic loop reads (GEO_ROWS less the 3 fibre rows, which only the general loop reads) and 4
    # int64 indices
    work={"tet": (230.0, 8.0 * (GEO_ROWS - 3) + 32.0)},
    rank=2,
)
