"""Each model's spec (realtime/models/) says what its built Model does: the facts the harness reads
instead of a table of names are checked against the models themselves, so that a spec cannot drift
from its builder."""

import dataclasses

import numpy as np
import pytest

from meshes import structured_box
from realtime import InputError, Material, build_model
from realtime.models import SPECS, ModelSpec
from realtime.models.linear_tm import cut

MESH = structured_box((0.02, 0.01, 0.01), (2, 1, 1))
MATERIAL = Material(1e4, 0.3, 1000.0, law="stvk")


@pytest.mark.parametrize("name", list(SPECS))
def test_a_spec_says_what_its_model_does(name):
    spec = SPECS[name]
    model = build_model(name, MESH.points, MESH.tets, MATERIAL)
    assert model.name == spec.name == name
    # quasi-static: the model carries its own update to equilibrium, and nothing else does
    assert ("quasistatic" in model.extra) == spec.quasi_static
    # linear: the force is linear in u, measured: f(2u) = 2 f(u) to round-off (64 eps of the force's size,
    # the sums of a few hundred products); a model without mechanics has no force to measure
    # strains of 10 to 30%: displacements past hybrid-tm's threshold (10% of an edge), where StVK bends
    u = np.column_stack([0.2 * MESH.points[:, 1], -0.1 * MESH.points[:, 0], 0.3 * MESH.points[:, 2]])
    f1, f2 = model.internal_force(u), model.internal_force(2.0 * u)
    if spec.mechanics:
        scale = np.abs(f2).max()
        assert scale > 0.0
        assert (np.abs(f2 - 2.0 * f1).max() <= 64 * np.finfo(float).eps * scale) == spec.linear
    else:
        assert not f1.any() and not spec.linear
    # float32: it builds in single precision exactly where its spec says so
    if spec.float32:
        assert build_model(name, MESH.points, MESH.tets, MATERIAL, precision="float32").precision == "float32"
    else:
        with pytest.raises(InputError, match="float64 only"):
            build_model(name, MESH.points, MESH.tets, MATERIAL, precision="float32")
    # cuttable: a cut succeeds exactly where its spec says so
    if spec.cuttable:
        assert cut(model, [0]).tets.shape[0] == MESH.tets.shape[0] - 1
    else:
        with pytest.raises(InputError, match="does not support cutting"):
            cut(model, [0])
    # own mesh: a model on a mesh of its own has vertices beyond the scene's
    assert (model.extra.get("observed") is not None) == spec.own_mesh


def test_a_spec_refuses_a_term_it_cannot_represent_and_an_empty_list_of_integrators():
    with pytest.raises(ValueError, match="'tendons'"):
        ModelSpec("x", None, "a law", represents=("fibres", "tendons"))
    with pytest.raises(ValueError, match="integrators"):
        ModelSpec("x", None, "a law", integrators=())
    undeclared = ModelSpec("x", None, "a law", represents=None)
    assert undeclared.unrepresented(dataclasses.replace(MATERIAL, volume_penalty=5e4)) == []
