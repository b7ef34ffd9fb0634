"""A scene carried onto a mesh an engine made of the body itself (adapters/own_mesh.py): by the rules
``tissuebench export`` writes (``regions``), with numpy alone, as an adapter does in its engine's venv.

Carried onto the scene's own mesh, the rules must give back the export's arrays: the same held components,
the same tool vertices and displacements, the same gravity load. That is the check that a rule means on
another mesh what the scene means (a box's faces, a sphere's inside, a rotation about its axis)."""

from __future__ import annotations

import json

import numpy as np
import pytest

from tests.verification.test_adapter_driver import adapter_module
from verification.engines.export import export
from verification.inputs import scene_inputs
from verification.scene_file import load_scene


@pytest.fixture(scope="module")
def adapters():
    """The adapters' ``exported`` and ``own_mesh`` modules, loaded from their files."""
    return adapter_module("exported"), adapter_module("own_mesh")


def _exported(tmp_path, adapters, name: str):
    export(scene_inputs(load_scene(name)), tmp_path / name)
    return adapters[0].read(tmp_path / name)


@pytest.mark.parametrize("name", ["cantilever", "cantilever-pull", "sofa-liver", "block-twist"])
def test_a_scene_carried_onto_its_own_mesh_by_its_rules_is_its_export(tmp_path, adapters, name):
    """A box hold and gravity (cantilever), a box tool (cantilever-pull), a sphere hold inside the body and a
    sphere tool (sofa-liver), a tool rotating a face (block-twist): the rules select the export's vertices and
    components exactly, and give its tool displacements and gravity load to round-off (1e-12 of the largest:
    a rotation and a lumped mass computed again in another order)."""
    scene = _exported(tmp_path, adapters, name)
    own = adapters[1].on_mesh(scene, scene.points, scene.tets)
    assert np.array_equal(own.free, scene.free)
    prescribed, theirs = own.prescribed(0.0), scene.prescribed(0.0)
    assert np.abs(prescribed - theirs).max() <= 1e-12 * max(np.abs(theirs).max(), 1e-300)
    assert np.abs(own.external_force - scene.external_force).max() <= 1e-12 * np.abs(scene.external_force).max()


def test_the_surface_a_mesher_reads_is_closed_and_faces_out(tmp_path, adapters):
    """The boundary triangles of sofa-liver's tetrahedra: every edge in two of them, and by the divergence
    theorem the volume they enclose, sum of (x . n) A / 3 over outward faces, is the tetrahedra's (1e-12)."""
    scene = _exported(tmp_path, adapters, "sofa-liver")
    faces = adapters[1].surface(scene)
    edges = np.sort(np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]]), axis=1)
    assert set(np.unique(edges, axis=0, return_counts=True)[1].tolist()) == {2}
    x = scene.points[faces]
    doubled_area_normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    enclosed = np.einsum("ij,ij->", x[:, 0], doubled_area_normal) / 6.0
    assert enclosed == pytest.approx(scene.volumes().sum(), rel=1e-12)


def test_what_has_no_rule_on_another_mesh_is_refused_naming_it(tmp_path, adapters):
    """A region drawn on the scene mesh (its rule null), an export without regions, a dynamic scene and a
    rule that selects no vertex of the engine's mesh: each an AdapterError naming it."""
    exported, own_mesh = adapters
    scene = _exported(tmp_path, adapters, "sofa-liver")

    def refused(spec: dict, points=scene.points) -> str:
        with pytest.raises(exported.AdapterError) as err:
            own_mesh.on_mesh(type(scene)(**{**scene.__dict__, "spec": spec}), points, scene.tets)
        return str(err.value)

    drawn = json.loads(json.dumps(scene.spec))
    drawn["regions"]["fixed"][0]["rule"] = None
    assert "fixed[0] is drawn on the scene mesh" in refused(drawn)
    assert "carries no regions" in refused({k: v for k, v in scene.spec.items() if k != "regions"})
    dynamic = {**scene.spec, "time": {**scene.spec["time"], "mode": "dynamic"}}
    assert "dynamic scene" in refused(dynamic)
    far = scene.points + 1.0  # the body a metre away: the held sphere holds none of it
    assert "fixed[0] holds none of its" in refused(scene.spec, far)
