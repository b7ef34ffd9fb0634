"""The engine inside a simulator: the tool force a step returns, two threads on one model, a cut model.

A surgical simulator steps the engine from a haptic thread while a visual thread runs beside it, and the
haptic device renders the force the tools feel. These tests hold the engine to what such a simulator
relies on (docs/engine-internals.md, "Embedding the engine").
"""

import threading

import numpy as np
import pytest

from meshes import stored_mesh
from meshes.generators import box
from realtime import (
    CentralDifference,
    ImplicitEuler,
    InputError,
    Loading,
    Material,
    State,
    SymplecticEuler,
    build_model,
)
from realtime.models.linear_tm import cut
from realtime.spectra import min_eigenvalue
from verification.engines.builtin import scene_model
from verification.scene_file import load_scene

MAT = Material(5e5, 0.45, 1000.0, law="stvk")


def _floating_block(model_name: str):
    """A 2 cm block with no support, pulled up at one face by a tool (ramp 2 ms) under gravity: nothing
    but the tool acts on it besides its weight, so its momentum changes by exactly the tool's force."""
    mesh = box((0.02, 0.02, 0.02), 0.005)
    top = np.flatnonzero(mesh.points[:, 2] > 0.02 - 1e-9)
    n = mesh.n_vertices
    # the tool holds z only: x and y stay free
    load = Loading.translating_tool(np.ones((n, 3)), np.zeros((n, 3)), top, (0.0, 0.0, 2e-3), 2e-3, mask=[0, 0, 1])
    model = build_model(model_name, mesh.points, mesh.tets, MAT, load)
    gravity = model.mass[:, None] * np.array([0.0, 0.0, -9.81])
    return model, gravity


@pytest.mark.parametrize(
    "model_name, integ",
    [
        ("stvk-tm", SymplecticEuler(alpha=30.0, beta=1e-5)),
        ("mass-spring", SymplecticEuler(alpha=30.0)),
        ("linear-tm", ImplicitEuler(alpha=30.0, beta=1e-5, tol=1e-13)),
        ("stvk-tm", ImplicitEuler(alpha=30.0, tol=1e-13)),
    ],
    ids=["stvk-symplectic", "springs-symplectic", "linear-implicit", "stvk-implicit"],
)
def test_the_tool_force_a_step_returns_is_the_momentum_the_tool_gives_the_body(model_name, integ):
    """Newton's second law for the whole body: internal forces cancel, so the total momentum changes in a
    step by (the tool's force + the weight - the mass damping) dt. The force ``step`` returns must close
    that balance at every step, inertia included: during the ramp's start (a velocity jump) it is
    dominated by m a, and the static reaction -(f_int + f_ext) misses it. Symplectic Euler's discrete
    balance is exact (round-off: 1e-9 of the largest term, the elastic forces that cancel); implicit
    Euler's holds to its CG tolerance (1e-13 relative, so 1e-8 of the terms here)."""
    model, gravity = _floating_block(model_name)
    integ.set_forces(model, gravity)
    dt = 1e-5
    state = State.at_rest(model.n_vertices)
    m = model.mass[:, None]
    worst = 0.0
    inertia_seen = 0.0
    for _ in range(400):
        before = (m * state.v).sum(axis=0)
        force = integ.step(model, state, dt, 1)
        assert force.shape == (1, 3)
        after = (m * state.v).sum(axis=0)
        balance = (after - before) / dt + integ.alpha * after - gravity.sum(axis=0)
        elastic = np.abs(model.internal_force(state.u)).sum()
        worst = max(worst, float(np.abs(balance - force[0]).max()) / max(elastic, float(np.abs(force).max())))
        static = model.tool_reactions(state.u)[0]
        inertia_seen = max(inertia_seen, float(np.abs(force[0] - static).max() / max(np.abs(force[0]).max(), 1e-30)))
    tol = 1e-9 if isinstance(integ, SymplecticEuler) else 1e-7
    assert worst < tol, f"momentum balance off by {worst:.2e} of the forces"
    assert inertia_seen > 0.1, "the tool force never differed from the static reaction: inertia left out?"


@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference, ImplicitEuler])
def test_the_settled_tool_force_equals_the_references_reaction_on_cantilever_pull(cls):
    """cantilever-pull with stvk-tm, stepped from rest along the tool's ramp with damping until it
    settles: the force the last ``step`` returns is the P1 StVK reference's reaction on the same mesh
    (dolfinx, the same discrete problem: cross-code agreement). Tolerance 1e-6: the settling stops at a
    velocity of 1e-9 of the tool's travel per second; the reference's Newton is at 1e-10."""
    from reference.fem import ElasticityProblem

    scene = load_scene("cantilever-pull")
    model = scene_model(scene, "stvk-tm")
    ep = ElasticityProblem(scene.mesh, scene.material, scene.problem, degree=1)
    ep.solve_newton()
    reaction = ep.reaction()
    omega1 = float(np.sqrt(min_eigenvalue(model)))
    integ = cls(alpha=2.0 * omega1)
    dt = 0.5 * CentralDifference().critical_dt(model) if cls is not ImplicitEuler else 2e-4
    state = State.at_rest(model.n_vertices)
    for _ in range(2000):
        force = integ.step(model, state, dt, 50)
        if state.t > 0.5 and np.abs(state.v).max() < 1e-9 * 0.01:
            break
    assert force.shape == (1, 3)
    assert np.linalg.norm(force[0] - reaction) / np.linalg.norm(reaction) < 1e-6
    assert np.linalg.norm(model.reaction(state.u) - reaction) / np.linalg.norm(reaction) < 1e-6


@pytest.mark.parametrize(
    "model_name, threads",
    [("linear-tm", 1), ("stvk-tm", 1), ("corotational-tm", 1), ("hybrid-tm", 1), ("mass-spring", 1)]
    + [("linear-tm", 2), ("stvk-tm", 2), ("corotational-tm", 2)],
)
def test_two_threads_stepping_two_states_on_one_model_match_serial_runs_bit_for_bit(model_name, threads):
    """One model, two integrators, two states with different pulls, stepped at the same time from two
    threads (the kernels release the GIL, so they do run at once on two cores): each state ends bit for
    bit where a serial run takes it. With the kernels' scratch in the model, as before, the two threads
    wrote each other's element blocks. A threaded model (``threads`` = 2) launches its kernels' own
    threads from both at once, which numba's workqueue layer would abort on."""
    mesh = stored_mesh("liver")
    n = mesh.n_vertices
    free = np.ones((n, 3))
    free[mesh.points[:, 2] < mesh.points[:, 2].min() + 0.01] = 0.0
    loading = Loading(free=free, external_force=np.zeros((n, 3)))
    model = build_model(
        model_name, mesh.points, mesh.tets, MAT, loading, **({"threads": threads} if threads > 1 else {})
    )
    pulls = [model.mass[:, None] * np.array(g) for g in ([0.0, 0.0, -400.0], [300.0, 0.0, 100.0])]
    dt = 0.3 * CentralDifference().critical_dt(model)

    def run(pull, out, key):
        integ = SymplecticEuler(alpha=20.0)
        integ.set_forces(model, pull)
        state = State.at_rest(n)
        try:
            for _ in range(60):
                integ.step(model, state, dt, 5)
        except Exception as exc:  # a thread's failure is the test's (shared scratch blew runs up)
            out[key] = exc
            return
        out[key] = state.u.copy()

    serial = {}
    for k, pull in enumerate(pulls):
        run(pull, serial, k)
    parallel = {}
    threads = [threading.Thread(target=run, args=(pull, parallel, k)) for k, pull in enumerate(pulls)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not np.array_equal(serial[0], serial[1])  # two different runs, or the test proves nothing
    for k in range(2):
        assert not isinstance(parallel[k], Exception), f"thread {k} raised {parallel[k]}"
        assert np.array_equal(parallel[k], serial[k]), f"thread {k} differs from its serial run"


@pytest.mark.parametrize("integrator", [SymplecticEuler, CentralDifference, ImplicitEuler])
def test_one_integrator_called_from_a_second_thread_mid_step_refuses(integrator):
    """An integrator's workspace is its own: two threads stepping through one integrator at once
    overwrote each other's forces and returned wrong states without a word. The second call now
    raises at once, and the first run ends where a serial run does. The first call is held inside its
    step until the second has been refused (an event, not a race against the machine's speed)."""
    from realtime import InputError

    mesh = stored_mesh("liver")
    n = mesh.n_vertices
    free = np.ones((n, 3))
    free[mesh.points[:, 2] < mesh.points[:, 2].min() + 0.01] = 0.0
    model = build_model("linear-tm", mesh.points, mesh.tets, MAT, Loading(free=free, external_force=np.zeros((n, 3))))
    dt = 0.5 / np.sqrt(model.element_eigenvalue_bound())  # a quarter of a lower bound on the critical step
    pull = model.mass[:, None] * np.array([0.0, 0.0, -400.0])

    def run(integ, out):
        integ.set_forces(model, pull)
        state = State.at_rest(n)
        integ.step(model, state, dt, 20)
        out.append(state.u.copy())

    serial, shared, caught = [], integrator(alpha=20.0), []
    run(integrator(alpha=20.0), serial)
    inside, release = threading.Event(), threading.Event()
    steps = shared._step

    def held(*args):  # the first thread's step, entered (its lock taken) and held until released
        inside.set()
        assert release.wait(60.0), "the test never released the first thread"
        return steps(*args)

    shared._step = held
    first = threading.Thread(target=run, args=(shared, caught))
    first.start()
    try:
        assert inside.wait(60.0), "the first thread never started its step"
        with pytest.raises(
            InputError, match=rf"^{integrator.name}: this integrator is already stepping in another thread"
        ):
            shared.step(model, State.at_rest(n), dt, 1)
    finally:
        release.set()
        first.join()
    assert np.array_equal(caught[0], serial[0])
    shared.step(model, State.at_rest(n), dt, 1)  # free again once the first call returned


def test_a_cut_model_refuses_to_step_and_its_successor_steps():
    """cut updates the stiffness tensors in place (a cost proportional to the cut, as a haptic frame
    needs), which the model before the cut shares: stepping it would mix the old masses with the new
    stiffness. Every integrator refuses it with a one-line error instead."""
    mesh = stored_mesh("beam")
    model = build_model("linear-tm", mesh.points, mesh.tets, Material(5e5, 0.45, 1000.0))
    integ = SymplecticEuler()
    state = State.at_rest(mesh.n_vertices)
    integ.step(model, state, 1e-6, 1)
    after = cut(model, [0, 1, 2])
    with pytest.raises(
        InputError,
        match=r"linear-tm: this model.s mesh was changed 1 time\(s\) since it was built \(cut, slit or sutured\)",
    ):
        integ.step(model, state, 1e-6, 1)
    with pytest.raises(InputError, match="this model.s mesh was changed"):
        ImplicitEuler().step(model, state, 1e-6, 1)
    integ.step(after, state, 1e-6, 1)
    again = cut(after, [3])
    with pytest.raises(InputError, match="changed 1 time"):
        integ.step(after, state, 1e-6, 1)
    integ.step(again, state, 1e-6, 1)


def test_the_readmes_haptic_loop_runs_and_the_device_feels_the_liver_push_back(capsys):
    """The embedding example (docs/embedding.md), shortened to 0.3 s: it runs at 1 kHz on its recorded trajectory and prints
    the force the device renders, which at 0.25 s (the tool pressed 4 mm into the liver's top) points
    up, out of the liver. Nothing here is timed: the jitter it prints is the machine's."""
    import importlib.util
    from pathlib import Path

    path = Path(__file__).parents[2] / "examples" / "haptic_loop.py"
    spec = importlib.util.spec_from_file_location("haptic_loop", path)
    example = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(example)
    assert example.main(["--seconds", "0.3"]) == 0
    out = capsys.readouterr().out
    line = next(ln for ln in out.splitlines() if ln.startswith("t =  0.25 s"))
    fz = float(line.split("device force")[1].split()[2])
    assert fz > 0.1, line
    assert "300 frames: compute" in out and "jitter" in out


@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference, ImplicitEuler])
def test_the_compiled_entry_point_steps_exactly_as_numbas_dispatcher(cls, monkeypatch):
    """After its first call a workspace calls the step loop's compiled entry point, which skips numba's
    typing of twenty arguments (5 us of a haptic loop's call). A run through it, with the tool moved
    every frame, is bit for bit the run through the dispatcher."""
    from realtime import integrators

    mesh = stored_mesh("beam")
    n = mesh.n_vertices
    tip = np.flatnonzero(mesh.points[:, 0] > mesh.points[:, 0].max() - 1e-9).astype(np.int64)
    free = np.ones((n, 3))
    free[mesh.points[:, 0] < 1e-9] = 0.0
    free[tip] = 0.0
    load = Loading.translating_tool(free, np.zeros((n, 3)), tip)
    model = build_model("stvk-tm", mesh.points, mesh.tets, MAT, load)
    dt = 0.5 * CentralDifference().critical_dt(model)

    def run():
        integ, state = cls(alpha=10.0), State.at_rest(n)
        forces = []
        for k in range(40):
            integ.set_tool(model, 0, translation=[0.0, 0.0, 2e-5 * k])
            forces.append(integ.step(model, state, dt, 2))
        return state.u.copy(), np.array(forces), integ._prepared.entries

    fast_u, fast_f, entries = run()
    assert all(entry is not loop for loop, entry in entries.items())  # the entry point was taken
    monkeypatch.setattr(integrators, "_call", lambda p, loop, args: loop(*args))
    slow_u, slow_f, _ = run()
    assert np.array_equal(fast_u, slow_u) and np.array_equal(fast_f, slow_f)


@pytest.mark.parametrize("cls", [SymplecticEuler, CentralDifference, ImplicitEuler, "quasi-static"])
def test_a_wrong_state_or_step_is_a_one_line_error_not_a_crash(cls):
    """The kernels index u and v without bounds checks: a shorter array would be written past its end.
    Every integrator checks what step is given and names it."""
    from realtime.quasistatic import QuasiStatic

    mesh = stored_mesh("beam")
    n = mesh.n_vertices
    name = "precomputed" if cls == "quasi-static" else "linear-tm"
    model = build_model(name, mesh.points, mesh.tets, Material(5e5, 0.45, 1000.0))
    integ = QuasiStatic() if cls == "quasi-static" else cls()
    good = State.at_rest(n)
    shape = rf"\({n}, 3\)"
    cases = [
        (
            State(u=np.zeros((n - 1, 3)), v=np.zeros((n, 3))),
            1e-6,
            1,
            rf"State.u: must be a writable C-contiguous {shape} float64 array, got a \({n - 1}, 3\) float64 array",
        ),
        (State(u=np.zeros((n, 3), np.float32), v=np.zeros((n, 3))), 1e-6, 1, "got a .* float32 array"),
        (State(u=np.zeros((3, n)).T, v=np.zeros((n, 3))), 1e-6, 1, "that is not C-contiguous and writable"),
        (State(u=np.zeros((n, 3)), v=[[0.0] * 3] * n), 1e-6, 1, "State.v: .* got a list"),
        (State(u=np.zeros((n, 3)), v=np.zeros((n, 3)), t=float("nan")), 1e-6, 1, r"State.t = nan: must be a finite"),
        (good, 0.0, 1, r"step: dt = 0.0: must be a positive number of s"),
        (good, "1e-6", 1, r"step: dt = '1e-6'"),
        (good, 1e-6, -1, r"step: n = -1: must be a whole number of steps >= 0"),
        (good, 1e-6, 2.5, r"step: n = 2.5"),
        (good, float("inf"), 1, r"step: dt = inf"),
        (State(u=np.zeros((n, 3)), v=np.zeros((n, 3)), t=float("inf")), 1e-6, 1, r"State.t = inf"),
    ]
    frozen = np.zeros((n, 3))
    frozen.flags.writeable = False
    cases.append((State(u=np.zeros((n, 3)), v=frozen), 1e-6, 1, "State.v: .* that is not C-contiguous and writable"))
    for state, dt, steps, message in cases:
        with pytest.raises(InputError, match=message):
            integ.step(model, state, dt, steps)
    # what the exact-type fast path does not take, the full check still accepts: numpy scalars, an int t
    for dt, steps, t in ((np.float64(1e-6), np.int64(1), 0), (1e-6, 1, np.float64(0.0)), (1, 0, 0.0)):
        integ.step(model, State(u=np.zeros((n, 3)), v=np.zeros((n, 3)), t=t), dt, steps)
