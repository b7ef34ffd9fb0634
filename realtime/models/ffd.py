"""ffd: free-form deformation driven by the tools, the non-physics baseline (Sederberg & Parry 1986)."""

from __future__ import annotations

import scipy.sparse as sp

from ..ffd import FreeFormDeformation, no_energy, no_force
from ..material import Material, Materials
from ..model import Loading, Model, prepare_mesh
from .base import QUASI_STATIC, ModelSpec, assemble, with_quasistatic

NAME = "ffd"


def build(points, tets, material: Material | Materials, loading: Loading | None = None, degree: int = 3) -> Model:
    """Free-form deformation driven by the tools (Sederberg & Parry 1986; direct manipulation, Hsu et al.
    1992): no mechanics, the non-physics baseline; see realtime.ffd. ``degree``: the lattice's degree per
    axis, its knob ((degree + 1)^3 control points)."""
    points, tets = prepare_mesh(points, tets)
    model = assemble(
        NAME,
        points,
        tets,
        material,
        loading,
        no_force,
        no_energy,
        (),
        True,
        rest=lambda m: sp.csr_matrix((3 * m.n_vertices, 3 * m.n_vertices)),
        bound=lambda m: 0.0,
    )
    return with_quasistatic(model, NAME, lambda m: FreeFormDeformation(m, degree))


SPEC = ModelSpec(
    name=NAME,
    build=build,
    law="none: a Bernstein lattice over the body moved so that the tools' vertices follow them (Hsu et al. 1992)",
    drops="all mechanics: no material, no equilibrium, no load but the tools'",
    # no mechanics at all, so it claims every term: there is nothing it runs without
    represents=("fibres", "penalty"),
    integrators=QUASI_STATIC,
    mechanics=False,
    rank=7,
)
