"""Static equilibrium of a real-time model by damped dynamics: explicit (dynamic relaxation) or by
implicit Euler steps.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

from .contact import travel_end
from .errors import InputError
from .integrators import DivergenceError, ImplicitEuler, NotConvergedError, SymplecticEuler
from .model import Model, State
from .spectra import max_eigenvalue, min_eigenvalue


@dataclass
class StaticResult:
    """Outcome of ``solve_static``: state at equilibrium, steps taken, final relative residual."""

    state: State
    steps: int
    residual: float
    dt: float


#: A settling stops once its residual is within this factor of its round-off floor (residual_floor).
FLOOR_FACTOR = 10.0
#: A settling whose residual, above 1000 rtol, has not fallen by 10% in this many chunks will not settle:
#: it ends then, not at max_steps. hybrid-tm switching tetrahedra between its laws on the rates beam
#: (57 856 tetrahedra) sat near 6e-3 for 300 000 steps, ten minutes; a run that converges, however slowly
#: (a slender body's slowest mode a thousand times below its fastest), gains 10% in far fewer steps.
STALLED_CHUNKS = 250


def residual_floor(model: Model, u: np.ndarray, scale: float, f: np.ndarray | None = None, force=None) -> float:
    """The round-off floor of a relative residual at ``u`` (N, 3) m: |f(u') - f(u)| / ``scale`` (N) over
    the free components, u' = u with every component moved by one unit in the last place (alternating
    signs: deterministic). No iteration can tell residuals below it apart: they are what rounding u to
    float64 changes in the force. A damped run settles to a plateau a few times above it (the force's
    own summation adds as much). On the cantilever refined twice linear-tm's floor is 2.3e-10: the run
    stops at 57 400 steps, at 2.3e-9; by the stall rule alone its residual stalled at 2.0e-9 and it
    ended after 74 000 steps, a count the summation order decided (69 600 with the two-thread kernel,
    whose sums differ by round-off). ``f`` (N, 3) N: the internal force at u, if the caller has it;
    ``force``: the force function, u -> f, that made it (default ``model.internal_force``; a settling
    passes its integrator's, whose hybrid-tm remembers which law each vertex is under)."""
    lo = model.loading
    force = model.internal_force if force is None else force
    signs = np.where(np.arange(u.size).reshape(u.shape) % 2 == 0, 1.0, -1.0)
    moved = u + signs * np.spacing(u)
    delta = (force(moved) - (force(u) if f is None else f)) * lo.free
    return float(np.linalg.norm(delta)) / scale


def solve_static(
    model: Model,
    dt: float | None = None,
    rtol: float = 1e-10,
    max_steps: int = 2_000_000,
    chunk: int = 200,
    safety: float = 0.9,
    steps: int | None = None,
    progress=None,
    omega2: float | None = None,
    omega2_min: float | None = None,
) -> StaticResult:
    """Static equilibrium under the full loads by damped explicit dynamics (dynamic relaxation).

    Symplectic Euler with mass damping alpha = 2 omega_1, critical for the slowest mode (``_Damping``:
    omega_1 at rest where it is cheap to know, else Underwood's estimate every ``chunk`` steps). The tools move
    along their ramps from t = 0 (a load path: a large displacement imposed in one step would crush the
    elements beside the tool before the rest of the body can follow; a rigid tool given no ramp follows
    ``_RigidPath``) and then hold. Converged when every tool has arrived and the free components' residual
    |f_int + f_ext| is below rtol times the load scale (|f_ext| and the tools' reaction), or below
    FLOOR_FACTOR times its round-off floor where that is higher (``residual_floor``; up to 1000 rtol), or
    has stalled for 50 chunks on a plateau below 1000 rtol (``StaticResult.residual`` says which).

    With ``dt`` given, every step uses it, and a dt above the critical one raises DivergenceError as
    any explicit run does. With dt = None the step adapts: ``safety`` x dt_crit at rest, and when a
    non-linear model stiffens (tension, compression) and a chunk diverges, the solve returns to the
    last good chunk, re-estimates omega_max there and goes on at ``safety`` times the new critical step.
    ``StaticResult.dt`` is the step in use at the end.

    ``steps``: take exactly that many steps and return, whatever the residual (``_step_budget``: a float32
    model needs it). ``progress``: called as progress(steps taken, relative residual) after every chunk.
    ``omega2``: omega_max^2 (1/s^2) at rest (``spectra.max_eigenvalue``), where the caller knows it.
    ``omega2_min``: omega_1^2 (1/s^2) at rest, where the caller knows it; 0: Underwood's (``_Damping``).
    """
    max_steps = _step_budget(model, steps, max_steps)
    state, lo = model.rest_state(), model.loading
    arrived = _arrival(lo)
    free = lo.free
    omega2 = max_eigenvalue(model) if omega2 is None else omega2
    dt_crit = 2.0 / math.sqrt(omega2)
    adaptive = dt is None
    dt = safety * dt_crit if adaptive else dt
    integ, damping = SymplecticEuler(alpha=0.0), _Damping(model, omega2, omega2_min)
    force = functools.partial(integ.static_force, model)  # as the steps see it (hybrid-tm's memory too)
    path = _RigidPath(model)
    taken, residual, best, since_best = 0, np.inf, np.inf, 0
    fmag = float(np.linalg.norm(lo.external_force * free))
    while taken < max_steps:
        integ.alpha = damping.alpha
        good = state.copy()
        n = min(chunk, max_steps - taken)  # the budget is a number of steps, not of chunks
        path.move(integ, model)
        try:
            integ.step(model, state, dt, n, dt_crit=dt_crit)
        except DivergenceError:
            if not adaptive or model.linear:
                raise
            state = good
            omega2, dt_crit = _stiffer(model, state, omega2, dt_crit)
            dt = safety * dt_crit
            continue
        taken += n
        f = force(state.u)
        scale = max(fmag, float(np.linalg.norm(model.reaction(state.u))), 1e-300)
        residual = float(np.linalg.norm((f + lo.external_force) * free)) / scale
        if progress is not None:
            progress(taken, residual)
        if state.t >= arrived and path.done and steps is None:
            best, since_best = (residual, 0) if residual < 0.9 * best else (best, since_best + 1)
            if _converged(model, state.u, residual, rtol, scale, f, best, since_best, force):
                break
            if since_best >= STALLED_CHUNKS:
                raise _not_settled(model, residual, rtol, taken, dt, omega2, damping.alpha, state.u, chunk * since_best)
        damping.update(model, state.u, free, omega2, force)
    else:
        if steps is None:
            raise _not_settled(model, residual, rtol, taken, dt, omega2, damping.alpha, state.u)
    state.v[:] = 0.0
    state.steps = taken
    return StaticResult(state=state, steps=taken, residual=residual, dt=dt)


#: A static solve moves a rigid tool given no ramp (its whole travel at once) along a load path of its own,
#: at most this fraction of the shortest edge at its candidate vertices between two chunks of steps: at
#: once, a tool 1 mm into a block of 1 mm cells put the vertices it held on its surface in one step and
#: inverted the cells beside them (neohookean-tm diverged at its second step; the truth steps its load).
RIGID_PATH_FRACTION = 0.25


class _RigidPath:
    """The load path of the rigid tools with no ramp in a static solve: ``move`` before each chunk sets each
    one's translation (Integrator.set_rigid_tool) a chunk further, until ``done``."""

    def __init__(self, model: Model):
        c = model.loading.contacts
        self.tools, self.chunks, self.moved = [], 0, 0
        if c is None:
            return
        for k in range(c.count):
            mine = c.vertex[c.tool == k]
            if c.ramp[k] > 0.0 or not len(mine):
                continue
            near = model.tets[np.isin(model.tets, mine).any(axis=1)]
            x = model.points[near]
            edge = min(float(np.linalg.norm(x[:, i] - x[:, j], axis=1).min()) for i in range(4) for j in range(i))
            self.chunks = max(self.chunks, math.ceil(np.linalg.norm(c.travel[k]) / (RIGID_PATH_FRACTION * edge)))
            self.tools.append((k, c.travel[k].copy()))

    @property
    def done(self) -> bool:
        return self.moved >= self.chunks

    def move(self, integ, model: Model) -> None:
        if self.done:
            return
        self.moved += 1
        for k, travel in self.tools:
            integ.set_rigid_tool(model, k, travel * (self.moved / self.chunks))


def _arrival(lo) -> float:
    """When every tool, prescribed or rigid, has arrived (s): the ramps' end."""
    prescribed = float(lo.tool_ramp.max()) if len(lo.tool_ramp) else 0.0
    return max(prescribed, 0.0 if lo.contacts is None else travel_end(lo.contacts))


class _Damping:
    """solve_static's mass damping alpha = 2 omega_1 (1/s), critical for the slowest mode: every mode then
    decays at least as fast as exp(-omega_1 t), the most one mass damping gives them all. omega_1^2 at
    rest is ``omega2_min`` (1/s^2), else ``spectra.min_eigenvalue`` where the rest stiffness can be
    factored (shift-invert: milliseconds on the scenes' meshes, 11 s on SOFA's liver refined twice), and
    the damping is held. Where it cannot be, omega_1^2 is re-estimated every chunk by the Rayleigh
    quotient of the free displacement (``_damping``, Underwood's adaptive dynamic relaxation), which
    exceeds omega_1^2 where the displacement is local (a tool's) and so overdamps the slowest mode: SOFA's
    liver pressed by its tool settled in 34 400 steps with it (stvk-tm), in 6 000 at 2 omega_1; refined
    once, 113 200 and 17 600; the cantilever 20 200 and 9 400 (the equilibria equal to 1e-9)."""

    def __init__(self, model: Model, omega2: float, omega2_min: float | None):
        omega2_min = min_eigenvalue(model, factored_only=True) if omega2_min is None else omega2_min
        self.held = omega2_min is not None and omega2_min > 0.0
        self.alpha = 2.0 * math.sqrt(omega2_min) if self.held else 2.0 * math.sqrt(omega2) * 1e-3

    def update(self, model: Model, u: np.ndarray, free: np.ndarray, omega2: float, force) -> None:
        """The next chunk's damping: held, or re-estimated at u (N, 3) m (``_damping``)."""
        if not self.held:
            self.alpha = _damping(model, u, free, omega2, self.alpha, force)


def _not_settled(model: Model, residual, rtol, taken: int, dt: float, omega2: float, alpha: float, u, stalled: int = 0):
    """The error of a settling that ran out of steps, or (``stalled`` > 0) whose residual has not fallen
    by 10% in its last ``stalled`` steps; omega2 (1/s^2) and alpha (1/s): its fastest mode and damping,
    as last estimated (alpha = 2 omega_1); u (N, 3) m where it stopped (the error's ``u``)."""
    error = _not_settled_text(model, residual, rtol, taken, dt, omega2, alpha, stalled)
    error.u = np.array(u)
    return error


def _not_settled_text(model: Model, residual, rtol, taken: int, dt: float, omega2: float, alpha: float, stalled: int):
    """``_not_settled``'s error, its words."""
    slow = math.sqrt(omega2) / max(0.5 * alpha, 1e-300)
    if stalled:
        return NotConvergedError(
            f"{model.name}: damped dynamics reached a relative residual of {residual:.2e} (asked {rtol:.1e}) in "
            f"{taken} steps of {dt:.3g} s and has not fallen by 10% in its last {stalled} steps: it does not "
            "settle (a model that switches between laws, or a state with no equilibrium); settle with "
            "implicit Euler"
        )
    return NotConvergedError(
        f"{model.name}: damped dynamics reached a relative residual of {residual:.2e} "
        f"(asked {rtol:.1e}) in {taken} steps of {dt:.3g} s: its slowest mode is about {slow:.2g} times "
        "slower than its fastest (a slender or finely meshed body), and explicit steps settle it in about "
        "that many steps per tenfold; allow more steps, or settle with implicit Euler"
    )


def _converged(
    model: Model, u, residual: float, rtol: float, scale: float, f, best: float, since_best: int, force
) -> bool:
    """solve_static's stopping rule: the residual below rtol, or within 1000 rtol and below FLOOR_FACTOR
    times its round-off floor, or a plateau within 1000 rtol that has not improved for 50 chunks (the
    residual reached is reported)."""
    if residual < rtol:
        return True
    if residual < 1e3 * rtol and residual < FLOOR_FACTOR * residual_floor(model, u, scale, f, force):
        return True
    return since_best >= 50 and best < 1e3 * rtol


def _stiffer(model: Model, state: State, omega2: float, dt_crit: float) -> tuple[float, float]:
    """After a chunk diverged, back at its start (``state``, at rest now): omega_max^2 re-estimated there
    and the new critical step, half the old one where the estimate did not move (instead of looping)."""
    omega2 = max(omega2, max_eigenvalue(model, state.u))
    new_crit = 2.0 / math.sqrt(omega2)
    state.v[:] = 0.0
    return omega2, (new_crit if new_crit < dt_crit else 0.5 * dt_crit)


def _step_budget(model: Model, steps, max_steps: int) -> int:
    """The steps solve_static may take: ``steps`` exactly where given (a whole number), else ``max_steps``;
    InputError for a float32 model without ``steps``. The rounding of u to float32 puts a residual floor
    far above any tolerance (1.3e-2 of the load on the cantilever, K amplifying the rounding's high
    frequencies, also when the residual is evaluated in float64), reached long before u has converged
    (after 2000 steps its u was 4.5e-2 off the equilibrium, after 8000 steps 3e-6, then no closer), so
    no residual can say when to stop. Given the steps its float64 twin took at the same dt, the float32
    run has made the same progress and differs from it by round-off (``verification``'s sweep does this)."""
    if steps is None and model.precision != "float64":
        raise InputError(
            f"solve_static: {model.name} was built with precision = {model.precision!r}, whose residual cannot show "
            "convergence; pass steps (the count its float64 twin took at the same dt)"
        )
    if steps is None:
        return max_steps
    if isinstance(steps, bool) or not isinstance(steps, (int, np.integer)) or steps < 0:
        raise InputError(f"solve_static: steps = {steps!r}: must be a whole number of steps >= 0")
    return int(steps)


def _damping(model: Model, u: np.ndarray, free: np.ndarray, omega2: float, alpha: float, force) -> float:
    """The mass damping 2 omega_1 of the next chunk, omega_1^2 the Rayleigh quotient
    u_f.K(u) u_f / u_f.M u_f of the free displacement u_f, K(u) the tangent stiffness at the current
    state applied to the free part alone (K_fp u_p is no stiffness of the free system): a central
    difference of the force along u_f, exact for a linear model. ``alpha`` where the quotient says
    nothing (u_f = 0, or a non-positive quotient). ``force``: u -> the internal force, as the steps see it."""
    uf = u * free
    den = float(np.sum(model.mass[:, None] * uf * uf))
    if den <= 0.0:
        return alpha
    h = 1e-4 / max(float(np.abs(uf).max()), 1e-300) * float(np.abs(u).max() + 1e-12)
    kuf = (force(u - h * uf) - force(u + h * uf)) / (2.0 * h)
    rq = float(np.sum(kuf * uf)) / den
    return 2.0 * math.sqrt(min(rq, omega2)) if rq > 0.0 else alpha


def solve_static_implicit(
    model: Model,
    dt: float,
    rtol: float = 1e-10,
    max_steps: int = 20_000,
    integrator: ImplicitEuler | None = None,
    progress=None,
) -> StaticResult:
    """Static equilibrium by implicit Euler steps of dt (its numerical damping settles every mode a
    large step resolves poorly): the tools follow their ramps, then the loop stops when the free
    residual is below rtol times the load scale. Raises NotConvergedError past ``max_steps``.
    ``progress``: called as progress(steps taken, relative residual or None before the tools arrive)
    after every step, as solve_static's (a step of a large body's CG can take seconds)."""
    integ = integrator if integrator is not None else ImplicitEuler(tol=min(1e-10, rtol))
    lo = model.loading
    state = model.rest_state()
    arrived = _arrival(lo)
    fmag = float(np.linalg.norm(lo.external_force * lo.free))
    residual = best = np.inf
    since_best = 0
    path = _RigidPath(model)
    for k in range(1, max_steps + 1):
        path.move(integ, model)
        integ.step(model, state, dt, 1)  # raises NotConvergedError when CG stops short (unless a budget)
        if state.t < arrived or not path.done:
            if progress is not None:
                progress(k, None)
            continue
        r = (integ.static_force(model, state.u) + lo.external_force) * lo.free
        scale = max(fmag, float(np.linalg.norm(model.reaction(state.u))), 1e-300)
        residual = float(np.linalg.norm(r)) / scale
        if progress is not None:
            progress(k, residual)
        if residual < 0.9 * best:
            best, since_best = residual, 0
        else:
            since_best += 1
        # a round-off floor (a nearly incompressible system, condition number 1e8, stalls near 4e-10):
        # accept a plateau within 1000 rtol that has not improved for 50 steps, as solve_static does,
        # and report the residual reached; a plateau above it will not come down either
        if residual < rtol or (since_best >= 50 and best < 1e3 * rtol):
            state.v[:] = 0.0
            return StaticResult(state=state, steps=k, residual=residual, dt=dt)
        if since_best >= 50:
            break
    raise NotConvergedError(
        f"{model.name}: implicit Euler reached a relative residual of {best:.2e} "
        f"(asked {rtol:.1e}) in {k} steps of {dt:.3g} s"
    )
