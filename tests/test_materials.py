"""Several materials in one body (issue 12): the engine's per-tetrahedron materials.

A body's elastic energy, force, stiffness and masses are sums over its tetrahedra, so a model of two
materials must equal, term by term, the sum of two one-material models, each built on its own
tetrahedra. That is the test of every model here; it checks the per-block coefficients of the element
kernels, the per-tetrahedron tensors of tensor-mass and the springs' calibration without trusting any of
their formulas. The closed-form check (layers in series) is in tests/test_scene.py's layered slab.
"""

import numpy as np
import pytest

from meshes import stored_mesh
from realtime import Material, MaterialError, Materials, build_model
from realtime.models import cut

HOST = Material(3.0e3, 0.45, 1000.0, law="stvk")
#: 100 times stiffer than HOST, another Poisson's ratio and density, fibres around an axis and the
#: volume penalty: every coefficient differs between the two parts.
STIFF = Material(
    3.0e5,
    0.3,
    1300.0,
    law="stvk",
    fiber_axis=(0.1, 0.2, 1.0),
    fiber_point=(1e-3, 2e-3, 0.0),
    young_fiber=6e5,
    fiber_shear=2e4,
    volume_penalty=1e5,
)
STIFF_ISO = Material(3.0e5, 0.3, 1300.0, law="stvk")

#: Two sums of the same terms in another order differ by round-off: a few hundred ulps of the largest
#: term, which the stiff part's force sets.
ROUND_OFF = 1e-12


def two_parts():
    """The cylinder with the tetrahedra whose centroid has z above the middle given material 1."""
    mesh = stored_mesh("cylinder")
    z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    index = (z > np.median(z)).astype(np.int64)
    return mesh, index


CASES = [
    ("linear-tm", STIFF, {}),
    ("stvk-tm", STIFF, {}),
    ("corotational-tm", STIFF_ISO, {}),
    ("hybrid-tm", STIFF, {"threshold": 2e-3}),  # u below has both sides of the threshold
    ("mass-spring", STIFF, {}),
]


@pytest.mark.parametrize("name, stiff, options", CASES, ids=[c[0] for c in CASES])
def test_two_materials_are_the_sum_of_two_bodies(name, stiff, options, rng):
    mesh, index = two_parts()
    both = build_model(name, mesh.points, mesh.tets, Materials((HOST, stiff), index), **options)
    parts = [build_model(name, mesh.points, mesh.tets[index == k], m, **options) for k, m in enumerate((HOST, stiff))]
    u = 1e-3 * rng.standard_normal(mesh.points.shape)  # 10% of the edge length: the non-linear terms count
    f = both.internal_force(u)
    f_sum = sum(p.internal_force(u) for p in parts)
    scale = np.abs(f_sum).max()
    assert np.abs(f - f_sum).max() <= ROUND_OFF * scale
    # the stiff part's force dominates: a model that gave every tetrahedron one material fails by far
    assert np.abs(parts[1].internal_force(u)).max() > 10 * np.abs(parts[0].internal_force(u)).max()
    energy = both.elastic_energy(u)
    assert energy == pytest.approx(sum(p.elastic_energy(u) for p in parts), rel=ROUND_OFF)
    np.testing.assert_allclose(both.mass, sum(p.mass for p in parts), rtol=ROUND_OFF)
    K = both.rest_stiffness()
    K_sum = sum(p.rest_stiffness() for p in parts)
    assert abs(K - K_sum).max() <= ROUND_OFF * abs(K_sum).max()
    # the element bound is a max over elements: the stiffer part's
    bound = both.element_eigenvalue_bound()
    assert bound == pytest.approx(max(p.element_eigenvalue_bound() for p in parts), rel=ROUND_OFF)


@pytest.mark.parametrize("name", ["linear-tm", "stvk-tm", "mass-spring"])
def test_one_material_twice_is_one_material(name, rng):
    mesh, index = two_parts()
    one = build_model(name, mesh.points, mesh.tets, HOST)
    twice = build_model(name, mesh.points, mesh.tets, Materials((HOST, HOST), index))
    u = 1e-3 * rng.standard_normal(mesh.points.shape)
    f = one.internal_force(u)
    assert np.abs(twice.internal_force(u) - f).max() <= ROUND_OFF * np.abs(f).max()
    np.testing.assert_allclose(twice.mass, one.mass, rtol=ROUND_OFF)


def test_cutting_a_body_of_two_materials_equals_rebuilding_it(rng):
    mesh, index = two_parts()
    materials = Materials((HOST, STIFF), index)
    model = build_model("linear-tm", mesh.points, mesh.tets, materials)
    removed = np.flatnonzero(
        np.linalg.norm(mesh.points[mesh.tets].mean(axis=1) - mesh.points.mean(axis=0), axis=1) < 4e-3
    )
    assert 0 < len(removed) < len(mesh.tets) // 4
    after = cut(model, removed)
    keep = np.setdiff1d(np.arange(len(mesh.tets)), removed)
    rebuilt = build_model("linear-tm", mesh.points, mesh.tets[keep], materials.subset(keep))
    u = 1e-3 * rng.standard_normal(mesh.points.shape)
    f = rebuilt.internal_force(u)
    assert np.abs(after.internal_force(u) - f).max() <= ROUND_OFF * np.abs(f).max()
    used = np.unique(mesh.tets[keep])
    np.testing.assert_allclose(after.mass[used], rebuilt.mass[used], rtol=ROUND_OFF)
    assert np.array_equal(after.materials.index, index[keep])


def test_bad_materials_are_one_line_errors():
    mesh, index = two_parts()
    with pytest.raises(MaterialError, match=r"materials.index\[\d+\] = 2: tetrahedron \d+ names no material"):
        Materials((HOST, STIFF), np.where(index == 1, 2, 0))
    with pytest.raises(MaterialError, match=f"materials.index: {len(index) - 1} entries for a mesh of {len(index)}"):
        build_model("stvk-tm", mesh.points, mesh.tets, Materials((HOST, STIFF), index[1:]))
    with pytest.raises(MaterialError, match="non-empty sequence of Material"):
        Materials((), index)
    with pytest.raises(Exception, match="isotropic materials only"):
        build_model("corotational-tm", mesh.points, mesh.tets, Materials((HOST, STIFF), index))
