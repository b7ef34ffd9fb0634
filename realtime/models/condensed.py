"""condensed: the static linear model condensed onto the surface (Bro-Nielsen 1996)."""

from __future__ import annotations

from ..material import Material, Materials
from ..model import Loading, Model
from ..quasistatic import Condensed
from . import linear_tm
from .base import QUASI_STATIC, ModelSpec, with_quasistatic

NAME = "condensed"


def build(points, tets, material: Material | Materials, loading: Loading | None = None) -> Model:
    """Static linear model condensed onto the surface (Bro-Nielsen 1996); see realtime.quasistatic."""
    return with_quasistatic(linear_tm.build(points, tets, material, loading), NAME, Condensed)


def memory(dofs: float, surface_dofs: float) -> float:
    """Bytes of the Schur complement on the surface dofs and its Cholesky factor (float64, squared, twice)."""
    return 8 * 2 * surface_dofs * surface_dofs


SPEC = ModelSpec(
    name=NAME,
    build=build,
    own_law="linear",
    law="linear elasticity condensed onto the surface vertices, its static answer solved there (Bro-Nielsen 1996)",
    drops="the dynamics and the geometric non-linearity",
    represents=("fibres",),
    integrators=QUASI_STATIC,
    linear=True,
    memory=memory,
    rank=6,
)
