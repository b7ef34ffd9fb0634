"""Dynamic scenes: the trajectory runner, the reference's trajectory, and their comparison."""

import numpy as np
import pytest

from realtime import State, SymplecticEuler
from verification.engines.builtin import BUILTIN, scene_model
from verification.inputs import scene_inputs
from verification.runs.compare import compare
from verification.runs.reference import reference_result
from verification.runs.simulate import output_times, run_model, trajectory
from verification.scene_file import load_scene


@pytest.fixture(scope="module")
def scene():
    return load_scene("cantilever-dynamic")


def test_trajectory_interpolates_between_steps(scene):
    """Sampling at output times equals stepping exactly onto them when dt divides the interval, and is
    a linear interpolation otherwise (checked against a run that lands on the instant)."""
    model = scene_model(scene, "linear-tm")
    integ = SymplecticEuler(scene.time.damping_mass, scene.time.damping_stiffness)  # as the run steps
    dt = 0.5 * integ.critical_dt(model)
    times = np.array([0.0, 7.3 * dt, 12.0 * dt])
    sim = BUILTIN.build(scene_inputs(scene), "linear-tm", "symplectic-euler", {})
    sim.start(dt)
    u, _ = trajectory(sim, times)
    st = State.at_rest(model.n_vertices)
    integ.step(model, st, dt, 7)
    u7 = st.u.copy()
    integ.step(model, st, dt, 1)
    np.testing.assert_allclose(u[1], 0.7 * u7 + 0.3 * st.u, rtol=0, atol=1e-15)
    integ.step(model, st, dt, 4)
    np.testing.assert_allclose(u[2], st.u, rtol=0, atol=1e-15)
    assert np.all(u[0] == 0.0)


def test_dynamic_reference_follows_the_tool(scene):
    ref = reference_result(scene)
    assert np.allclose(ref.times, output_times(scene))
    tip = scene.mesh.points[:, 0] > 0.1 - 1e-9
    # the tool's prescribed motion, exactly: the smooth ramp at t = 10 ms (output 2), s = 0.2, has made
    # 10 s^3 - 15 s^4 + 6 s^5 = 0.05792 of its 5 mm; all of it from t = 50 ms on
    np.testing.assert_allclose(ref.displacement[2][tip, 2], -0.005 * 0.05792, atol=1e-12)
    np.testing.assert_allclose(ref.displacement[10][tip, 2], -0.005, atol=1e-12)
    np.testing.assert_allclose(ref.displacement[-1][tip, 2], -0.005, atol=1e-12)
    assert ref.meta["ref_err_estimate"] == ref.meta["ref_err_space"] + 2 * ref.meta["ref_err_time"]
    # the tool's force has a bar by the same rule (a haptic verdict on a dynamic scene is judged with it)
    f = ref.meta
    assert f["ref_reaction_err_estimate"] == f["ref_reaction_err_space"] + 2 * f["ref_reaction_err_time"]
    assert 0.0 < f["ref_reaction_err_estimate"] < 1.0


@pytest.mark.parametrize("model", ["linear-tm", "stvk-tm", "precomputed", "condensed"])
def test_models_on_a_dynamic_scene(scene, model):
    ref = reference_result(scene)
    out = compare(scene, model, reference=ref)
    assert out.status == "ok"
    # P1 on a two-element-thick beam against P2: a few per cent, never a blow-up or a zero
    assert 1e-3 < out.rel_l2 < 0.2
    assert out.reaction_rel_err is not None


def test_quasi_static_models_agree_on_the_surface(scene):
    a = run_model(scene, "precomputed").displacement
    b = run_model(scene, "condensed").displacement
    surf = scene.mesh.surface_vertices
    assert np.linalg.norm(a[:, surf] - b[:, surf]) / np.linalg.norm(a[:, surf]) < 1e-10
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-10  # condensed recovers the interior for output
