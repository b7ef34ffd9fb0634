"""adaptive-tm: StVK tensor-mass on the mesh refined where the strain is (realtime.adaptive)."""

from __future__ import annotations

from functools import partial

from ..adaptive import adaptive_model
from .base import ModelSpec

NAME = "adaptive-tm"

#: ``build(points, tets, material, loading=None, threshold, plan, mixed_loading, levels)``: StVK
#: tensor-mass on the mesh refined where the predictor's strain reaches ``threshold`` times its largest,
#: ``levels`` times (``realtime.adaptive.adaptive_model``, where ``plan`` and ``mixed_loading`` are
#: explained).
build = partial(adaptive_model, NAME)

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
