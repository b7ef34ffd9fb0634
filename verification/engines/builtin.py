"""The built-in engine: ``realtime``'s models behind the seam (``verification.engines.protocol``).

Everything the harness knows of ``realtime`` is here and in ``settling`` (how a time-stepping model
settles a static scene, and the cache of those settlings): which model a name builds (``model_for``),
each model's spec (``BuiltinEngine.models``), the critical step behind a default time step, and how a
trajectory is sampled between two steps. A study asks for runs (``verification.runs.simulate``), never
for a Model.
"""

from __future__ import annotations

import math
import time

import numpy as np

import realtime
from realtime import ImplicitEuler, State, SymplecticEuler, build_model, make_integrator, solve_static
from realtime.models import SPECS, adaptive_tm
from realtime.quasistatic import QuasiStatic

from .protocol import SceneInputs, Settling
from .settling import omega2_min_rest, omega2_rest, settled


def model_for(inputs: SceneInputs, model: str, **options):
    """The real-time Model of a scene (its SceneInputs), with its loading. adaptive-tm's mixed mesh gets
    the scene's loads as exactly as the scene's mesh (``SceneInputs.loading_on``)."""
    if model == adaptive_tm.NAME and inputs.loading_on is not None:
        from realtime.adaptive import adaptive_plan

        plan = adaptive_plan(inputs.points, inputs.tets, inputs.material, inputs.loading, **options)
        options = {**options, "plan": plan, "mixed_loading": inputs.loading_on(plan.points, plan.tets, plan.parent)}
    return build_model(model, inputs.points, inputs.tets, inputs.material, inputs.loading, **options)


def observed(model, u: np.ndarray) -> np.ndarray:
    """The displacements (..., N, 3) of the scene's N vertices in a model's u (..., V, 3): all of them,
    but for a model with vertices of its own after the scene's (adaptive-tm's midpoints)."""
    return u[..., : model.extra.get("observed", model.n_vertices), :]


class BuiltinSimulation:
    """A ``realtime`` Model on a scene with its integrator and State (the protocol's Simulation)."""

    def __init__(self, inputs: SceneInputs, model, integrator: str, options: dict):
        ts = inputs.time
        self.inputs, self.options, self.model_obj = inputs, options, model
        self.model = model.name
        self.quasi_static = SPECS[model.name].quasi_static
        self.integ = (
            QuasiStatic() if self.quasi_static else make_integrator(integrator, ts.damping_mass, ts.damping_stiffness)
        )
        self.integrator = self.integ.name
        slow = isinstance(self.integ, (ImplicitEuler, QuasiStatic))
        self.timing = (5, 7) if slow else (100, 9)
        self.state = model.rest_state()
        self.dt, self.dt_step_crit = None, None
        self._sample = None  # (u (V, 3), reaction (3,)) held at an instant, or None: the state's
        self.readapt = None  # a dynamic adaptive-tm run's re-adaptation (engines.readapting.Readapting)

    def critical_dt(self) -> float | None:
        """The explicit (symplectic Euler) critical step at rest, s; None for a quasi-static update."""
        if self.quasi_static:
            return None
        ts = self.inputs.time
        return SymplecticEuler(ts.damping_mass, ts.damping_stiffness).critical_dt(
            self.model_obj, omega2_rest(self.inputs, self.model_obj, self.options)
        )

    def start(self, dt: float | None) -> None:
        """Rest, stepping with dt (s), the integrator's blow-up guard armed with the critical step."""
        self.state = self.model_obj.rest_state()
        self.dt, self.dt_step_crit, self._sample = dt, self.critical_dt(), None
        if self.readapt is not None:
            self.readapt.start()

    @property
    def adaptation(self) -> list | None:
        """A re-adapting run's record (time, active tetrahedra and vertices, step at each check), or None."""
        return None if self.readapt is None else self.readapt.adaptation

    def advance_to(self, t: float) -> None:
        """Step until the step that passes t, holding the state at t by linear interpolation between the
        two steps around it (quasi-static: the equilibrium with the tools where they are at t). A
        re-adapting run stops at each check due by t, re-adapts, and goes on (the state at a check that
        falls on t is sampled before the mesh changes)."""
        last = None
        while self.readapt is not None and (due := self.readapt.due(t)) is not None:
            self._advance(due)
            sample = self._sample
            self.readapt.check()
            self._sample, last = sample, due
        if last is None or last < t - 1e-12:
            self._advance(t)

    def _advance(self, t: float) -> None:
        model, state = self.model_obj, self.state
        if self.quasi_static:
            self._sample = self.integ.equilibrium(model, t)
            return
        n = int(np.ceil((t - state.t) / self.dt - 1e-9))
        if n > 1:
            self.integ.step(model, state, self.dt, n - 1, dt_crit=self.dt_step_crit)
        if n >= 1:
            before, t_before = state.u.copy(), state.t
            self.integ.step(model, state, self.dt, 1, dt_crit=self.dt_step_crit)
            w = (t - t_before) / (state.t - t_before)
            u = (1.0 - w) * before + w * state.u
        else:
            u = state.u
        self._sample = (u, model.reaction(u))

    def settle(self, rtol: float, max_steps: int, dt: float | None, dt_fraction: float | None) -> Settling:
        """Equilibrium from rest (``settled``, cached; quasi-static: one update)."""
        model = self.model_obj
        if self.quasi_static:
            t1 = time.perf_counter()
            self._sample = self.integ.equilibrium(model)
            self.dt = 1e-3
            self.state = State.at_rest(model.n_vertices)
            static = {
                "method": "quasi-static update (precomputed responses / condensed surface system)",
                "steps": 1,
                "residual": None,
                "rtol": None,
                "wall_s": time.perf_counter() - t1,
            }
            meta = {"dt_crit_element": None, "omega_max": None}
            return Settling(1, None, None, None, static["wall_s"], static, meta)
        s = settled(self.inputs, model, self.integrator, dt, dt_fraction, rtol, max_steps, self.options)
        self.state, self.dt, self._sample = s.state.copy(), s.dt, (s.state.u, model.reaction(s.state.u))
        implicit = isinstance(self.integ, ImplicitEuler)
        static = {
            "method": "implicit Euler steps" if implicit else "damped dynamics (adaptive dynamic relaxation)",
            "steps": s.steps,
            "residual": s.residual,
            "rtol": rtol,
            "wall_s": s.wall_s,
        }
        if implicit:
            static["cg_iterations_last_step"] = s.cg_iterations
        meta = {"dt_crit_element": realtime.element_critical_dt(model), "omega_max": math.sqrt(s.omega2)}
        if implicit:
            meta = {"dt_crit_rest": s.dt_crit, **meta}
        return Settling(s.steps, s.residual, s.dt, s.dt_crit, s.wall_s, static, meta)

    def settle_steps(self, dt: float, steps: int) -> None:
        """Damped dynamics from rest for exactly ``steps`` steps of dt (s): a float32 twin's settling,
        whose residual cannot say when to stop, takes as many steps as its float64 run did, with its
        damping: omega_1 found once, under the float64 run's key (the precision does not change it)."""
        twin = {k: v for k, v in self.options.items() if k != "precision"}
        slowest = omega2_min_rest(self.inputs, self.model_obj, twin)
        static = solve_static(self.model_obj, dt=dt, steps=steps, omega2_min=slowest)
        self.state, self.dt, self._sample = static.state, dt, None

    def step(self, n: int) -> None:
        self.integ.step(self.model_obj, self.state, self.dt, n)
        self._sample = None

    def step_us(self) -> None:
        return None  # the harness times the built-in engine (``timing``)

    def displacement(self) -> np.ndarray:
        u = self.state.u if self._sample is None else self._sample[0]
        return observed(self.model_obj, u)

    def tool_force(self) -> np.ndarray:
        return self.model_obj.reaction(self.state.u) if self._sample is None else self._sample[1]

    def contact_area(self) -> np.ndarray:
        """(K,) float64, m^2: each rigid tool's contact area now (realtime.contact.areas), at the end of its
        travel (static scenes only take rigid tools)."""
        u = self.state.u if self._sample is None else self._sample[0]
        return self.model_obj.rigid_areas(u)


class BuiltinEngine:
    """``realtime``'s models (docs/models.md) as an Engine."""

    name = "realtime"
    models = SPECS

    def build(self, inputs: SceneInputs, model: str, integrator: str = "symplectic-euler", options: dict | None = None):
        options = dict(options or {})
        if model == adaptive_tm.NAME and inputs.time.mode == "dynamic" and inputs.loading_on is not None:
            from .readapting import Readapting, initial_model, readapting_options

            options = readapting_options(options)
            sim = BuiltinSimulation(inputs, initial_model(inputs, options), integrator, options)
            sim.readapt = Readapting(sim, options)
            return sim
        return BuiltinSimulation(inputs, model_for(inputs, model, **options), integrator, options)


BUILTIN = BuiltinEngine()


def scene_model(scene, model: str, **options):
    """The Model of a Scene, for what studies the built-in engine itself (its critical steps, its seeds
    experiments, its tests); a study of any engine runs through ``runs.simulate``."""
    from ..inputs import scene_inputs

    return model_for(scene_inputs(scene), model, **options)
