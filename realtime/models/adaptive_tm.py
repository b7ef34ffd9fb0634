"""adaptive-tm: StVK tensor-mass on the mesh refined where the strain is (realtime.adaptive)."""

from __future__ import annotations

from ..adaptive import DEFAULT_THRESHOLD, AdaptivePlan, adaptive_model
from ..material import Material, Materials
from ..model import Loading, Model
from .base import ModelSpec

NAME = "adaptive-tm"


def build(
    points,
    tets,
    material: Material | Materials,
    loading: Loading | None = None,
    threshold: float = DEFAULT_THRESHOLD,
    plan: AdaptivePlan | None = None,
    mixed_loading: Loading | None = None,
    levels: int = 1,
) -> Model:
    """StVK tensor-mass on the mesh refined where the predictor's strain reaches ``threshold`` times its
    largest, ``levels`` times (``realtime.adaptive.adaptive_model``, where ``plan`` and
    ``mixed_loading`` are explained)."""
    return adaptive_model(NAME, points, tets, material, loading, threshold, plan, mixed_loading, levels)


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="St Venant-Kirchhoff tensor-mass on a mixed mesh, refined with hanging vertices where a linear predictor strains most",
    drops="the coarse mesh's resolution away from the refined region",
    represents=("fibres", "penalty"),
    own_mesh=True,
    cost=5,
    rank=8,
)
