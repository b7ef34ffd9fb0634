"""precomputed: the quasi-static linear model of precomputed responses (Cotin et al. 1999)."""

from __future__ import annotations

from ..material import Material, Materials
from ..model import Loading, Model
from ..quasistatic import Precomputed
from . import linear_tm
from .base import QUASI_STATIC, ModelSpec, with_quasistatic

NAME = "precomputed"


def build(points, tets, material: Material | Materials, loading: Loading | None = None) -> Model:
    """Quasi-static precomputed linear model (Cotin et al. 1999); see realtime.quasistatic."""
    return with_quasistatic(linear_tm.build(points, tets, material, loading), NAME, Precomputed)


def memory(dofs: float, surface_dofs: float) -> float:
    """Bytes of the responses: a dense float64 column of every dof per surface dof."""
    return 8 * dofs * surface_dofs


SPEC = ModelSpec(
    name=NAME,
    build=build,
    own_law="linear",
    law="linear elasticity, its static answer superposed from responses precomputed per tool vertex (Cotin et al. 1999)",
    drops="the dynamics and the geometric non-linearity",
    represents=("fibres",),
    integrators=QUASI_STATIC,
    linear=True,
    memory=memory,
    rank=5,
)
