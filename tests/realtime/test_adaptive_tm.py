"""adaptive-tm (issue 12): StVK tensor-mass on a mesh refined where the predictor strains it, with the
hanging midpoints of the non-conforming interface following their edges."""

import numpy as np
import pytest
from scipy.spatial import cKDTree

from meshes import stored_mesh
from realtime import InputError, Loading, Material, build_model
from realtime.adaptive import adaptive_plan
from realtime.geometry import boundary_faces, red_refinement

from ..conftest import assert_same_model

MATERIAL = Material(5e3, 0.45, 1000.0, law="stvk")
#: The same element sums in another order: a few hundred ulps of the largest force.
ROUND_OFF = 1e-12


def pulled_cylinder():
    """The cylinder held at its base, a tool pulling its top sideways: strain concentrates at the base."""
    mesh = stored_mesh("cylinder")
    x = mesh.points
    free = np.ones_like(x)
    free[x[:, 2] < x[:, 2].min() + 1e-9] = 0.0
    top = np.flatnonzero(x[:, 2] > x[:, 2].max() - 1e-9)
    loading = Loading.translating_tool(free, np.zeros_like(x), top, vector=(2e-3, 0.0, 0.0))
    return mesh, loading


def test_threshold_above_one_is_the_coarse_stvk_model(rng):
    mesh, loading = pulled_cylinder()
    adaptive = build_model("adaptive-tm", mesh.points, mesh.tets, MATERIAL, loading, threshold=2.0)
    coarse = build_model("stvk-tm", mesh.points, mesh.tets, MATERIAL, loading)
    assert len(adaptive.extra["plan"].hanging) == 0
    assert_same_model(adaptive, coarse, rng, ROUND_OFF)


def test_threshold_zero_is_the_stvk_model_of_the_refined_mesh(rng):
    mesh, loading = pulled_cylinder()
    adaptive = build_model("adaptive-tm", mesh.points, mesh.tets, MATERIAL, loading, threshold=0.0)
    points, tets = red_refinement(mesh.points, mesh.tets)
    fine = build_model("stvk-tm", points, tets, MATERIAL, adaptive.loading)
    assert np.array_equal(adaptive.points, points)
    assert_same_model(adaptive, fine, rng, ROUND_OFF)


def partly_refined(levels: int = 1):
    """The pulled cylinder refined where most strained, ``levels`` deep (balanced)."""
    mesh, loading = pulled_cylinder()
    model = build_model("adaptive-tm", mesh.points, mesh.tets, MATERIAL, loading, threshold=0.3, levels=levels)
    plan = model.extra["plan"]
    assert 0 < plan.refined.sum() < len(mesh.tets) and len(plan.hanging) > 0
    return mesh, model, plan


@pytest.mark.parametrize("levels", [1, 2])
def test_hanging_midpoints_pass_the_patch_test(levels):
    """Under an affine displacement the stress is the same everywhere, so every vertex inside the body
    is in equilibrium: with the hanging midpoints following their edges and their forces folded onto
    the ends, the non-conforming interface is no exception."""
    mesh, model, plan = partly_refined(levels)
    A = np.array([[0.02, 0.01, -0.03], [0.00, -0.01, 0.02], [0.04, 0.00, 0.01]])  # F = I + A, 2-4% strains
    f = model.internal_force(model.points @ A.T)
    # the body's surface: the boundary of the uniformly refined mesh (the mixed mesh's own boundary
    # faces would include the interface, whose faces do not pair up)
    points, tets = mesh.points, mesh.tets
    for _ in range(levels):
        points, tets = red_refinement(points, tets)
    distance, _ = cKDTree(points[np.unique(boundary_faces(tets))]).query(model.points)
    inner = distance > 1e-12
    ends = np.zeros(model.n_vertices, dtype=bool)
    ends[np.unique(plan.hanging)] = True
    assert (inner & ends).sum() > 20  # interface vertices inside the body, where the fold matters
    # 1e-12: round-off of sums of terms as large as the largest force; unfolded, these reach 0.5 of it
    assert np.abs(f[inner]).max() <= 1e-12 * np.abs(f).max()


@pytest.mark.parametrize("levels", [1, 2])
def test_force_is_minus_the_energy_gradient_across_the_interface(rng, levels):
    mesh, model, plan = partly_refined(levels)
    u = 1e-3 * rng.standard_normal((model.n_vertices, 3))
    f = model.internal_force(u)
    h = 1e-8
    for k in np.unique(plan.hanging)[:6]:  # the vertices whose force holds the folded halves
        for c in range(3):
            d = np.zeros_like(u)
            d[k, c] = h
            fd = -(model.elastic_energy(u + d) - model.elastic_energy(u - d)) / (2 * h)
            # central difference: truncation ~1e-12 f, round-off eps W / h ~1e-8 |f|max
            assert fd == pytest.approx(f[k, c], rel=1e-5, abs=1e-6 * np.abs(f).max())


def test_the_refined_tetrahedra_are_the_strained_ones():
    mesh, model, plan = partly_refined()
    assert plan.strain[plan.refined].min() >= 0.3 * plan.strain.max() > plan.strain[~plan.refined].max()


def test_bad_threshold():
    mesh, loading = pulled_cylinder()
    with pytest.raises(InputError, match="threshold = -1"):
        adaptive_plan(mesh.points, mesh.tets, MATERIAL, loading, threshold=-1)


def test_balanced_levels_leave_no_hanging_vertex_on_a_hanging_one():
    """Neighbours within one level: every hanging vertex's ends are model vertices."""
    _, _, plan = partly_refined(levels=2)
    assert set(np.unique(plan.level)) == {0, 1, 2}
    assert np.all(plan.hanging < plan.n_model)
