"""Integrators: the critical time step, blow-up detection, tools, order of accuracy."""

import math
import re
from pathlib import Path

import numpy as np
import pytest

from meshes import stored_mesh
from realtime import (
    CentralDifference,
    DivergenceError,
    ImplicitEuler,
    Loading,
    Material,
    NotConvergedError,
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


@pytest.mark.parametrize("mesh_name", ["beam", "liver"])
@pytest.mark.parametrize("model_name", ["linear-tm", "stvk-tm", "corotational-tm", "mass-spring"])
@pytest.mark.parametrize(
    "material",
    [
        Material(5e5, 0.45, 1000.0),
        Material(1e4, 0.3, 1000.0, fiber=(1.0, 1.0, 0.0), young_fiber=3e4, fiber_shear=3e3),
        Material(1e4, 0.3, 1000.0, volume_penalty=5e4),
    ],
    ids=["isotropic", "fibres", "penalty"],
)
def test_element_critical_step_is_a_lower_bound(mesh_name, model_name, material):
    """The element eigenvalue inequality: 2 / sqrt(max_e lambda_max(K_e, M_e)) <= 2 / omega_max, the
    latter from dense eigenvalues of the free body. Measured ratios: 0.31 to 0.37 for tetrahedra (0.15
    for linear-tm with a volume penalty, which it leaves out while the bound keeps it), 0.45 to 0.46 for
    springs; the lower limit only says the bound is not uselessly loose."""
    if model_name == "corotational-tm" and material.fiber is not None:
        pytest.skip("corotational-tm is isotropic only")
    mesh = stored_mesh(mesh_name)
    model = build_model(model_name, mesh.points, mesh.tets, material)
    if mesh.n_vertices <= 600:
        K = model.rest_stiffness().toarray()
        s = 1 / np.sqrt(np.repeat(model.mass, 3))
        omega2 = np.linalg.eigvalsh(s[:, None] * K * s[None, :]).max()
    else:  # Lanczos, tested against dense above to 1e-7
        omega2 = max_eigenvalue(model)
    ratio = element_critical_dt(model) / (2 / math.sqrt(omega2))
    assert 0.1 < ratio <= 1.0 + 1e-6


@pytest.mark.parametrize("name, nu", [("linear-tm", 0.45), ("stvk-tm", 0.4999), ("mass-spring", 0.3)])
def test_min_eigenvalue_matches_dense(name, nu):
    """omega_1^2 by shift-invert on the rest stiffness (exact at rest for these models) against the
    dense eigenvalues of M^-1/2 K M^-1/2, K from the force kernel's finite differences at rest; the
    tolerance is the 1e-3 the time-step choice asks for."""
    from realtime.spectra import min_eigenvalue

    mat = Material(5e5, nu, 1000.0, law="stvk")
    mesh, lin = clamped_beam(mat)
    model = build_model(name, mesh.points, mesh.tets, mat, lin.loading)
    free = model.loading.free.ravel() != 0
    h = 1e-9  # columns of K = -df/du by central differences of the force (exact for linear-tm)
    cols = []
    for k in np.flatnonzero(free):
        e = np.zeros(3 * mesh.n_vertices)
        e[k] = h
        e = e.reshape(-1, 3)
        cols.append((model.internal_force(-e) - model.internal_force(e)).ravel()[free] / (2 * h))
    K = np.array(cols).T
    s = 1 / np.sqrt(np.repeat(model.mass, 3))[free]
    dense = np.linalg.eigvalsh(0.5 * (K + K.T) * s[:, None] * s[None, :]).min()
    assert min_eigenvalue(model) == pytest.approx(dense, rel=1e-3)


EXPLICIT_MODELS = ["linear-tm", "corotational-tm", "stvk-tm", "hybrid-tm", "mass-spring"]


@pytest.mark.parametrize("model_name", EXPLICIT_MODELS)
@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference])
def test_stable_below_and_diverging_above_the_critical_step(cls, model_name, rng):
    """10^4 steps at 0.9 dt_crit stay bounded; at 1.2 dt_crit the run raises the blow-up error.

    The perturbation (1e-6 m on 5 mm elements, strains ~1e-4) keeps the non-linear models in their
    linearised range, where the critical step at rest is the critical step. At 1e-5 m (strains ~1%
    in the highest modes) stvk-tm with symplectic Euler diverges after ~1600 steps at 0.9 dt_crit:
    the stiffened state's omega_max is 1.7% above the rest value and symplectic Euler's first kick
    puts twice leapfrog's energy into those modes. That is why the harness takes a non-linear
    model's critical step as the smaller of rest and equilibrium.
    """
    mesh, base = clamped_beam()
    model = build_model(model_name, mesh.points, mesh.tets, MAT, base.loading)
    integ = cls()
    dt_crit = integ.critical_dt(model)
    perturbation = 1e-6 * rng.standard_normal((mesh.n_vertices, 3)) * model.loading.free
    state = State(u=perturbation.copy(), v=np.zeros_like(perturbation))
    integ.step(model, state, 0.9 * dt_crit, 10_000)
    # bounded: both schemes conserve a modified energy below dt_crit; 100x the start is far from it
    assert np.abs(state.u).max() < 100 * np.abs(perturbation).max()
    state = State(u=perturbation.copy(), v=np.zeros_like(perturbation))
    state.steps, state.t = 7, 7 * 1.2 * dt_crit  # a state that has run before
    with pytest.raises(DivergenceError, match=r"diverged at step \d+: dt = .* critical dt") as info:
        integ.step(model, state, 1.2 * dt_crit, 10_000)
    assert info.value.dt_crit == pytest.approx(dt_crit)
    # u and v went through the failed step: the state's clock says so too (it stayed behind before)
    assert state.steps == info.value.step + 1 > 7
    assert state.t == pytest.approx(state.steps * 1.2 * dt_crit, rel=1e-12)


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


def test_implicit_euler_is_stable_far_beyond_the_explicit_limit():
    """Nearly incompressible (nu = 0.4999): 100 x the explicit critical step, energy never grows."""
    mesh, model = clamped_beam(Material(5e5, 0.4999, 1000.0))
    dt = 100 * SymplecticEuler().critical_dt(model)
    state = State.at_rest(mesh.n_vertices)
    state.u[:, 2] = 1e-3 * (mesh.points[:, 0] / 0.1) ** 2 * model.loading.free[:, 2]
    integ = ImplicitEuler()
    energies = []
    for _ in range(10):
        integ.step(model, state, dt, 5)
        energies.append(model.elastic_energy(state.u) + model.kinetic_energy(state.v))
    # implicit Euler dissipates: the total energy decreases monotonically (round-off aside)
    assert np.all(np.diff(energies) <= 1e-12 * energies[0])


def test_implicit_euler_settles_on_the_static_solution():
    """Gravity on the clamped beam: implicit Euler with large steps reaches K u = f (a direct solve)."""
    mesh, model = clamped_beam()
    fext = model.mass[:, None] * np.array([0.0, 0.0, -9.81])
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, Loading(free=model.loading.free, external_force=fext))
    import scipy.sparse.linalg as spla

    K = model.extra["tensors"].matrix()
    free = model.loading.free.ravel() != 0.0
    static = np.zeros(3 * mesh.n_vertices)
    static[free] = spla.spsolve(K[free][:, free].tocsc(), fext.ravel()[free])
    state = State.at_rest(mesh.n_vertices)
    ImplicitEuler(tol=1e-12).step(model, state, 1.0, 40)  # dt = 1 s: a hundred times the first period
    err = np.linalg.norm(state.u.ravel() - static) / np.linalg.norm(static)
    # each step shrinks the error by the amplification of the slowest mode, 1 / (1 + dt^2 omega_1^2)
    assert err < 1e-8


@pytest.mark.parametrize("name", ["linear-tm", "mass-spring"])
def test_factored_preconditioner_solves_the_rest_system(name, rng):
    """The sparse LU the implicit integrator preconditions with, applied in numba (permutations,
    triangular solves, free components only), against scipy's direct solve of the same system
    (M (1 + dt alpha) + (dt beta + dt^2) K0) on the free components: round-off."""
    import scipy.sparse as sp
    import scipy.sparse.linalg as spla

    from realtime.linsolve import factor_solve, factorise

    mesh, lin = clamped_beam()
    model = build_model(name, mesh.points, mesh.tets, MAT, lin.loading)
    dt, alpha, beta = 1e-3, 2.0, 1e-4
    cm, ck = 1 + dt * alpha, dt * beta + dt * dt
    free = model.loading.free.ravel() != 0.0
    A = (sp.diags(cm * np.repeat(model.mass, 3)) + ck * model.rest_stiffness()).tocsr()[free][:, free]
    r = rng.standard_normal((mesh.n_vertices, 3)) * model.loading.free
    z = np.full_like(r, np.nan)
    factor_solve(factorise(model, cm, ck), r, z)
    want = spla.spsolve(A.tocsc(), r.ravel()[free])
    assert np.linalg.norm(z.ravel()[free] - want) / np.linalg.norm(want) < 1e-12
    assert np.all(z.ravel()[~free] == 0.0)
    if name == "linear-tm":  # the rest stiffness of linear-tm is its own: -K0 u is its force
        u = rng.standard_normal(r.shape)
        f = -(model.rest_stiffness() @ u.ravel())
        assert np.linalg.norm(model.internal_force(u).ravel() - f) < 1e-12 * np.linalg.norm(f)


def test_factored_implicit_euler_on_nearly_incompressible_statics():
    """nu = 0.4999 under gravity: the mass-preconditioned CG needs more than 5000 iterations a step at
    dt = 10 ms and stops; factored, each step of a linear model is one CG iteration, and the static
    solve reaches K u = f (a direct solve) to its round-off floor (condition number ~1e8)."""
    import scipy.sparse.linalg as spla

    from realtime.statics import solve_static_implicit

    soft = Material(5e5, 0.4999, 1000.0, law="linear")
    mesh, model = clamped_beam(soft)
    fext = model.mass[:, None] * np.array([0.0, 0.0, -9.81])
    model = build_model(
        "linear-tm", mesh.points, mesh.tets, soft, Loading(free=model.loading.free, external_force=fext)
    )
    K = model.extra["tensors"].matrix()
    free = model.loading.free.ravel() != 0.0
    static = np.zeros(3 * mesh.n_vertices)
    static[free] = spla.spsolve(K[free][:, free].tocsc(), fext.ravel()[free])
    integ = ImplicitEuler(tol=1e-10)
    assert integ.preconditioner_for(model) == "factored"
    res = solve_static_implicit(model, 0.01, rtol=1e-10, integrator=integ)
    assert integ.worst_iterations <= 2  # an exact preconditioner: one iteration, two at round-off
    # the round-off floor: condition number ~1e8 times eps (measured 1.2e-10)
    assert np.linalg.norm(res.state.u.ravel() - static) / np.linalg.norm(static) < 1e-8
    # a weak preconditioner at the same step: CG stops at maxit, and says so instead of returning an
    # inexact step as if it were converged; the state has taken that step
    weak = ImplicitEuler(tol=1e-10, maxit=50, preconditioner="mass")
    state = State.at_rest(mesh.n_vertices)
    with pytest.raises(NotConvergedError, match=r"CG stopped at maxit = 50 iterations .* at step 0 \(dt = 0.01 s\)"):
        weak.step(model, state, 0.01, 3)
    assert (state.steps, state.t, weak.worst_iterations) == (1, 0.01, 50)
    # as a fixed budget (a real-time simulator's CG), the steps are taken and counted
    budget = ImplicitEuler(tol=1e-10, maxit=50, preconditioner="mass", budget=True)
    budget.step(model, state, 0.01, 3)
    assert (state.steps, budget.unconverged) == (4, 3)


def test_implicit_euler_is_first_order():
    """On a smooth motion (the beam released from its static sag, mostly the first bending mode) with
    steps that resolve its period T1; the high modes, which implicit Euler damps to nothing at any
    of these steps, carry almost no energy here."""
    import scipy.sparse.linalg as spla

    mesh, model = clamped_beam()
    K = model.extra["tensors"].matrix()
    free = model.loading.free.ravel() != 0
    sag = np.zeros((mesh.n_vertices, 3))
    sag[:, 2] = -model.mass
    u0 = np.zeros(3 * mesh.n_vertices)
    u0[free] = spla.spsolve(K[free][:, free].tocsc(), sag.ravel()[free])
    u0 = (1e-3 / np.abs(u0).max() * u0).reshape(-1, 3)
    w2 = (u0.ravel() @ (K @ u0.ravel())) / np.sum(model.mass[:, None] * u0**2)
    T1 = 2 * math.pi / math.sqrt(w2)

    def run(dt):
        st = State(u=u0.copy(), v=np.zeros_like(u0))
        ImplicitEuler(tol=1e-13).step(model, st, dt, int(round(0.5 * T1 / dt)))
        return st.u

    fine = run(T1 / 6400)
    dts = [T1 / 50, T1 / 100, T1 / 200]
    errs = [np.linalg.norm(run(dt) - fine) for dt in dts]
    slope = np.polyfit(np.log(dts), np.log(errs), 1)[0]
    assert slope == pytest.approx(1.0, abs=0.1)  # 0.95 measured: the fine run's own O(dt) error


def _pulled_beam():
    """The clamped beam with its free end held by a translating tool (ramp 1 ms) and a pull of gravity."""
    mesh, base = clamped_beam()
    tip = np.flatnonzero(mesh.points[:, 0] > mesh.points[:, 0].max() - 1e-9)
    free = base.loading.free.copy()
    free[tip] = 0.0
    load = Loading(
        free=free,
        external_force=base.mass[:, None] * np.array([0.0, 0.0, -9.81]),
        tool_vertex=tip.astype(np.int64),
        tool_mask=np.ones((len(tip), 3)),
        tool_id=np.zeros(len(tip), dtype=np.int64),
        tool_kind=np.zeros(1, dtype=np.int64),
        tool_vector=np.array([[0.0, 0.0, 1e-3]]),
        tool_axis=np.array([[0.0, 0.0, 1.0]]),
        tool_center=np.zeros((1, 3)),
        tool_angle=np.zeros(1),
        tool_ramp=np.array([1e-3]),
    )
    return mesh, load


@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference, ImplicitEuler])
def test_forces_and_tool_targets_changed_mid_run_are_honoured_identically_by_every_integrator(cls):
    """A simulator's frame: after some steps the external forces and the tool's target change. Through
    set_forces and set_tool, every integrator continues exactly as one that started at that state on a
    model built with the new forces and target (bit for bit: the same arithmetic). Before, symplectic
    Euler kept the forces it cached at its first step while the other two read the Loading live."""
    import dataclasses

    mesh, load = _pulled_beam()
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, load)
    dt = 0.5 * SymplecticEuler().critical_dt(model)
    pushed = np.zeros((mesh.n_vertices, 3))
    pushed[:, 1] = 1e-4 * model.mass  # a sideways push instead of gravity
    target = np.array([0.0, 2e-4, -5e-4])

    live, state = cls(), State.at_rest(mesh.n_vertices)
    live.step(model, state, dt, 30)
    live.set_forces(model, pushed)
    live.set_tool(model, 0, translation=target)
    live.step(model, state, dt, 30)

    other = State.at_rest(mesh.n_vertices)
    cls().step(model, other, dt, 30)
    changed = dataclasses.replace(load, external_force=pushed, tool_vector=target[None], tool_ramp=np.zeros(1))
    rebuilt = build_model("linear-tm", mesh.points, mesh.tets, MAT, changed)
    other.acc = None  # central difference: the acceleration of the new forces
    cls().step(rebuilt, other, dt, 30)

    assert np.abs(state.u).max() > 0.0
    np.testing.assert_array_equal(state.u, other.u)
    np.testing.assert_array_equal(state.v, other.v)
    tip = load.tool_vertex
    np.testing.assert_allclose(state.u[tip], np.broadcast_to(target, (len(tip), 3)), rtol=0, atol=0)
    # the model itself did not change: its Loading still holds the forces it was built with
    assert np.all(model.loading.external_force[:, 1] == 0.0)


def test_frame_inputs_are_checked_with_one_line_errors():
    from realtime import InputError
    from realtime.quasistatic import QuasiStatic

    mesh, load = _pulled_beam()
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, load)
    integ = SymplecticEuler()
    n = mesh.n_vertices
    for args, message in (
        (np.zeros((n, 2)), rf"forces: must have shape \({n}, 3\), got \({n}, 2\)"),
        (np.full((n, 3), np.nan), r"forces\[0, 0\]: must be finite, got nan"),
        ("many", r"forces: must be a .* array of numbers, got str"),
    ):
        with pytest.raises(InputError, match=message):
            integ.set_forces(model, args)
    with pytest.raises(InputError, match=r"set_tool: tool = 1: must be an index in 0..0"):
        integ.set_tool(model, 1, translation=[0.0, 0.0, 1e-3])
    bare = build_model("linear-tm", mesh.points, mesh.tets, MAT)
    with pytest.raises(InputError, match=r"set_tool: tool = 0: linear-tm was built with no tools"):
        SymplecticEuler().set_tool(bare, 0, translation=[0.0, 0.0, 1e-3])
    with pytest.raises(InputError, match=r"set_tool: tool 0 translates: give translation \(3,\) m"):
        integ.set_tool(model, 0, angle=0.1)
    with pytest.raises(InputError, match=r"translation: must have shape \(3,\), got \(2,\)"):
        integ.set_tool(model, 0, translation=[0.0, 1e-3])
    # a rotating tool takes an angle, and holds its vertices turned by it about its axis from the next step
    import dataclasses

    turning = dataclasses.replace(load, tool_kind=np.ones(1, dtype=np.int64))
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, turning)
    with pytest.raises(InputError, match=r"set_tool: tool 0 rotates: give angle \(rad\), got translation"):
        integ.set_tool(model, 0, translation=[0.0, 0.0, 1e-3])
    with pytest.raises(InputError, match=r"angle: must be a \(\) array of numbers, got str"):
        integ.set_tool(model, 0, angle="a quarter turn")
    integ.set_tool(model, 0, angle=0.01)
    state = State.at_rest(n)
    integ.step(model, state, 1e-7, 1)
    x = mesh.points[load.tool_vertex]
    turned = x @ np.array([[np.cos(0.01), -np.sin(0.01), 0.0], [np.sin(0.01), np.cos(0.01), 0.0], [0, 0, 1]]).T
    np.testing.assert_allclose(state.u[load.tool_vertex], turned - x, rtol=0, atol=1e-15)
    condensed = build_model("condensed", mesh.points, mesh.tets, MAT, load)
    with pytest.raises(InputError, match="set_forces: condensed precomputed its response to the loads"):
        QuasiStatic().set_forces(condensed, np.zeros((n, 3)))


def test_a_settling_below_its_round_off_floor_stops_there_whatever_the_order_of_the_sums(monkeypatch):
    """Asked for a residual of 1e-12 of the load, linear-tm on the cantilever cannot get there: its
    round-off floor (the force's response to moving u by one unit in the last place) is 1.0e-11. It
    stops once within FLOOR_FACTOR of that floor, at the same step with the one- and two-thread kernels,
    whose sums differ only in order. The stall rule alone, the only way out before, waited for 50 chunks
    without progress (21 200 and 22 200 steps measured, one thread against two: round-off decided)."""
    from realtime import statics
    from verification.engines.builtin import scene_model
    from verification.scene_file import load_scene

    scene = load_scene("cantilever")
    runs = []
    for threads in (1, 2):
        model = scene_model(scene, "linear-tm", threads=threads)
        dt = 0.9 * SymplecticEuler().critical_dt(model)
        res = statics.solve_static(model, dt=dt, rtol=1e-12)
        lo = model.loading
        scale = max(np.linalg.norm(lo.external_force * lo.free), np.linalg.norm(model.reaction(res.state.u)))
        floor = statics.residual_floor(model, res.state.u, scale)
        assert 1e-12 < res.residual < statics.FLOOR_FACTOR * floor  # stopped by the floor, not by rtol
        runs.append(res.steps)
    assert runs[0] == runs[1]
    monkeypatch.setattr(statics, "FLOOR_FACTOR", 0.0)  # the stall rule alone
    stalled = statics.solve_static(model, dt=dt, rtol=1e-12)
    assert stalled.steps > 1.5 * runs[1]


def test_a_settling_that_stops_progressing_far_above_its_tolerance_ends_early():
    """Asked for 1e-20 of the load, which no float64 run reaches (linear-tm's floor on the cantilever is
    1.0e-11), a settling that no floor or plateau rule may stop (1e-20 x 1000 is still far below what it
    reaches) ends when its residual has not fallen by 10% in STALLED_CHUNKS chunks: it does not settle,
    and says so then, not after max_steps (hybrid-tm ran 300 000 steps on the rates beam for that)."""
    from realtime import statics
    from verification.engines.builtin import scene_model
    from verification.scene_file import load_scene

    model = scene_model(load_scene("cantilever"), "linear-tm")
    dt = 0.9 * SymplecticEuler().critical_dt(model)
    with pytest.raises(NotConvergedError, match=r"has not fallen by 10% in its last 50000 steps") as err:
        statics.solve_static(model, dt=dt, rtol=1e-20, max_steps=2_000_000)
    taken = int(re.search(r"in (\d+) steps of", str(err.value)).group(1))
    assert statics.STALLED_CHUNKS * 200 <= taken < 200_000


def test_a_settling_is_damped_critically_for_its_slowest_mode_where_that_mode_is_known():
    """solve_static damps at alpha = 2 omega_1 (the slowest mode's critical damping, so every mode decays
    at least as fast as exp(-omega_1 t)) where omega_1 is cheap to know (shift-invert on the rest
    stiffness). Underwood's Rayleigh quotient, which it used throughout, exceeds omega_1^2 where the
    displacement is local: on SOFA's liver pressed by its tool it overdamped the slowest mode and
    stvk-tm settled in 34 400 steps instead of 6 000. Here both rules reach one equilibrium (to 1e-8
    relative: two runs each within 1e-10 of the load in residual), the critical one in under a third of
    the steps, and its damping is 2 omega_1 of the model's smallest eigenvalue."""
    from realtime import statics
    from realtime.spectra import min_eigenvalue
    from verification.engines.builtin import scene_model
    from verification.scene_file import load_scene

    model = scene_model(load_scene("sofa-liver"), "stvk-tm")
    omega1 = math.sqrt(min_eigenvalue(model))
    assert statics._Damping(model, 1.0, None).alpha == pytest.approx(2.0 * omega1, rel=1e-3)  # eigsh's tol
    critical = statics.solve_static(model, rtol=1e-10)
    quotient = statics.solve_static(model, rtol=1e-10, omega2_min=0.0)  # 0: not known, Underwood's estimate
    u = critical.state.u
    assert np.linalg.norm(quotient.state.u - u) <= 1e-8 * np.linalg.norm(u)
    assert 3 * critical.steps < quotient.steps


STATIC_SCENES = sorted(
    p.stem for p in (Path(__file__).parents[2] / "verification" / "scenes").glob("*.toml")
    if 'mode = "static"' in p.read_text()
)  # fmt: skip


@pytest.mark.slow
@pytest.mark.parametrize("scene", [*STATIC_SCENES, "rates-beam-refined"])
def test_hybrid_settles(scene):
    """hybrid-tm reaches equilibrium to 1e-10 of the load on every built-in static scene and on the rates
    beam refined once (7232 tetrahedra), where, switching its tetrahedra between laws at every step
    before it had a hysteresis, it stalled at a residual of 6e-3 (and at 5.9e-3 on a liver pressed by a
    5 mm tool)."""
    from realtime import statics
    from verification.engines.builtin import scene_model
    from verification.scene_file import load_scene
    from verification.studies.seeds.common import seed_scene

    found = seed_scene("rates-beam", refine=1) if scene == "rates-beam-refined" else load_scene(scene)
    res = statics.solve_static(scene_model(found, "hybrid-tm"), rtol=1e-10, max_steps=400_000)
    assert res.residual < 1e-7  # rtol, or a round-off floor or plateau at most 1000 rtol (solve_static)


@pytest.mark.parametrize("name", ["linear-tm", "stvk-tm", "mass-spring", "condensed"])
def test_a_wrong_array_given_to_a_models_methods_is_a_one_line_error(name):
    """The force and energy kernels index (N, 3) arrays without bounds checks: a (3, 3) u given to
    Model.internal_force wrote past its output and the process aborted ("corrupted size vs.
    prev_size"). Every method that takes a nodal field checks its shape first, and names itself."""
    from realtime import InputError
    from realtime.spectra import max_eigenvalue

    mesh, load = _pulled_beam()
    model = build_model(name, mesh.points, mesh.tets, MAT, load)
    n = mesh.n_vertices
    calls = {
        "internal_force: u": model.internal_force,
        "elastic_energy: u": model.elastic_energy,
        "kinetic_energy: v": model.kinetic_energy,
        "tool_reactions: u": model.tool_reactions,
        "max_eigenvalue: u": lambda u: max_eigenvalue(model, u),
    }
    for what, call in calls.items():
        for bad, got in (
            (np.zeros((3, 3)), r"\(3, 3\)"),
            (np.zeros(3 * n), rf"\({3 * n},\)"),
            (np.zeros((n, 3, 1)), ""),
        ):
            with pytest.raises(
                InputError, match=rf"^{what}: must have shape \({n}, 3\) \(the model's vertices\), got {got}"
            ):
                call(bad)
        with pytest.raises(InputError, match=rf"^{what}: must be an \({n}, 3\) array of numbers, got str"):
            call("zeros")
    # the right shape as a list, or in another float type, is taken as it is
    assert model.internal_force(np.zeros((n, 3)).tolist()).shape == (n, 3)
    assert model.elastic_energy(np.zeros((n, 3), np.float32)) == 0.0


@pytest.mark.parametrize("integrator", [SymplecticEuler, CentralDifference, ImplicitEuler])
def test_integrator_settings_are_checked_when_made(integrator):
    """A NaN damping coefficient surfaced as a divergence "at step 0", a negative one fed energy in
    without a word, and a string was a TypeError in the middle of a step."""
    from realtime import InputError

    for key, value in (("alpha", float("nan")), ("alpha", -10.0), ("beta", -1e-3), ("beta", "x"), ("alpha", True)):
        with pytest.raises(InputError, match=rf"^{integrator.name}: {key} = .*: a Rayleigh damping coefficient must"):
            integrator(**{key: value})
    assert integrator(alpha=2.0, beta=1e-4).alpha == 2.0  # numbers >= 0 are taken


def test_a_model_without_stiffness_has_no_critical_step():
    """ffd's lattice exerts no force: omega_max is 0 and the explicit step has no limit (it was 2 / 0, a
    ZeroDivisionError, reached when a step of it diverged and the message asked for dt_crit)."""
    mesh = stored_mesh("beam")
    model = build_model("ffd", mesh.points, mesh.tets, MAT)
    assert SymplecticEuler().critical_dt(model, omega2=0.0) == math.inf
    assert CentralDifference(beta=1e-3).critical_dt(model) == math.inf


def test_implicit_euler_cg_settings_are_checked():
    from realtime import InputError

    for kwargs, message in (
        ({"tol": 0.0}, r"tol = 0.0: CG's relative tolerance must be a number in \(0, 1\)"),
        ({"tol": float("nan")}, r"tol = nan"),
        ({"maxit": 0}, r"maxit = 0: must be a whole number of CG iterations >= 1"),
        ({"maxit": 10.5}, r"maxit = 10.5"),
    ):
        with pytest.raises(InputError, match=r"^implicit-euler: " + message):
            ImplicitEuler(**kwargs)


def test_model_options_are_checked_by_name_and_type():
    """An option a model does not take was a TypeError from its builder's signature; a threshold that
    is not a number, a TypeError from a comparison; tool vertices given as fractions were truncated."""
    from realtime import InputError, LoadingError

    mesh = stored_mesh("beam")
    with pytest.raises(
        InputError, match=r"^linear-tm: option 'treads' is not one of its options \(threads, precision\)"
    ):
        build_model("linear-tm", mesh.points, mesh.tets, MAT, treads=2)
    with pytest.raises(InputError, match=r"^hybrid-tm: threshold = 'a' must be a number >= 0 m"):
        build_model("hybrid-tm", mesh.points, mesh.tets, MAT, threshold="a")
    free, zero = np.ones((mesh.n_vertices, 3)), np.zeros((mesh.n_vertices, 3))
    n = mesh.n_vertices
    for vertices, message in (
        ([n], rf"vertices: {n} is outside 0..{n - 1}"),
        ([0.5], r"vertices: must be whole-number indices"),
    ):
        with pytest.raises(LoadingError, match=r"^Loading.translating_tool: " + message):
            Loading.translating_tool(free, zero, vertices, (0.0, 0.0, 1e-3))
