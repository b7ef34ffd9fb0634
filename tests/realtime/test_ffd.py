"""The free-form deformation baseline (issue 12): what a lattice driven by the tools does, and does not."""

import numpy as np
import pytest

from meshes import structured_box
from realtime import InputError, Loading, Material, State, build_model
from realtime.ffd import bernstein, lattice_basis
from realtime.quasistatic import QuasiStatic

MATERIAL = Material(5e3, 0.45, 1000.0)


def test_bernstein_basis_is_a_partition_of_unity_with_linear_precision(rng):
    s = rng.uniform(0.0, 1.0, 50)
    for n in (1, 3, 6):
        b = bernstein(n, s)
        # sums of n + 1 positive terms of order 1: a few ulps
        np.testing.assert_allclose(b.sum(axis=1), 1.0, rtol=0, atol=8 * n * np.finfo(float).eps)
        np.testing.assert_allclose(b @ (np.arange(n + 1) / n), s, rtol=0, atol=8 * n * np.finfo(float).eps)
    x = rng.uniform(0.0, 1.0, (20, 3))
    B = lattice_basis(x, np.zeros(3), np.ones(3), 2)
    assert B.shape == (20, 27) and np.all(B >= 0.0)


def clamped_block(shear=0.002):
    """A 4 x 1 x 1 cm block held at x = 0, a tool moving its face x = 4 cm by (0, 0, shear)."""
    mesh = structured_box((0.04, 0.01, 0.01), (8, 5, 5))  # faces of 6 x 6 vertices pin degree 5
    x = mesh.points
    free = np.ones_like(x)
    free[x[:, 0] < 1e-9] = 0.0
    right = np.flatnonzero(x[:, 0] > 0.04 - 1e-9)
    loading = Loading.translating_tool(free, np.zeros_like(x), right, vector=(0.0, 0.0, shear), ramp=0.0)
    return mesh, loading


@pytest.mark.parametrize("degree", [1, 3, 5])
def test_a_field_the_lattice_holds_is_reproduced(degree):
    """One end held, the other driven, so that the smoothest lattice field is u_z = shear x / L, which Bernstein
    polynomials of any degree hold exactly (linear precision): every vertex gets it. (Each end face has
    more vertices a side than the degree, so that it pins its layer of control points: on a coarser face
    the polynomials that vanish at its vertices are free, and the smoothest field is another.)"""
    mesh, loading = clamped_block()
    model = build_model("ffd", mesh.points, mesh.tets, MATERIAL, loading, degree=degree)
    state = State.at_rest(mesh.n_vertices)
    force = QuasiStatic().step(model, state, 1e-3)
    expected = np.zeros_like(mesh.points)
    expected[:, 2] = 0.002 * mesh.points[:, 0] / 0.04
    # an exact fit through an SVD: round-off, amplified by the basis' conditioning (1e3 at degree 5)
    assert np.abs(state.u - expected).max() <= 1e-10 * 0.002
    assert np.all(force == 0.0)  # a lattice exerts no force: no haptic feedback


def test_no_mechanics_loads_move_nothing_and_the_internal_force_is_zero(rng):
    mesh, loading = clamped_block(shear=0.0)
    heavy = Loading(**{**loading.__dict__, "external_force": np.tile([0.0, 0.0, -1.0], (mesh.n_vertices, 1))})
    model = build_model("ffd", mesh.points, mesh.tets, MATERIAL, heavy)
    u, reaction = QuasiStatic().equilibrium(model)
    assert np.all(u == 0.0) and np.all(reaction == 0.0)
    assert np.all(model.internal_force(rng.standard_normal(mesh.points.shape)) == 0.0)
    assert model.elastic_energy(rng.standard_normal(mesh.points.shape)) == 0.0


def test_the_degree_is_checked():
    mesh, loading = clamped_block()
    with pytest.raises(InputError, match="ffd: degree = 0"):
        build_model("ffd", mesh.points, mesh.tets, MATERIAL, loading, degree=0)
