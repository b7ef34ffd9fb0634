"""How the built-in engine brings a time-stepping model to a static equilibrium, and what that costs:
the settling (damped dynamics at a fraction of the critical step, or implicit Euler steps) with its
disk cache, the omega_max^2 estimates behind the critical steps with their cache in this process, and
the refusal of a scene whose own answer lies past the blow-up guard (``UnboundedAnswerError``).
``BuiltinSimulation.settle`` calls ``settled``; a study that settles ahead of a timed run
(``studies.prefetch``) finds the cache entry by ``settled_path``.
"""

from __future__ import annotations

import json
import math
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshes.io import atomic_savez
from realtime import DivergenceError, ImplicitEuler, State, SymplecticEuler, build_model, make_integrator, solve_static
from realtime.models import linear_tm
from realtime.spectra import max_eigenvalue, min_eigenvalue
from realtime.statics import solve_static_implicit
from reference.progress import Progress

from ..cache import RUN_CODE, code_digest, digest, entry, library_versions, machine_id, read_cached
from ..progress import mpi_rank
from .protocol import SceneInputs

#: omega_max^2 (1/s^2) of M^-1 K for each (scene hash, model, options, at) computed in this process, at
#: "rest" or at the "settled" state (with the relaxation's rtol): a sweep asks for the same model's
#: critical step at every step fraction, and the eigenvalue and, for a non-linear model, the first
#: settling behind it are what its critical step costs.
_OMEGA2: dict[tuple, float] = {}

#: The most implicit Euler steps a static settling takes (it settles in tens where it settles at all).
IMPLICIT_MAX_STEPS = 20_000


def _omega2_key(inputs: SceneInputs, model_name: str, options: dict | None, *at) -> tuple:
    return (inputs.sha256, model_name, json.dumps(options or {}, sort_keys=True, default=str), *at)


def omega2_min_rest(inputs: SceneInputs, model, options: dict | None = None) -> float | None:
    """omega_1^2 (1/s^2) of ``model`` at rest where it is cheap (``min_eigenvalue``'s shift-invert; None
    where not), computed once per scene, model and options: the damping of every settling of it."""
    key = _omega2_key(inputs, model.name, options, "min")
    if key not in _OMEGA2:
        _OMEGA2[key] = min_eigenvalue(model, factored_only=True)
    return _OMEGA2[key]


def omega2_rest(inputs: SceneInputs, model, options: dict | None = None) -> float:
    """omega_max^2 (1/s^2) of ``model`` at rest, computed once per scene, model and options."""
    key = _omega2_key(inputs, model.name, options, "rest")
    if key not in _OMEGA2:
        _OMEGA2[key] = max_eigenvalue(model)
    return _OMEGA2[key]


@dataclass
class Settled:
    """A static scene settled by a time-stepping model (``settled``): the state at equilibrium, the
    steps it took from rest and the final relative residual, the step dt and the explicit critical step
    dt_crit (s) (the one dt was chosen from, or, for implicit Euler, the limit it steps over), omega_max^2
    (1/s^2) behind dt_crit, the settling's wall time (s) when it ran, and implicit Euler's CG iterations
    in its last step (-1 for an explicit integrator)."""

    state: State
    steps: int
    residual: float
    dt: float
    dt_crit: float
    omega2: float
    wall_s: float
    cg_iterations: int = -1


def settled_path(
    inputs: SceneInputs, model_name: str, integrator: str, dt, dt_fraction, rtol, max_steps, options
) -> Path:
    """Where ``settled`` keeps a settling: it holds the settling's wall time, so the machine is in its key,
    and its state depends on the libraries' versions (numba's and numpy's arithmetic)."""
    fields = {
        "code": code_digest(RUN_CODE),
        "libraries": library_versions(),
        "machine": machine_id(),
        "scene": inputs.sha256,
        "model": model_name,
        "integrator": integrator,
        "dt": dt,
        "fraction": dt_fraction,
        "rtol": rtol,
        "max_steps": max_steps,
        "options": json.dumps(options or {}, sort_keys=True, default=str),
    }
    return entry("settled", inputs.name, digest(fields), ".npz")


#: Settled's fields after the state, as the cache file stores them.
_SETTLED_NUMBERS = ("steps", "residual", "dt", "dt_crit", "omega2", "wall_s", "cg_iterations")


def settled(
    inputs: SceneInputs,
    model,
    integrator: str = "symplectic-euler",
    dt: float | None = None,
    dt_fraction: float | None = None,
    rtol: float = 1e-10,
    max_steps: int = 2_000_000,
    options: dict | None = None,
) -> Settled:
    """A static scene settled from rest by ``model`` (a Model) with ``integrator``, through a cache of
    settlings: the report settles its static scenes ahead on every core (``prefetch.settle_ahead``) and
    times the steps afterwards on a quiet machine. Raises DivergenceError or NotConvergedError as the
    solvers do (nothing is cached then).

    - Explicit: damped dynamics (``solve_static``) at dt, default ``dt_fraction`` (default 0.9) of the
      critical step; a non-linear model's is the smaller of rest's and equilibrium's (it moves as the
      body deforms), except that by default rest's stands where the equilibrium's is at most 5% shorter
      than 0.9 of it (EQUILIBRIUM_MARGIN: the equilibrium is found once).
    - Implicit Euler: steps of dt (default 2 / omega_1, the slowest mode's time scale, which it damps by
      1/sqrt(5) a step; or ``dt_fraction`` of the explicit critical step), at most IMPLICIT_MAX_STEPS.
    """
    path = settled_path(inputs, model.name, integrator, dt, dt_fraction, rtol, max_steps, options)
    kept = read_cached(path, _read_settled)
    if kept is not None:
        return kept
    ts = inputs.time
    integ = make_integrator(integrator, ts.damping_mass, ts.damping_stiffness)
    omega2 = omega2_rest(inputs, model, options)
    t1 = time.perf_counter()
    if isinstance(integ, ImplicitEuler):
        dt_crit = SymplecticEuler().critical_dt(model, omega2)
        if dt is None:
            dt = 2.0 / math.sqrt(min_eigenvalue(model)) if dt_fraction is None else dt_fraction * dt_crit
        ticker = Progress(f"settling: {inputs.name} / {model.name}, implicit step", rank=mpi_rank())
        static = solve_static_implicit(
            model,
            dt,
            rtol=rtol,
            integrator=integ,
            max_steps=min(max_steps, IMPLICIT_MAX_STEPS),
            progress=lambda k, res: ticker.tick(
                k, ": the tools on their way" if res is None else f": residual {res:.2e} of the load (asked {rtol:.0e})"
            ),
        )
        cg = integ.iterations
    else:
        static, dt, dt_crit, omega2 = _settle_explicit(
            inputs, model, integ, omega2, dt, dt_fraction, rtol, max_steps, options
        )
        cg = -1
    out = Settled(static.state, static.steps, static.residual, dt, dt_crit, omega2, time.perf_counter() - t1, cg)
    numbers = {k: getattr(out, k) for k in _SETTLED_NUMBERS}
    atomic_savez(path, u=out.state.u, v=out.state.v, t=out.state.t, state_steps=out.state.steps, **numbers)
    return out


#: A non-linear model settles first with solve_static's own step (0.9 of rest's critical step, shorter
#: only where a chunk diverged), which finds its equilibrium; that settling stands, at that step, when
#: the step is within this share of the equilibrium's critical step: a body that stiffens there by
#: less than 11% in omega_max^2 is stepped on at its equilibrium with a 5% margin. Otherwise it settles
#: again at 0.9 of the equilibrium's critical step. corotational-tm on the rates beam's 57 856
#: tetrahedra stiffened by 3e-5 at its equilibrium, and settled twice, 182 s each, for a step 1.6e-5
#: shorter.
EQUILIBRIUM_MARGIN = 0.95


def _settle_explicit(inputs, model, integ, omega2, dt, dt_fraction, rtol, max_steps, options):
    """Damped dynamics at dt (default a fraction of the critical step, a non-linear model's taken at
    equilibrium too; EQUILIBRIUM_MARGIN); returns the solve, dt, dt_crit and omega_max^2."""
    dt_crit = integ.critical_dt(model, omega2)
    ticker = Progress(f"settling: {inputs.name} / {model.name}, step", rank=mpi_rank())

    def progress(taken, residual):
        ticker.tick(taken, f": residual {residual:.2e} of the load (asked {rtol:.0e})")

    static = None
    slowest = omega2_min_rest(inputs, model, options)
    if not model.linear:
        key = _omega2_key(inputs, model.name, options, "settled", rtol)
        if key not in _OMEGA2:
            try:
                static = solve_static(
                    model, dt=None, rtol=rtol, max_steps=max_steps, progress=progress, omega2=omega2,
                    omega2_min=slowest,
                )  # fmt: skip
            except DivergenceError as exc:
                refuse_unbounded(inputs, exc)
                raise
            _OMEGA2[key] = max_eigenvalue(model, static.state.u)
        crit_eq = integ.critical_dt(model, max(omega2, _OMEGA2[key]))
        if dt is None and dt_fraction is None and 0.9 * dt_crit <= EQUILIBRIUM_MARGIN * crit_eq:
            dt = 0.9 * dt_crit  # rest's step stands (the first settling's, unless a chunk diverged)
        omega2, dt_crit = max(omega2, _OMEGA2[key]), min(dt_crit, crit_eq)
    if dt is None:
        dt = (0.9 if dt_fraction is None else dt_fraction) * dt_crit
    if static is None or static.dt != dt:
        try:
            static = solve_static(model, dt=dt, rtol=rtol, max_steps=max_steps, progress=progress, omega2_min=slowest)
        except DivergenceError as exc:
            refuse_unbounded(inputs, exc)
            raise
    return static, dt, dt_crit, omega2


def _read_settled(path: Path) -> Settled:
    """A Settled as ``settled`` keeps it (an .npz of the state and _SETTLED_NUMBERS)."""
    with np.load(path) as z:
        state = State(u=z["u"], v=z["v"], t=float(z["t"]), steps=int(z["state_steps"]))
        return Settled(state, *(z[k].item() for k in _SETTLED_NUMBERS))


class UnboundedAnswerError(DivergenceError):
    """A static settle blew up because the scene's own answer lies beyond the blow-up guard. To a study
    it is a divergence like any other (the stability study's extremes record it as one), with the
    cause named; to the command line it is the scene's input (exit 2)."""

    def __init__(self, exc: DivergenceError, message: str):
        self.step, self.dt, self.dt_crit, self.reason = exc.step, exc.dt, exc.dt_crit, exc.reason
        RuntimeError.__init__(self, message)


def refuse_unbounded(inputs: SceneInputs, exc: DivergenceError) -> None:
    """After a static settle blew up (``exc``): UnboundedAnswerError when the scene's own answer lies
    beyond the blow-up guard, so that no time step is blamed for it. The answer's size is the P1 linear
    equilibrium on the scene's mesh (a sparse solve where it fits, as the quasi-static models do); a load
    far too large for the stiffness (a unit slip, a soft body under its own weight) puts it past 10 times
    the body, where the guard stops every run at any step. Otherwise nothing: the divergence is the run's."""
    import scipy.sparse.linalg as spla

    from realtime.integrators import blowup_bound
    from realtime.linsolve import FACTOR_LIMIT

    if inputs.has_tools:
        return
    loading = inputs.loading
    free = np.flatnonzero(loading.free.reshape(-1) != 0.0)
    if not len(free) or len(free) > FACTOR_LIMIT:
        return
    linear = build_model(linear_tm.NAME, inputs.points, inputs.tets, inputs.material, loading)
    K = linear.rest_stiffness()[free][:, free].tocsc()
    u = spla.spsolve(K, loading.external_force.reshape(-1)[free])
    reach, bound = float(np.abs(u).max()), blowup_bound(linear)
    if np.isfinite(reach) and reach > bound:
        raise UnboundedAnswerError(
            exc,
            f"{inputs.source}: load: the scene's own static answer reaches {reach:.3g} m (P1, linear), beyond 10 "
            f"times the body ({bound:.3g} m), where every run stops at any time step: the load is far too large for "
            "this stiffness; lower the load, raise young, or check the units (scale, Pa, kg/m^3)",
        ) from None
