"""adaptive-tm on a dynamic scene, re-adapted as it runs (``realtime.readapt``), behind the seam.

The run starts on the scene's mesh (level 0: nothing has deformed yet) and, every ``every`` seconds
of simulated time (default: the scene's output interval), asks each tetrahedron for its indicator,
refines and merges (``readapt.adapted_sets``), rebuilds the model on the new mixed mesh with the
scene's loading on it (``SceneInputs.loading_on``) and carries the state over. Smaller tetrahedra
have a shorter critical step, and a deformed StVK body a shorter one than at rest: after each change the
step is the run's fraction of the new model's critical step at rest or at the state reached, whichever
is shorter, and for an explicit integrator at most MIXED_FRACTION of it. ``adaptation`` records, at each check, the
time, the active tetrahedra and vertices and the step: the result's meta carries it.
"""

from __future__ import annotations

from realtime import build_model
from realtime.adaptive import coarse_plan, expand, plan_of
from realtime.integrators import ImplicitEuler, SymplecticEuler
from realtime.model import State
from realtime.models import adaptive_tm
from realtime.readapt import INDICATORS, adapted_sets, carried, indicator
from realtime.spectra import max_eigenvalue
from reference.progress import Progress

from ..progress import mpi_rank
from .protocol import SceneInputs

#: What a dynamic adaptive-tm run re-adapts by, unless its options say otherwise: the a-posteriori
#: estimator, one level below the scene's mesh, refining at 0.3 of the largest indicator. One level by
#: default for its cost: on cantilever-dynamic two levels reach 11 600 tetrahedra at 6.5e-6 s steps, and
#: the report's sweep (three steps, each with its error budget's run at an eighth of it) took 160 s more.
DEFAULTS = {"criterion": "estimator", "levels": 1, "threshold": 0.3}
#: The largest fraction of a mixed mesh's critical step a re-adapted run steps at. On cantilever-dynamic,
#: from the state its re-adapted mesh had reached at 50 ms, 0.9 of the critical step (at rest or at that
#: state, the larger omega) grew without bound within 700 steps and 0.8 stayed bounded: the light
#: vertices of small tetrahedra beside large ones, in a body StVK stiffens as it deforms, leave less
#: margin than a uniform mesh. 0.7 keeps a margin beyond what was measured.
MIXED_FRACTION = 0.7
#: The options a re-adapting run takes (``every``: s between checks).
OPTIONS = ("criterion", "levels", "threshold", "every")


def readapting_options(options: dict) -> dict:
    """The run's options with the defaults; InputError (one line) for a criterion not in INDICATORS."""
    from realtime.errors import InputError

    out = {**DEFAULTS, **{k: v for k, v in options.items() if k in OPTIONS}}
    if out["criterion"] not in INDICATORS:
        raise InputError(f"adaptive-tm: criterion = {out['criterion']!r}: one of {', '.join(INDICATORS)}")
    if "every" in out and not (isinstance(out["every"], (int, float)) and out["every"] > 0):
        raise InputError(f"adaptive-tm: every = {out['every']!r}: seconds between checks, > 0")
    if not (isinstance(out["threshold"], (int, float)) and 0.0 <= out["threshold"] <= 1.0):
        raise InputError(f"adaptive-tm: threshold = {out['threshold']!r}: a fraction of the largest indicator, 0 to 1")
    return out


def initial_model(inputs: SceneInputs, options: dict):
    """adaptive-tm on the scene's mesh alone, its hierarchy ``levels`` deep."""
    return _model(inputs, coarse_plan(inputs.points, inputs.tets, options["levels"]))


def _model(inputs: SceneInputs, plan):
    mixed_loading = inputs.loading_on(plan.points, plan.tets, plan.parent)
    return build_model(
        adaptive_tm.NAME,
        inputs.points,
        inputs.tets,
        inputs.material,
        inputs.loading,
        plan=plan,
        mixed_loading=mixed_loading,
    )


class Readapting:
    """The re-adaptation of a BuiltinSimulation's adaptive-tm run (its ``readapt`` hook)."""

    def __init__(self, sim, options: dict):
        self.sim, self.options = sim, options
        self.every = options.get("every", sim.inputs.time.output_every)
        self.adaptation: list[dict] = []
        self.next = self.every
        self.fraction = None

    def start(self) -> None:
        sim = self.sim
        self.fraction = None if not sim.dt_step_crit else sim.dt / sim.dt_step_crit
        self.next = self.every
        self.adaptation = [self._record()]
        checks = int(round(self.sim.inputs.time.end / self.every))
        self.ticker = Progress(
            f"run: adaptive-tm re-adapted by its {self.options['criterion']}, check", checks, mpi_rank()
        )

    def _record(self) -> dict:
        sim = self.sim
        plan = sim.model_obj.extra["plan"]
        return {"t": sim.state.t, "tets": len(plan.tets), "vertices": plan.n_model, "dt": sim.dt}

    def due(self, t: float) -> float | None:
        """The next check at or before t (s), or None."""
        return self.next if self.next <= t + 1e-12 else None

    def check(self) -> None:
        """Re-adapt at the state reached (module docstring)."""
        sim = self.sim
        self.next += self.every
        model, state = sim.model_obj, sim.state
        plan = model.extra["plan"]
        u_full = expand(state.u, plan.hanging)
        eta = indicator(plan, _materials(sim.inputs), u_full, self.options["criterion"])
        sets = adapted_sets(plan, eta, self.options["threshold"], u_full)
        if sets is not None:
            new_plan = plan_of(plan.hierarchy, sets, plan.strain)
            new = _model(sim.inputs, new_plan)
            u = carried(plan, new_plan, state.u, expand)
            v = carried(plan, new_plan, state.v, expand)
            sim.model_obj = new
            sim.state = State(u=u, v=v, t=state.t, steps=state.steps)
            if self.fraction is not None:
                ts = sim.inputs.time
                omega2 = max(max_eigenvalue(new), max_eigenvalue(new, u))  # StVK stiffens as it deforms
                crit = SymplecticEuler(ts.damping_mass, ts.damping_stiffness).critical_dt(new, omega2)
                explicit = not isinstance(sim.integ, ImplicitEuler)  # implicit Euler steps over the limit
                sim.dt = (min(self.fraction, MIXED_FRACTION) if explicit else self.fraction) * crit
                sim.dt_step_crit = crit
        self.adaptation.append(self._record())
        last = self.adaptation[-1]
        self.ticker.tick(
            len(self.adaptation) - 1, f", t = {last['t']:.4g} s: {last['tets']} tetrahedra, dt = {last['dt']:.3g} s"
        )


def _materials(inputs: SceneInputs):
    from realtime.material import Materials

    return Materials.of(inputs.material, len(inputs.tets))
