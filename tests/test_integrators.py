"""Integrators: the critical time step, blow-up detection, tools, order of accuracy."""

import math

import numpy as np
import pytest

from meshes import stored_mesh
from realtime import (
    CentralDifference,
    DivergenceError,
    Loading,
    Material,
    State,
    SymplecticEuler,
    build_model,
    element_critical_dt,
    max_eigenvalue,
)
from realtime.model import TOOL_ROTATION
from reference.problem import Displacement

MAT = Material(5e5, 0.45, 1000.0, law="linear")


def clamped_beam(material=MAT):
    mesh = stored_mesh("beam")
    free = np.ones((mesh.n_vertices, 3))
    free[mesh.points[:, 0] < 1e-9] = 0.0
    fext = np.zeros((mesh.n_vertices, 3))
    load = Loading(free=free, external_force=fext)
    return mesh, build_model("linear-tm", mesh.points, mesh.tets, material, load)


def test_max_eigenvalue_matches_dense():
    mesh, model = clamped_beam()
    K = model.extra["tensors"].matrix().toarray()
    free = model.loading.free.ravel() != 0
    s = 1 / np.sqrt(np.repeat(model.mass, 3))[free]
    dense = np.linalg.eigvalsh(s[:, None] * K[np.ix_(free, free)] * s[None, :]).max()
    assert max_eigenvalue(model) == pytest.approx(dense, rel=1e-7)
    # the element estimate L_min / c_p is of the same order (it ignores the mesh's assembly)
    dt = 2 / math.sqrt(dense)
    assert 0.2 * dt < element_critical_dt(model) < 5 * dt


@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference])
def test_stable_below_and_diverging_above_the_critical_step(cls, rng):
    mesh, model = clamped_beam()
    integ = cls()
    dt_crit = integ.critical_dt(model)
    state = State.at_rest(mesh.n_vertices)
    state.u[:] = 1e-4 * rng.standard_normal(state.u.shape) * model.loading.free
    integ.step(model, state, 0.9 * dt_crit, 10_000)
    assert np.abs(state.u).max() < 1e-2  # bounded: energy is conserved by both schemes
    state = State.at_rest(mesh.n_vertices)
    state.u[:] = 1e-4 * rng.standard_normal(state.u.shape) * model.loading.free
    with pytest.raises(DivergenceError, match=r"diverged at step \d+: dt = .* critical dt") as info:
        integ.step(model, state, 1.2 * dt_crit, 10_000)
    assert info.value.dt_crit == pytest.approx(dt_crit)


def test_damping_lowers_the_critical_step():
    _, model = clamped_beam()
    assert SymplecticEuler(beta=1e-5).critical_dt(model) < SymplecticEuler().critical_dt(model)


def test_rotation_tool_in_the_kernel_matches_the_scene_definition(rng):
    mesh = stored_mesh("beam")
    idx = np.arange(0, mesh.n_vertices, 7)
    free = np.ones((mesh.n_vertices, 3))
    free[idx] = 0
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    load = Loading(
        free=free,
        external_force=np.zeros_like(free),
        tool_vertex=idx,
        tool_mask=np.ones((len(idx), 3)),
        tool_id=np.zeros(len(idx), np.int64),
        tool_kind=np.array([TOOL_ROTATION]),
        tool_vector=np.zeros((1, 3)),
        tool_axis=axis[None],
        tool_center=np.array([[0.05, 0.01, 0.0]]),
        tool_angle=np.array([math.radians(75.0)]),
        tool_ramp=np.array([0.5]),
    )
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, load)
    scene_tool = Displacement(region=None, axis=tuple(axis), center=(0.05, 0.01, 0.0), angle=75.0, ramp=0.5)
    for t in (0.1, 0.5, 2.0):
        np.testing.assert_allclose(model.tool_displacement(t), scene_tool.value(mesh.points[idx], t), atol=1e-15)


@pytest.mark.parametrize("cls, order, tol", [(SymplecticEuler, 1, 0.15), (CentralDifference, 2, 0.1)])
def test_order_of_accuracy_on_the_beam(cls, order, tol):
    """Trajectory error against a much finer run; the fitted slope is the scheme's order.

    Symplectic Euler's error is C1 dt + C2 dt^2 where C1 comes only from the initial half-step
    offset of its velocity, so its slope approaches 1 from above (1.10 at these steps): 0.15.
    """
    mesh, model = clamped_beam()
    dt_crit = cls().critical_dt(model)
    u0 = np.zeros((mesh.n_vertices, 3))
    u0[:, 2] = 1e-3 * (mesh.points[:, 0] / 0.1) ** 2  # a smooth bending shape
    T = 200 * dt_crit

    def run(dt):
        st = State(u=u0.copy(), v=np.zeros_like(u0))
        cls().step(model, st, dt, int(round(T / dt)))
        return st.u

    fine = run(dt_crit / 512)
    dts = [dt_crit / 16, dt_crit / 32, dt_crit / 64]
    errs = [np.linalg.norm(run(dt) - fine) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert slope == pytest.approx(order, abs=tol)
