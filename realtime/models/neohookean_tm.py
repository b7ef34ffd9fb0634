"""neohookean-tm: compressible neo-Hookean tensor-mass (Bonet & Wood 2008, eq. 6.27), the law newton's,
Genesis', SOFA's and FEBio's soft bodies offer, which resists inversion where StVK softens."""

from __future__ import annotations

from ..blocks import block_scratch
from ..material import Material, Materials
from ..model import Loading, Model
from ..neohookean import neohookean_energy, neohookean_force
from .base import ModelSpec, block_model

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
    kernels = (neohookean_force, neohookean_energy, block_scratch)
    why = "the neo-Hookean law has no fibre terms; use stvk-tm for fibres"
    return block_model(NAME, points, tets, material, loading, kernels, threads, precision, isotropic=why)


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
