"""Time integrators: what a simulator calls each frame.

Every integrator advances a ``State`` by n steps of size dt in one compiled call
(``integrator.step(model, state, dt, n)``): the loop (``realtime.steppers``), the model's force kernel,
the tools and the blow-up check all run in numba with the GIL released, so a haptic thread can call it.
The spectra behind the critical steps are in ``realtime.spectra``, implicit Euler's factored
preconditioner in ``realtime.linsolve``, static equilibrium by damped dynamics in ``realtime.statics``.

Equations of motion, with lumped masses m_i and Rayleigh damping C = alpha M + beta K:

    m_i a_i = f_int(u + beta v)_i + f_ext_i + f_contact(u, t)_i - alpha m_i v_i

f_contact: the rigid tools' penalty force (``realtime.contact``), on the surface vertices near a tool.

Evaluating the internal force at u + beta v is exactly -K u - beta K v for a linear model and the
tangent stiffness damping to first order for a non-linear one, with no extra matrix.

Stability: both explicit schemes are stable for dt <= dt_crit = (2 / omega_max)(sqrt(1 + xi^2) - xi),
omega_max^2 the largest eigenvalue of M^-1 K on the free components and xi = beta omega_max / 2 the
stiffness damping ratio of that mode. The mass damping alpha is implicit in symplectic Euler's velocity
update (v <- (v + dt a) / (1 + dt alpha)) and trapezoidal in central difference's two half kicks
(second order), so it costs no stability however large it is: the static relaxation sets it near
2 omega_1 and, early on, near 2 omega_max. A run whose displacement leaves a bound (ten times the
mesh's bounding-box diagonal: an unstable run grows geometrically and crosses it in a few dozen steps)
or becomes NaN raises ``DivergenceError`` naming the step, dt and dt_crit.
"""

from __future__ import annotations

import math
import threading
from dataclasses import dataclass, field

import numpy as np

from .contact import Contacts, no_contacts
from .contact import forces as contact_forces
from .errors import InputError, float_array, is_real
from .linsolve import FACTOR_LIMIT, NO_FACTOR, factorise
from .model import TOOL_ROTATION, Model, State, Tools
from .spectra import max_eigenvalue
from .steppers import (
    CG,
    CGWork,
    StepWork,
    _run_central_difference,
    _run_implicit_euler,
    _run_symplectic_euler,
    se_sum_update_threads,
    se_update,
    step_work,
)
from .threaded import UNSUMMED

_JIT = dict(nogil=True, cache=True)


class DivergenceError(RuntimeError):
    """An explicit run blew up; carries the step, the time step and the critical one."""

    def __init__(self, model: str, step: int, dt: float, dt_crit: float, integrator: str, reason: str = ""):
        self.step, self.dt, self.dt_crit, self.reason = step, dt, dt_crit, reason
        super().__init__(
            f"{model} with {integrator} diverged at step {step}: dt = {dt:.4g} s, "
            f"critical dt = {dt_crit:.4g} s (ratio {dt / dt_crit:.3g})" + (f"; {reason}" if reason else "")
        )


def _blowup_reason(model: Model, u: np.ndarray) -> str:
    """Which of the two blow-up criteria fired: a non-finite value, or the displacement bound."""
    if not np.all(np.isfinite(u)):
        return "the displacement became NaN or infinite"
    return (
        f"the displacement reached {float(np.abs(u).max()):.3g} m, beyond 10 x the body's size "
        f"({blowup_bound(model):.3g} m)"
    )


class NotConvergedError(RuntimeError):
    """Damped dynamics did not reach static equilibrium within the step budget. ``u``: the displacement
    (N, 3) m where it stopped, where the solver gives it (``realtime.statics.solve_static``), else None."""

    u: np.ndarray | None = None


def blowup_bound(model: Model) -> float:
    """Displacement beyond which a run is declared diverged: 10 x the bounding-box diagonal, m."""
    return 10.0 * float(np.linalg.norm(model.points.max(axis=0) - model.points.min(axis=0)))


@dataclass
class _Prepared:
    """Per-model arrays of the step kernels (see Integrator._prepare): the integrator's workspace, which
    also holds what a simulator changes between frames (``set_forces``, ``set_tool``)."""

    model: Model
    inv_mass: np.ndarray  # (N,) 1/kg
    per_dof: np.ndarray  # (3N, 2): free mask / m (1/kg), free f_ext / m (m/s^2)
    fext: np.ndarray  # (N, 3) N, the external forces applied: the Loading's until set_forces
    tools: Tools  # the Loading's, with the targets (vector, angle, ramp) copied for set_tool
    bound: float  # m, the blow-up bound
    n_free: int  # the free components: implicit Euler's preconditioner depends on their count
    shape: tuple  # (N, 3), the State's arrays' shape
    dtype: np.dtype  # the State's arrays' float type (Model.dtype)
    f: np.ndarray  # (N, 3) force buffer, the model's dtype
    w: np.ndarray  # (N, 3) buffer for u + beta v, the model's dtype
    scratch: tuple  # the force kernel's own scratch (Model.new_scratch): this workspace's alone
    vt: np.ndarray  # (P, 3) m/s, the tool vertices' velocities before the last step
    reaction: np.ndarray  # (L, 3) N, the tools' force on the body in the last step
    contacts: Contacts  # the rigid tools (the Loading's, or none)
    creaction: np.ndarray  # (K, 3) N, each rigid tool's force on the body at the last contact force evaluated
    threads: int  # the threads of the model's force (Model.extra), on which symplectic Euler's update runs
    # symplectic Euler's (force, update): the model's kernel and se_update, or a threaded model's unsummed
    # kernel (threaded.UNSUMMED) and se_sum_update_threads, which adds the threads' arrays and updates
    se_kernels: tuple
    # a linear tensor-mass model's shared tensors and their generation when it was built: a model whose
    # tensors a cut (realtime.models.linear_tm.cut) has changed since is refused (Model.check_current), without
    # looking the two up in Model.extra at every call
    tensors: object = None
    generation: int = 0
    version: int = 0  # set_forces calls: a stored acceleration from an older version is stale
    entries: dict = field(default_factory=dict)  # step loop -> its compiled entry point (_call)
    work: StepWork | None = None  # these arrays as the step loops take them (step_work), made on first use
    cg: CGWork | None = None  # implicit Euler's CG vectors, made on its first call

    @staticmethod
    def of(model: Model) -> _Prepared:
        lo = model.loading
        inv_mass = 1.0 / model.mass
        free = lo.free.reshape(-1)
        im = np.repeat(inv_mass, 3) * free
        fext = lo.external_force.copy()
        per_dof = np.ascontiguousarray(np.stack([im, fext.reshape(-1) * im], axis=1))
        own = lo.tools_tuple()
        tools = own._replace(vector=own.vector.copy(), angle=own.angle.copy(), ramp=own.ramp.copy())
        vert, kind = tools.vertex, tools.kind
        n = model.n_vertices
        threads = int(model.extra.get("threads", 1))
        tensors = model.extra.get("tensors")
        own_contacts = lo.contacts if lo.contacts is not None else no_contacts()
        # the paths copied for set_rigid_tool, as the tools' targets are for set_tool
        contacts = own_contacts._replace(travel=own_contacts.travel.copy(), ramp=own_contacts.ramp.copy())
        # a threaded model's fused sum and update would overwrite the contact force added between them:
        # with rigid tools its force kernel sums its threads itself and the update is the serial one
        fused = threads > 1 and contacts.count == 0
        return _Prepared(
            model,
            inv_mass,
            per_dof,
            fext,
            tools,
            blowup_bound(model),
            int(np.count_nonzero(lo.free)),
            (n, 3),
            model.dtype,
            np.empty((n, 3), model.dtype),
            np.empty((n, 3), model.dtype),
            model.new_scratch(),
            np.zeros((len(vert), 3)),
            np.zeros((len(kind), 3)),
            contacts,
            np.zeros((contacts.count, 3)),
            threads if fused else 1,
            (UNSUMMED[model.force_kernel.__name__], se_sum_update_threads)
            if fused
            else (model.force_kernel, se_update),
            tensors,
            model.extra.get("generation", tensors.generation) if tensors is not None else 0,
        )

    def step_work(self) -> StepWork:
        """This workspace's arrays in one StepWork (made on the first call), as the step loops take them."""
        if self.work is None:
            m = self.model
            self.work = step_work(
                m.data, self.scratch, m.points, m.mass, self.inv_mass, m.loading.free, self.per_dof, self.fext,
                self.tools, self.bound, self.f, self.w, self.vt, self.reaction, self.threads, self.contacts,
                self.creaction,
            )  # fmt: skip
        return self.work


@dataclass
class Integrator:
    """Base of the explicit integrators: Rayleigh damping coefficients alpha (1/s), beta (s)."""

    alpha: float = 0.0
    beta: float = 0.0
    _prepared: _Prepared | None = field(default=None, init=False, repr=False, compare=False)
    _busy: threading.Lock = field(default_factory=threading.Lock, init=False, repr=False, compare=False)
    name = "base"

    def __post_init__(self) -> None:
        for key in ("alpha", "beta"):
            value = getattr(self, key)
            if not (is_real(value) and 0.0 <= value < math.inf):
                raise InputError(
                    f"{self.name}: {key} = {value!r}: a Rayleigh damping coefficient must be a number >= 0 "
                    f"({'1/s' if key == 'alpha' else 's'}; a negative one feeds energy in)"
                )

    def step(self, model: Model, state: State, dt: float, n: int = 1, dt_crit: float | None = None) -> np.ndarray:
        """Advance ``state`` in place by n steps of dt (s); raises DivergenceError on blow-up (``dt_crit``,
        if known, goes into its message). Returns the tools' force on the body, (L, 3) float64 N.

        An integrator steps in one thread at a time: its workspace (force buffers, the kernel's
        scratch) is its own, and two calls at once would overwrite each other's forces and return
        wrong states without a word. A call made while another thread's is running raises InputError
        instead; give each thread its own integrator (they may share the model)."""
        if not self._busy.acquire(False):
            raise InputError(
                f"{self.name}: this integrator is already stepping in another thread; give each thread its own "
                "integrator (they may share the model)"
            )
        try:
            return self._step(model, state, dt, n, dt_crit)
        finally:
            self._busy.release()

    def critical_dt(self, model: Model, omega2: float | None = None) -> float:
        """dt_crit = (2 / omega_max)(sqrt(1 + xi^2) - xi), s. Pass omega2 if already known."""
        w2 = max_eigenvalue(model) if omega2 is None else omega2
        if not w2 > 0.0:  # no stiffness (ffd's lattice, a model with every component held): no limit
            return math.inf
        w = math.sqrt(w2)
        xi = 0.5 * self.beta * w  # mass damping (implicit or trapezoidal in the updates) costs no stability
        return 2.0 / w * (math.sqrt(1.0 + xi * xi) - xi)

    def _prepare(self, model: Model) -> _Prepared:
        """What every call on ``model`` needs, computed on the first call and kept while the model
        stays the same object (a Model is immutable): a haptic loop calling ``step`` with n = 1 then
        pays only the compiled call. Two threads may step one model, each with its own integrator: the
        buffers and the kernel's scratch are the integrator's."""
        p = self._prepared
        if p is None or p.model is not model:
            model.check_current()
            p = self._prepared = _Prepared.of(model)
        elif p.tensors is not None and p.tensors.generation != p.generation:
            model.check_current()  # raises: the mesh was cut since the model was built
        return p

    def internal_force(self, model: Model, u: np.ndarray) -> np.ndarray:
        """The internal force (N, 3), N, of ``model`` at u (N, 3) m as this integrator's steps see it: with
        its kernel's scratch, so a force with a memory (hybrid-tm's hysteresis) has the run's. A settling
        measures its residual by it (with the force from rest, hybrid-tm's equilibrium showed a residual
        wherever a vertex sat in the hysteresis band)."""
        return model.force_with(self._prepare(model).scratch, u)

    def static_force(self, model: Model, u: np.ndarray) -> np.ndarray:
        """``internal_force`` plus the rigid tools' contact force at the end of their travel (N, 3) N: the
        force a static equilibrium balances against the external loads (``realtime.statics``)."""
        return self.internal_force(model, u) + model.contact_force(u)

    def set_forces(self, model: Model, forces: np.ndarray) -> None:
        """Apply the external nodal forces ``forces`` (N, 3) float64, N, from the next step on, in place of
        the model's ``loading.external_force`` (the model does not change; the forces live in this
        integrator's workspace for this model, and every integrator reads them the same way)."""
        f = _frame_array("forces", forces, (model.n_vertices, 3))
        p = self._prepare(model)
        p.fext[:] = f
        p.per_dof[:, 1] = p.fext.reshape(-1) * p.per_dof[:, 0]
        p.version += 1

    def set_tool(self, model: Model, tool: int, translation=None, angle: float | None = None) -> None:
        """Hold tool ``tool`` at a new target from the next step on, without a ramp: ``translation``
        (3,) m for a translating tool, ``angle`` (rad, about its axis through its centre) for a rotating
        one. The vertices jump there in one step, their velocity the jump over dt, as a haptic device's
        frame moves them."""
        p = self._prepare(model)
        kind = p.tools.kind
        if len(kind) == 0:
            raise InputError(f"set_tool: tool = {tool!r}: {model.name} was built with no tools (Loading.tool_vertex)")
        if not isinstance(tool, (int, np.integer)) or not 0 <= tool < len(kind):
            raise InputError(f"set_tool: tool = {tool!r}: must be an index in 0..{len(kind) - 1}")
        if kind[tool] == TOOL_ROTATION:
            if translation is not None or angle is None:
                raise InputError(f"set_tool: tool {tool} rotates: give angle (rad), got translation = {translation!r}")
            p.tools.angle[tool] = float(_frame_array("angle", angle, ()))
        else:
            if angle is not None or translation is None:
                raise InputError(f"set_tool: tool {tool} translates: give translation (3,) m, got angle = {angle!r}")
            p.tools.vector[tool] = _frame_array("translation", translation, (3,))
        p.tools.ramp[tool] = 0.0  # held at the target from now on

    def set_rigid_tool(self, model: Model, tool: int, translation) -> None:
        """Hold rigid tool ``tool`` (the Loading's ``contacts``, in order) moved by ``translation`` (3,) m from
        where it was built, from the next step on, without a ramp: a haptic device's frame moves it so."""
        p = self._prepare(model)
        count = p.contacts.count
        if count == 0:
            raise InputError(
                f"set_rigid_tool: tool = {tool!r}: {model.name} was built with no rigid tools (Loading.contacts)"
            )
        if not isinstance(tool, (int, np.integer)) or not 0 <= tool < count:
            raise InputError(f"set_rigid_tool: tool = {tool!r}: must be an index in 0..{count - 1}")
        p.contacts.travel[tool] = _frame_array("translation", translation, (3,))
        p.contacts.ramp[tool] = 0.0

    def rigid_forces(self, model: Model) -> np.ndarray:
        """Each rigid tool's force on the body (K, 3) float64 N at the last contact force the steps evaluated
        (symplectic Euler and implicit Euler: at the last step's start; central difference: at its end),
        the Loading's ``contacts`` in order; (0, 3) without rigid tools."""
        return self._prepare(model).creaction.copy()

    def _diverged(self, model, state, bad, dt, dt_crit):
        """Raise DivergenceError for the step ``bad`` of this call, the last one the kernel took: the
        state's time and step count first advance to it, as u and v have."""
        state.t += (bad + 1) * dt
        state.steps += bad + 1
        if dt_crit is None:
            dt_crit = self.critical_dt(model)
        raise DivergenceError(model.name, state.steps - 1, dt, dt_crit, self.name, _blowup_reason(model, state.u))


def _check_step(model: Model, state: State, dt, n) -> tuple[float, int]:
    """dt as a float and n as an int, after checking what a step is given: the State's u and v writable
    C-contiguous (N, 3) arrays of this model's N vertices and float type (Model.dtype; the kernels index
    them without bounds checks, so a shorter array would be written past its end), its t a finite
    number, dt a positive finite number of s and n a whole number of steps >= 0. Raises InputError
    naming what is wrong."""
    return _check_state((len(model.points), 3), model.dtype, state, dt, n)


def _check_state(shape: tuple, dtype: np.dtype, state: State, dt, n) -> tuple[float, int]:
    """_check_step for a model of state arrays ``shape`` and ``dtype`` (an integrator's workspace keeps
    both). A haptic loop pays this at every call: what such a loop passes (Python floats and ints, the
    arrays it stepped last time) is accepted by exact type and identity tests first (numpy's built-in
    dtypes are singletons), 0.5 us on an AVX2 EPYC instead of 0.95; anything else goes through
    ``_checked_step``, which accepts numpy scalars too and names what is wrong."""
    try:
        u, v, t = state.u, state.v, state.t
    except AttributeError:
        return _checked_step(shape, dtype, state, dt, n)
    if (
        type(dt) is float
        and 0.0 < dt < math.inf
        and type(n) is int
        and n >= 0
        and type(t) is float
        and -math.inf < t < math.inf
        and type(u) is np.ndarray
        and type(v) is np.ndarray
        and u.dtype is dtype
        and v.dtype is dtype
        and u.shape == shape
        and v.shape == shape
    ):
        fu, fv = u.flags, v.flags
        if fu.c_contiguous and fu.writeable and fv.c_contiguous and fv.writeable:
            return dt, n
    return _checked_step(shape, dtype, state, dt, n)


def _checked_step(shape: tuple, dtype: np.dtype, state: State, dt, n) -> tuple[float, int]:
    """_check_step's full check, with its one-line InputError."""
    for name in ("u", "v"):
        a = getattr(state, name, None)
        if not (
            isinstance(a, np.ndarray)
            and a.dtype == dtype
            and a.shape == shape
            and a.flags.c_contiguous
            and a.flags.writeable
        ):
            got = f"{a.shape} {a.dtype} array" if isinstance(a, np.ndarray) else type(a).__name__
            if isinstance(a, np.ndarray) and a.shape == shape and a.dtype == dtype:
                got += " that is not C-contiguous and writable"
            why = "" if dtype == np.float64 else f" (the model was built with precision = {dtype.name!r})"
            raise InputError(f"State.{name}: must be a writable C-contiguous {shape} {dtype} array, got a {got}{why}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InputError(f"step: n = {n!r}: must be a whole number of steps >= 0")
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.number)) or not (math.isfinite(dt) and dt > 0):
        raise InputError(f"step: dt = {dt!r}: must be a positive number of s")
    t = getattr(state, "t", None)
    if isinstance(t, bool) or not isinstance(t, (int, float, np.number)) or not math.isfinite(t):
        raise InputError(f"State.t = {t!r}: must be a finite number of s")
    return float(dt), int(n)


def _call(p: _Prepared, loop, args: tuple):
    """``loop(*args)`` through its compiled entry point once the first call has compiled it for these
    argument types. numba's dispatcher types every argument on every call, 5 us for a step loop's twenty
    (a haptic loop's per-call cost); the entry point only unboxes them. It is sound because nothing a
    workspace passes changes type between calls: its own arrays are fixed, the State's are checked by
    _check_step and every scalar is passed as float, int or bool. Where numba's internals differ from
    what this relies on (Dispatcher.overloads, CompileResult.entry_point), every call dispatches."""
    entry = p.entries.get(loop)
    if entry is not None:
        return entry(*args)
    out = loop(*args)
    try:
        p.entries[loop] = loop.overloads[tuple(loop.typeof_pyval(a) for a in args)].entry_point
    except (AttributeError, KeyError):
        p.entries[loop] = loop
    return out


def _frame_array(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as a finite float64 array of ``shape``, or InputError naming ``name`` and what it got."""
    a = float_array(name, value, np.float64, f"a {shape} array")
    if a.shape != shape:
        raise InputError(f"{name}: must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise InputError(f"{name}{list(bad)}: must be finite, got {a[bad]}")
    return a


class SymplecticEuler(Integrator):
    """Semi-implicit (symplectic) Euler: v_{n+1} = (v_n + dt a(u_n)) / (1 + dt alpha), u_{n+1} = u_n + dt v_{n+1}."""

    name = "symplectic-euler"

    def _step(self, model: Model, state: State, dt: float, n: int, dt_crit: float | None) -> np.ndarray:
        """``step``; the tools' force is the last step's (``_tool_reaction``)."""
        p = self._prepare(model)
        dt, n = _check_state(p.shape, p.dtype, state, dt, n)
        force, update = p.se_kernels
        work, alpha, beta = p.step_work(), float(self.alpha), float(self.beta)
        args = (n, dt, float(state.t), force, update, work, alpha, beta, state.u, state.v)
        entry = p.entries.get(_run_symplectic_euler)  # _call inlined: 0.1 us of a haptic loop's call
        bad = entry(*args) if entry is not None else _call(p, _run_symplectic_euler, args)
        if bad >= 0:
            self._diverged(model, state, bad, dt, dt_crit)
        state.t += n * dt
        state.steps += n
        return p.reaction.copy()


class CentralDifference(Integrator):
    """Central difference in velocity-Verlet form (second order, explicit)."""

    name = "central-difference"

    def _step(self, model: Model, state: State, dt: float, n: int, dt_crit: float | None) -> np.ndarray:
        """``step``; the tools' force is the one at the end of the last step (``_tool_reaction``)."""
        p = self._prepare(model)
        dt, n = _check_state(p.shape, p.dtype, state, dt, n)
        lo = model.loading
        acc = state.acc
        key = (id(p), p.version)  # the acceleration is stale after set_forces (or from another model)
        usable = (
            isinstance(acc, np.ndarray)
            and acc.shape == state.u.shape
            and acc.dtype == np.float64
            and acc.flags.c_contiguous
            and acc.flags.writeable
        )
        if not usable or state.acc_key not in (None, key):
            f0 = model.internal_force(state.u + self.beta * state.v)
            f0 += contact_forces(p.contacts, model.points, state.u, state.t)[0]
            acc = (f0 + p.fext) * p.inv_mass[:, None] * lo.free
            state.acc = acc
        state.acc_key = key
        args = (n, dt, float(state.t), model.force_kernel, p.step_work(), float(self.alpha), float(self.beta))
        bad = _call(p, _run_central_difference, (*args, state.u, state.v, acc))
        if bad >= 0:
            self._diverged(model, state, bad, dt, dt_crit)
        state.t += n * dt
        state.steps += n
        return p.reaction.copy()


#: ImplicitEuler's preconditioners. "factored": A0 = M (1 + dt alpha) + (dt beta + dt^2) K0 with the
#: rest stiffness K0, factored once per model and dt by SuperLU: exact for a linear model (CG takes
#: one iteration), close for a non-linear one near rest. "mass": the mass term, free but weak (CG's
#: iterations grow with dt^2 K / M and with lambda / mu). "auto": factored up to FACTOR_LIMIT free
#: components, beyond which the fill-in of a 3D mesh's factor makes it too costly.
PRECONDITIONERS = ("auto", "factored", "mass")


class ImplicitEuler(Integrator):
    """Linearised (one Newton step) implicit Euler, Baraff & Witkin (1998): unconditionally stable for
    a linear model, the integrator of stiff and nearly incompressible materials. Each step solves
    (M (1 + dt alpha) + (dt beta + dt^2) K) dv = dt (f + f_ext - alpha M v - (beta + dt) K v) by
    preconditioned CG (K from the model's force kernel: exact for linear models, a central difference
    for non-linear ones; the preconditioner from PRECONDITIONERS). First order; numerically
    dissipative (damps high frequencies).

    Attributes: alpha, beta (Rayleigh), tol (CG relative residual), maxit (CG iterations per step),
    preconditioner, iterations (CG iterations of the last ``step`` call, all its steps together),
    worst_iterations (the most one step of it took). A step whose CG stops at maxit above tol raises
    NotConvergedError after it, unless ``budget``: maxit is then a fixed iteration budget per step (as a
    real-time simulator runs CG), and ``unconverged`` counts the steps that used it all.
    """

    name = "implicit-euler"

    def __init__(
        self,
        alpha: float = 0.0,
        beta: float = 0.0,
        tol: float = 1e-10,
        maxit: int = 5000,
        preconditioner: str = "auto",
        budget: bool = False,
    ):
        super().__init__(alpha=alpha, beta=beta)
        self.budget, self.unconverged = budget, 0
        if not (is_real(tol) and 0.0 < tol < 1.0):
            raise InputError(f"implicit-euler: tol = {tol!r}: CG's relative tolerance must be a number in (0, 1)")
        if not (is_real(maxit) and isinstance(maxit, (int, np.integer)) and maxit >= 1):
            raise InputError(f"implicit-euler: maxit = {maxit!r}: must be a whole number of CG iterations >= 1")
        if preconditioner not in PRECONDITIONERS:
            raise InputError(f"preconditioner = {preconditioner!r}: must be one of {', '.join(PRECONDITIONERS)}")
        self.tol, self.maxit, self.iterations, self.worst_iterations = tol, maxit, 0, 0
        self.preconditioner = preconditioner
        self._factor = None  # (model, (dt, alpha, beta), factor tuple)

    def preconditioner_for(self, model: Model) -> str:
        """The preconditioner this integrator uses on ``model``: "factored" or "mass"."""
        return self._preconditioner(int(np.count_nonzero(model.loading.free)))

    def _preconditioner(self, n_free: int) -> str:
        """preconditioner_for a model with ``n_free`` free components (``step`` knows the count from its
        workspace: counting them took 6.9 us of a 9.9 us call on the liver)."""
        if self.preconditioner != "auto":
            return self.preconditioner
        return "factored" if n_free <= FACTOR_LIMIT else "mass"

    def _factored(self, model: Model, dt: float) -> tuple:
        key = (dt, self.alpha, self.beta)
        if self._factor is None or self._factor[0] is not model or self._factor[1] != key:
            self._factor = (model, key, factorise(model, 1.0 + dt * self.alpha, dt * self.beta + dt * dt))
        return self._factor[2]

    def critical_dt(self, model: Model, omega2: float | None = None) -> float:
        return math.inf  # A-stable for linear models; the non-linear ones are checked by the blow-up bound

    def _step(self, model: Model, state: State, dt: float, n: int, dt_crit: float | None) -> np.ndarray:
        """``step``; the tools' force is the last step's (``_run_implicit_euler``)."""
        if model.precision != "float64":
            raise InputError(
                f"implicit-euler: {model.name} was built with precision = {model.precision!r}; its CG solves in "
                "float64 only (step a float32 model with symplectic-euler or central-difference)"
            )
        p = self._prepare(model)
        dt, n = _check_state(p.shape, p.dtype, state, dt, n)
        factored = self._preconditioner(p.n_free) == "factored"
        fac = self._factored(model, dt) if factored else NO_FACTOR
        if p.cg is None:
            p.cg = CGWork.like(state.u)
        cg = CG(float(self.tol), int(self.maxit), bool(factored), bool(self.budget))
        args = (n, dt, float(state.t), model.force_kernel, p.step_work(), bool(model.linear), float(self.alpha))
        status, last, its, worst, spent = _call(
            p, _run_implicit_euler, (*args, float(self.beta), cg, fac, state.u, state.v, p.cg)
        )
        self.iterations, self.worst_iterations = int(its), int(worst)
        self.unconverged += int(spent)
        if status == 1:
            self._diverged(model, state, last, dt, math.inf)
        if status == 2:
            state.t += (last + 1) * dt
            state.steps += last + 1
            raise NotConvergedError(
                f"{model.name} with implicit-euler: CG stopped at maxit = {self.maxit} iterations above its "
                f"tolerance {self.tol:.1e} at step {state.steps - 1} (dt = {dt:.4g} s): (M + dt^2 K) is too "
                f"ill-conditioned for the {self.preconditioner_for(model)} preconditioner; raise maxit, take a "
                "smaller dt, or pass budget=True to take maxit as a fixed iteration budget"
            )
        state.t += n * dt
        state.steps += n
        return p.reaction.copy()


INTEGRATORS = {cls.name: cls for cls in (SymplecticEuler, CentralDifference, ImplicitEuler)}


def make_integrator(name: str, alpha: float = 0.0, beta: float = 0.0) -> Integrator:
    """An integrator from the registry by name."""
    try:
        cls = INTEGRATORS[name]
    except KeyError:
        raise InputError(f"integrator = {name!r}: must be one of {', '.join(INTEGRATORS)}") from None
    return cls(alpha=alpha, beta=beta)
