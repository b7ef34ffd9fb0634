"""stvk-tm: non-linear St Venant-Kirchhoff tensor-mass (Picinbono et al. 2003)."""

from __future__ import annotations

from ..blocks import GEO_ROWS, block_scratch
from ..material import Material, Materials
from ..model import Loading, Model
from ..stvk import stvk_energy, stvk_force
from .base import ModelSpec, block_model

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
    return block_model(
        NAME, points, tets, material, loading, (stvk_force, stvk_energy, block_scratch), threads, precision
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
