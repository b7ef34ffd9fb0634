"""The engine seam (docs/architecture.md section 11): the built-in engine answers the protocol, and an
engine no study knows, registered beside it, is run and judged by the same calls."""

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from realtime import build_model
from realtime.errors import InputError
from verification import engines
from verification.engines.builtin import BUILTIN
from verification.engines.protocol import Engine, SceneInputs, Settling, Simulation
from verification.inputs import scene_inputs
from verification.runs.compare import compare
from verification.runs.simulate import run_model
from verification.scene_file import load_scene


class DirectP1:
    """A plug-in engine: the P1 linear-elastic equilibrium by one sparse solve (what a settled
    linear-tm reaches by damped dynamics), built from the scene's arrays alone."""

    name = "direct-p1"
    models = ("direct-p1",)

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict):
        return _DirectSimulation(inputs)


class _DirectSimulation:
    model, integrator, timing = "direct-p1", "sparse LU", (3, 3)

    def __init__(self, inputs: SceneInputs):
        self.inputs = inputs
        self.u = np.zeros_like(inputs.points)

    def critical_dt(self):
        return None

    def start(self, dt):
        self.u[:] = 0.0

    def advance_to(self, t):
        raise NotImplementedError("a static engine")

    def settle(self, rtol, max_steps, dt, dt_fraction):
        i = self.inputs
        linear = build_model("linear-tm", i.points, i.tets, i.material.replace(law="linear"), i.loading)
        free = np.flatnonzero(i.loading.free.reshape(-1) != 0.0)
        K = linear.rest_stiffness()[free][:, free].tocsc()
        self.u.reshape(-1)[free] = spla.spsolve(K, i.loading.external_force.reshape(-1)[free])
        self.reaction = linear.reaction(self.u)
        return Settling(1, None, None, None, 0.0, {"method": "sparse LU", "steps": 1})

    def step(self, n):
        pass

    def displacement(self):
        return self.u

    def tool_force(self):
        return self.reaction


def test_the_builtin_engine_answers_the_protocol():
    scene = load_scene("cantilever")
    inputs = scene_inputs(scene)
    assert isinstance(BUILTIN, Engine) and set(engines.ENGINES) == {"realtime"}
    sim = BUILTIN.build(inputs, "linear-tm", "symplectic-euler", {})
    assert isinstance(sim, Simulation)
    # the scene's arrays as the protocol documents them
    assert inputs.points.shape == (scene.mesh.n_vertices, 3) and inputs.points.dtype == np.float64
    assert inputs.tets.shape == (scene.mesh.n_tets, 4) and inputs.loading.free.shape == inputs.points.shape
    assert inputs.sha256 == scene.sha256() and inputs.source == str(scene.path)


def test_an_unknown_model_names_the_engines_models():
    with pytest.raises(InputError, match=r"no engine offers 'nope'; the models are .*linear-tm"):
        engines.engine_for("nope")


def test_a_plug_in_engine_is_run_and_judged_through_the_seam(monkeypatch):
    """A linear static scene: the plug-in's direct P1 solve and linear-tm settled by damped dynamics
    (rtol 1e-10) are one linear system, so compare gives both the same error against the reference, to
    the settling's tolerance (1e-7 of the error, far above 1e-10 of the load)."""
    monkeypatch.setitem(engines.ENGINES, "direct-p1", DirectP1())
    scene = load_scene("cantilever").with_material(law="linear")
    res = run_model(scene, "direct-p1")
    assert res.meta["solver"] == "direct-p1" and res.meta["model"] == "direct-p1"
    assert res.meta["integrator"] == "sparse LU"
    assert res.meta["static"]["method"] == "sparse LU" and res.meta["step_us"] > 0.0
    ours = compare(scene, "linear-tm", degree=1, budget=False)
    theirs = compare(scene, "direct-p1", degree=1, budget=False)
    assert theirs.status == "ok" and theirs.rel_l2 > 0.0
    assert theirs.rel_l2 == pytest.approx(ours.rel_l2, rel=1e-7)
