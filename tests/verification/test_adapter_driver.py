"""The adapters' shared driver (adapters/exported.py: the relaxation, its stall and hold rules), on an
engine made up in numpy: vertices on springs to their rest places, stepped by symplectic Euler, with a
noise that stands for an engine's round-off. The driver needs numpy alone: it is loaded from its file here,
as the adapters load it in the engines' venv."""

from __future__ import annotations

import importlib.util
import sys

import numpy as np
import pytest

from verification.engines.adapters import ADAPTERS_DIR


def adapter_module(name: str):
    """The module ``adapters/NAME.py``, loaded from its file once (the adapters import each other by name)."""
    if name not in sys.modules:
        spec = importlib.util.spec_from_file_location(name, ADAPTERS_DIR / f"{name}.py")
        module = importlib.util.module_from_spec(spec)
        sys.modules[name] = module
        spec.loader.exec_module(module)
    return sys.modules[name]


@pytest.fixture(scope="module")
def driver():
    return adapter_module("exported")


def _scene(driver, load: float):
    """Four vertices of a tetrahedron, vertex 0 held, the others pushed along z by ``load`` N each."""
    points = np.array([[0.0, 0.0, 0.0], [0.01, 0.0, 0.0], [0.0, 0.01, 0.0], [0.0, 0.0, 0.01]])
    free = np.ones_like(points)
    free[0] = 0.0
    force = np.zeros_like(points)
    force[1:, 2] = load
    spec = {"time": {"mode": "static", "output_times_s": [0.0]}, "materials": [{"density_kg_m3": 1000.0}]}
    empty = np.zeros((0, 3))
    return driver.Exported(spec, points, np.array([[0, 1, 2, 3]]), np.zeros(1, int), free, force,
                           np.zeros(0, int), empty, np.zeros((1, 0, 3)))  # fmt: skip


def _numpy_stepper(driver, scene):
    """The made-up engine's state and accessors: positions and velocities (N, 3) m, m/s, 1 g a vertex."""

    class NumpyStepper(driver.Stepper):
        def __init__(self):
            self.x, self.v = scene.points.copy(), np.zeros_like(scene.points)

        def positions(self):
            return self.x.copy()

        def set_positions(self, x):
            self.x = x.copy()

        def velocities(self):
            return self.v.copy()

        def set_velocities(self, v):
            self.v = v.copy()

        def masses(self):
            return np.full(len(self.x), 1e-3)

    return NumpyStepper


def _engine(driver, scene, noise: float, epsilon: float = 2.0**-52, seed: int = 0):
    """Springs of 100 N/m from each vertex to its rest place; ``noise`` m of random position error added at
    every step (an engine's round-off, or a relaxation that cycles when it is large), in an arithmetic of
    machine epsilon ``epsilon``."""
    rng = np.random.default_rng(seed)

    class Springs(_numpy_stepper(driver, scene)):
        def step(self, dt):
            f = -100.0 * (self.x - scene.points) + scene.external_force
            self.v = np.where(scene.held(), 0.0, self.v + dt * f / 1e-3)
            self.x = self.x + dt * self.v + np.where(scene.held(), 0.0, noise * rng.standard_normal(self.x.shape))

    engine = Springs()
    engine.epsilon = epsilon
    return engine


def _springs(driver, scene, k: np.ndarray):
    """Springs of stiffness ``k`` (N, 1) N/m from each vertex to its rest place, no noise, stepped by
    symplectic Euler, with the engine's own elastic force."""

    class Springs(_numpy_stepper(driver, scene)):
        def step(self, dt):
            f = -k * (self.x - scene.points) + scene.external_force
            self.v = np.where(scene.held(), 0.0, self.v + dt * f / 1e-3)
            self.x = self.x + dt * self.v

        def internal_force(self):
            return -k * (self.x - scene.points)

    return Springs


def test_an_unloaded_body_holds_at_its_round_off(driver):
    """A body nothing loads yet (a rigid tool short of it) sits at rest to its engine's round-off: the hold
    measured that noise against a displacement of nothing and read "no equilibrium" (newton's float32 on
    the liver press, 0.21 of its displacement at a quarter of the travel). It holds."""
    scene = _scene(driver, 0.0)
    engine = _engine(driver, scene, noise=1e-10, epsilon=float(np.finfo(np.float32).eps))  # its floor: 9.5e-9 m
    out = driver.relax(engine, scene, 1e-4, 1e-10, 20_000, lambda text: None)
    assert out["settled"] == 1 and out["hold_drift"] <= driver.HOLD


def test_a_budget_spent_at_round_off_is_a_stall_and_one_spent_far_from_it_is_not_settled(driver):
    """The stall rules wait for 40 ramps (8000 steps); a budget that runs out before (the adapter's wall,
    MuJoCo's 63 ms steps on the liver) left a run at its round-off "not settled". At the budget, the same
    evidence decides: a change below STALLED failing to halve is a stall, said so (``budget_spent``); a
    run still moving by more than that is not settled."""
    scene = _scene(driver, 1e-3)  # 1 mN on 100 N/m: 10 um
    quiet = driver.relax(_engine(driver, scene, noise=1e-12), scene, 1e-4, 1e-14, 3000, lambda text: None)
    assert quiet["settled"] == 1 and quiet["budget_spent"] == 1
    assert driver.STALLED > quiet["stalled_at"] > 0.0
    np.testing.assert_allclose(quiet["u"][1:, 2], 1e-5, rtol=1e-5)
    loud = driver.relax(_engine(driver, scene, noise=1e-6), scene, 1e-4, 1e-14, 3000, lambda text: None)
    assert loud["settled"] == 0 and "budget_spent" not in loud


@pytest.mark.parametrize("residual", [False, True])
def test_a_budget_spent_within_its_tolerance_is_the_answer_however_it_still_falls(driver, residual):
    """Springs of 100, 1 and 0.05 N/m: kinetic damping's restarts, paced by the stiff one, bring the soft one
    in slowly, its change (or, where the engine gives its net force, its residual) still halving when the
    budget runs out. At 20 000 steps it is within BUDGET_TOLERANCE (the answer right to 1e-9): a stall at
    the budget, said so. At 6000 steps it is 1e-3 from its answer: not settled."""
    scene = _scene(driver, 1e-3)
    k = np.array([0.0, 100.0, 1.0, 0.05])[:, None]

    class Soft(_springs(driver, scene, k)):
        def net_force(self):
            return np.where(scene.held(), 0.0, self.internal_force() + scene.external_force) if residual else None

    done = driver.relax(Soft(), scene, 1e-4, 1e-14, 20_000, lambda text: None)
    assert done["settled"] == 1 and done["budget_spent"] == 1
    assert (done["residual"] if residual else done["stalled_at"]) <= driver.BUDGET_TOLERANCE
    np.testing.assert_allclose(done["u"][1:, 2], 1e-3 / k[1:, 0], rtol=1e-9)
    short = driver.relax(Soft(), scene, 1e-4, 1e-14, 6000, lambda text: None)
    assert short["settled"] == 0


def test_a_float32_body_pressed_a_little_stalls_at_its_round_offs_walk(driver):
    """A float32 engine's change walks by some round-offs in a position (``round_off``) whatever the
    displacement: under a small one (a sphere just pressing) that walk is above STALLED of it, and the
    run went to its budget unsettled (newton's semi-implicit solver at half the liver press's travel).
    Below WALK round-offs the change has stalled: the run settles in the stall rules' 8000 steps, and its
    state holds. Under the old rule (STALLED alone) this run is unsettled at 60 000 steps."""
    scene = _scene(driver, 3e-3)  # 3 mN on 100 N/m: 30 um; its floor 9.5e-9 m
    engine = _engine(driver, scene, noise=1e-8, epsilon=float(np.finfo(np.float32).eps))  # a walk of ~16 floors
    out = driver.relax(engine, scene, 1e-4, 1e-10, 60_000, lambda text: None)
    assert out["settled"] == 1 and out["budget_spent"] == 0 and out["steps"] < 10_000
    assert driver.WALK * driver.round_off(engine, scene) / 3e-5 > out["stalled_at"] > driver.STALLED
    np.testing.assert_allclose(out["u"][1:, 2], 3e-5, rtol=1e-2)  # the walk's size: a few 1e-3 of it


def test_a_change_within_the_walk_has_stalled_though_it_still_halves(driver):
    """A float32 run's change can still shrink like 1 / n below its round-off walk (the liver press at its full
    travel: 3 round-offs and halving, into the 300 s wall). Below WALK round-offs nothing finer can be seen:
    the run stalls there, halving or not. Made up: springs whose load creeps as 1 + 0.69 / n, a change over
    the last quarter of 0.23 u / n, 3 round-offs at 8000 steps and halving with every doubling; under the
    old rule it was still moving at its 60 000 steps."""
    scene = _scene(driver, 0.1)  # 100 mN on 100 N/m: 1 mm; its floor 9.5e-9 m

    class Creeping(_numpy_stepper(driver, scene)):
        n = 0

        def step(self, dt):
            self.n += 1
            f = -100.0 * (self.x - scene.points) + scene.external_force * (1.0 + 0.69 / self.n)
            self.v = np.where(scene.held(), 0.0, self.v + dt * f / 1e-3)
            self.x = self.x + dt * self.v

    engine = Creeping()
    engine.epsilon = float(np.finfo(np.float32).eps)
    out = driver.relax(engine, scene, 1e-4, 1e-10, 60_000, lambda text: None)
    assert out["settled"] == 1 and out["steps"] < 10_000 and out["budget_spent"] == 0
    assert out["stalled_at"] * 1e-3 < driver.WALK * driver.round_off(engine, scene)


def test_a_residual_on_a_plateau_near_its_tolerance_stops_as_the_built_in_models_do(driver, monkeypatch):
    """Springs of 100, 1 and 0.05 N/m whose net force, as the engine gives it, carries a floor of twice the
    tolerance (MuJoCo's explicit flex sat at 1.6e-10 of the load against 1e-10 from step 40 000 on): the run
    stops PLATEAU_STEPS after its residual last fell by 10 %, as a built-in model's settling accepts such a
    plateau (realtime/statics.py), with its answer; the halving rule alone, which looks back over half the
    run, waits about as long again as the run took to reach the floor. A floor above PLATEAU_FACTOR times
    the tolerance is left to the halving rule."""
    scene = _scene(driver, 1e-3)
    k = np.array([0.0, 100.0, 1.0, 0.05])[:, None]
    rtol = 1e-9

    class Floored(_springs(driver, scene, k)):
        def __init__(self, floor: float = 2.0 * rtol * np.sqrt(3.0) * 1e-3):  # N: twice the tolerance of the
            super().__init__()  # residual's scale, the elastic force's norm at equilibrium (three 1 mN)
            self.floor = floor

        def net_force(self):
            net = np.where(scene.held(), 0.0, self.internal_force() + scene.external_force)
            net[1, 0] += self.floor
            return net

    plateau = driver.relax(Floored(), scene, 1e-4, rtol, 200_000, lambda text: None)
    assert plateau["settled"] == 1 and plateau["residual"] / rtol == pytest.approx(2.0, rel=0.1)
    np.testing.assert_allclose(plateau["u"][1:, 2], 1e-3 / k[1:, 0], rtol=1e-6)
    above = 2e3 * rtol * np.sqrt(3.0) * 1e-3  # a floor above PLATEAU_FACTOR times the tolerance
    high = driver.relax(Floored(above), scene, 1e-4, rtol, 200_000, lambda text: None)
    monkeypatch.setattr(driver, "PLATEAU_STEPS", 10**9)  # the halving rule alone
    halving = driver.relax(Floored(), scene, 1e-4, rtol, 200_000, lambda text: None)
    assert halving["steps"] > plateau["steps"] + 5000, (plateau["steps"], halving["steps"])  # measured 6850 more
    assert driver.relax(Floored(above), scene, 1e-4, rtol, 200_000, lambda text: None)["steps"] == high["steps"]


def test_a_residual_level_where_the_state_no_longer_moves_is_the_engines_fixed_point(driver):
    """An engine whose step stops moving the state once its own measure of the net force is below its own
    tolerance (an implicit step solved to 1e-6 of the load: MuJoCo's discrete flex sat at 3.7e-6 of it on
    the hanging bar, 9.6e-8 on the cantilever, its state not moving at all) ends at that fixed point, said
    so (``fixed_point``): no tolerance finer than its own can be reached by more steps. Here the soft
    spring brings the residual to the engine's tolerance at step 20 000; the run stops 3700 steps later, when
    it has not halved over the last half, and its answer is its own tolerance's."""
    scene = _scene(driver, 1e-3)
    k = np.array([0.0, 100.0, 1.0, 0.05])[:, None]
    own = 1e-6 * np.sqrt(3.0) * 1e-3  # N: 1e-6 of the residual's scale (the three 1 mN loads' norm)

    class Frozen(_springs(driver, scene, k)):
        def step(self, dt):
            if np.linalg.norm(self.net_force()) > own:
                super().step(dt)

        def net_force(self):
            return np.where(scene.held(), 0.0, self.internal_force() + scene.external_force)

    out = driver.relax(Frozen(), scene, 1e-4, 1e-10, 200_000, lambda text: None)
    assert out["fixed_point"] == 1 and out["settled"] == 1 and out["budget_spent"] == 0
    assert out["steps"] - out["tail_steps"] < 25_000
    assert 1e-10 < out["residual"] <= 1e-6
    np.testing.assert_allclose(out["u"][1:, 2], 1e-3 / k[1:, 0], rtol=1e-5)


def test_a_level_residual_within_the_budget_tolerance_is_a_floor_however_the_state_jitters(driver):
    """A contact solver keeps its engine's residual at a noise floor, the state jittering by as much for as
    long as it runs (MuJoCo's on the plane press: 3e-10 to 3e-8 of the load). A level within
    BUDGET_TOLERANCE is such a floor: the run stops once its last half makes no progress on its first (from
    RESIDUAL_WINDOW ramps), not a fixed point, its answer within the noise. Made up: springs whose positions
    take 1e-12 m of noise a step (10 um loads)."""
    scene = _scene(driver, 1e-3)
    Noisy = type(_engine(driver, scene, noise=1e-12))

    class Jittering(Noisy):
        def net_force(self):
            return np.where(scene.held(), 0.0, -100.0 * (self.x - scene.points) + scene.external_force)

    engine = Jittering()
    engine.epsilon = 2.0**-52
    out = driver.relax(engine, scene, 1e-4, 1e-10, 200_000, lambda text: None)
    assert out["fixed_point"] == 0 and out["settled"] == 1 and out["budget_spent"] == 0
    assert out["steps"] < 40 * 200  # before the halving rule's window (measured 3500)
    assert 1e-10 < out["residual"] <= driver.BUDGET_TOLERANCE
    np.testing.assert_allclose(out["u"][1:, 2], 1e-5, rtol=1e-5)
