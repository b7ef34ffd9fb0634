"""Linear tensor-mass against dolfinx's P1 stiffness, its energy, and the force-field contracts."""

import numpy as np
import pytest

from meshes import stored_mesh, structured_box
from realtime import Material, build_model
from realtime.laws import linear_pk1
from realtime.tensor_mass import element_stiffness
from reference.fem import ElasticityProblem
from reference.problem import Problem

from ..conftest import match_nodes

ISO = Material(5e5, 0.45, 1000.0, law="linear")
TRANSVERSE = Material(1e4, 0.4, 1000.0, law="linear", fiber=(1.0, 1.0, 0.0), young_fiber=4e4, fiber_shear=2e3)


@pytest.mark.parametrize("material", [ISO, TRANSVERSE], ids=["isotropic", "transversely-isotropic"])
def test_force_is_minus_dolfinx_stiffness_times_u(material, rng):
    mesh = stored_mesh("beam")
    K, coords = ElasticityProblem(mesh, material, Problem((), ())).stiffness_matrix()
    node = match_nodes(coords, mesh.points)
    model = build_model("linear-tm", mesh.points, mesh.tets, material)
    for _ in range(3):
        u = rng.standard_normal(mesh.points.shape) * 1e-3
        U = np.zeros((len(coords), 3))
        U[node] = u
        expected = -(K @ U.ravel()).reshape(-1, 3)[node]
        f = model.internal_force(u)
        # two assemblies of the same sums in different orders: round-off, far below 1e-10
        assert np.linalg.norm(f - expected) / np.linalg.norm(expected) < 1e-10


def test_element_stiffness_is_derivative_of_the_law(rng):
    mesh = structured_box([0.01, 0.02, 0.015], 1)
    ke = element_stiffness(mesh.points, mesh.tets[:1], TRANSVERSE)[0]  # (4, 4, 3, 3)
    from realtime.geometry import shape_gradients

    g, vol = shape_gradients(mesh.points, mesh.tets[:1])
    m = TRANSVERSE
    # force on vertex a: -V P(F) g_a with F = I + sum_b u_b (x) g_b; linear in u
    u = rng.standard_normal((4, 3))
    F = np.eye(3) + np.einsum("bi,bj->ij", u, g[0])
    P = linear_pk1(F, m.lam, m.mu, m.fiber_vector, m.dlam, m.dmu)
    f = -vol[0] * P @ g[0].T  # (3, 4)
    np.testing.assert_allclose(f.T, -np.einsum("abij,bj->ai", ke, u), rtol=1e-12, atol=1e-12 * np.abs(f).max())


def test_energy_gradient_and_invariances(rng):
    mesh = stored_mesh("cylinder")
    model = build_model("linear-tm", mesh.points, mesh.tets, TRANSVERSE)
    u = rng.standard_normal(mesh.points.shape) * 1e-3
    f = model.internal_force(u)
    # the energy is quadratic: central differences are exact up to round-off eps W / h
    h = 1e-7
    for k in rng.choice(mesh.n_vertices, 5, replace=False):
        for c in range(3):
            d = np.zeros_like(u)
            d[k, c] = h
            fd = -(model.elastic_energy(u + d) - model.elastic_energy(u - d)) / (2 * h)
            assert fd == pytest.approx(f[k, c], rel=1e-6, abs=1e-6 * np.abs(f).max())
    scale = np.abs(f).max()
    # internal forces are self-equilibrated: no net force, no net torque (linear: about the rest shape)
    assert np.abs(f.sum(axis=0)).max() < 1e-12 * scale * mesh.n_vertices
    assert np.abs(np.cross(mesh.points, f).sum(axis=0)).max() < 1e-12 * scale * mesh.n_vertices
    # a translation costs nothing
    t = np.tile([0.3, -0.2, 0.1], (mesh.n_vertices, 1))
    assert np.abs(model.internal_force(t)).max() < 1e-12 * scale


def test_linear_model_is_not_rotation_invariant():
    """Documents the spurious force of linear elasticity under a 90 degree rotation about z."""
    mesh = stored_mesh("beam")
    model = build_model("linear-tm", mesh.points, mesh.tets, ISO)
    R = np.array([[0.0, -1, 0], [1, 0, 0], [0, 0, 1]])
    c = mesh.points.mean(axis=0)
    u = (mesh.points - c) @ R.T + c - mesh.points
    # energy of the linear model under rotation theta: 2 (lambda + mu)(cos theta - 1)^2 per unit volume
    # (eps = (cos - 1)(e1e1 + e2e2)); at 90 degrees that is 2 (lambda + mu)
    volume = mesh.volumes().sum()
    assert model.elastic_energy(u) == pytest.approx(2 * (ISO.lam + ISO.mu) * volume, rel=1e-10)
