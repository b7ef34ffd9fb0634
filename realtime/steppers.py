"""The compiled step loops of the integrators, and what they share: the tools, the tools' force, the
tangent product and the preconditioner of implicit Euler's CG (``realtime.integrators`` calls them).

Each loop advances u and v (N, 3) float64 in place by n steps, calls the model's force kernel
``force(data, scratch, u, f)`` (taken as an argument: one compiled loop per kernel), moves the tools'
vertices along their paths and returns where it stopped, so that a whole call runs in numba with the
GIL released.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
from numba.core import types
from numba.experimental import structref

from .blocks import U1, U2
from .contact import contact_force, contact_kick, contact_tangent
from .linsolve import factor_solve
from .model import _tool_value
from .threaded import sum_range, thread_range

_JIT = dict(nogil=True, cache=True)


class CG(NamedTuple):
    """Implicit Euler's CG: relative tolerance ``tol``, at most ``maxit`` iterations a step, the
    ``factored`` preconditioner (else the mass term), and ``budget`` (maxit is a fixed budget, not a
    failure)."""

    tol: float
    maxit: int
    factored: bool
    budget: bool


class CGWork(NamedTuple):
    """Implicit Euler's (N, 3) float64 work arrays: the force f, K v, CG's r, z, p, A p and x, and two
    for the tangent product. The loop writes each before it reads it, so one set serves every call
    (the integrator's workspace keeps it)."""

    f: np.ndarray
    kv: np.ndarray
    r: np.ndarray
    z: np.ndarray
    p: np.ndarray
    ap: np.ndarray
    x: np.ndarray
    t1: np.ndarray
    t2: np.ndarray

    @staticmethod
    def like(u: np.ndarray) -> CGWork:
        return CGWork(*(np.zeros_like(u) for _ in range(9)))


@nb.njit(**_JIT)
def _apply_tools(points, tools, t, dt, u, v, tmp):
    """Set the prescribed components to their value at t and their velocity to the last increment."""
    for p in range(tools.vertex.shape[0]):
        k = tools.tool[p]
        i = tools.vertex[p]
        _tool_value(
            points[i], tools.kind[k], tools.vector[k], tools.axis[k], tools.center[k], tools.angle[k],
            tools.ramp[k], tools.shape[k], t, tmp,
        )  # fmt: skip
        for c in range(3):
            if tools.mask[p, c] != 0.0:
                v[i, c] = (tmp[c] - u[i, c]) / dt
                u[i, c] = tmp[c]


@nb.njit(**_JIT)
def _tool_velocities(tools, v, vt):
    """vt (P, 3) = the velocities of the tool vertices, before a step moves them."""
    for p in range(tools.vertex.shape[0]):
        for c in range(3):
            vt[p, c] = v[tools.vertex[p], c]


@nb.njit(**_JIT)
def _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, out):
    """out (L, 3) N = the force each tool exerts on the body, from the equation of motion on its
    prescribed components: R = m (v - vt) / dt + alpha m v - f - f_ext, with v their velocity after the
    step, vt before it, and f the internal force (N, 3) the integrator used for it (damping included).
    This is what holds the vertices on the tool's path, inertia included: what a haptic device renders
    (with the opposite sign: the body's force on the tool). At rest it is model.reaction's static force."""
    out[:] = 0.0
    for p in range(tools.vertex.shape[0]):
        i, k = tools.vertex[p], tools.tool[p]
        for c in range(3):
            if tools.mask[p, c] != 0.0:
                out[k, c] += mass[i] * ((v[i, c] - vt[p, c]) / dt + alpha * v[i, c]) - f[i, c] - fext[i, c]


@nb.njit(**_JIT)
def _damped_arg(u, v, beta, w):
    """w = u + beta v: where the internal force is evaluated (Rayleigh stiffness damping)."""
    for i in range(u.shape[0]):
        for c in range(3):
            w[i, c] = u[i, c] + beta * v[i, c]


@structref.register
class StepWorkType(types.StructRef):
    """numba's type of StepWork (its fields' types as given, literals widened)."""

    def preprocess_fields(self, fields):
        return tuple((name, types.unliteral(t)) for name, t in fields)


class StepWork(structref.StructRefProxy):
    """What the step loops read and write besides the state, for one model in one integrator's
    workspace, held by reference in one numba object: a call unboxes it in about 0.1 us, where the same
    25 arrays passed one by one took 1.3 us of a haptic loop's call (numba's entry point unboxes each).
    The arrays are the workspace's own, so what ``set_forces`` and ``set_tool`` write in place is read
    by the next call. Fields: data and scratch (the force kernel's), points (N, 3) m, mass (N,) kg,
    inv_mass (N,) 1/kg, free (N, 3) (the Loading's mask), per_dof (3N, 2) (_se_update),
    fext (N, 3) N, tools (model.Tools), bound m, f and w (N, 3), vt (P, 3) m/s, reaction (L, 3) N, parts
    (int) the threads of a threaded model's force (1 otherwise), on which the update runs too, contacts
    (contact.Contacts, the rigid tools) and creaction (K, 3) N, each rigid tool's force on the body at the
    last contact force a loop evaluated."""


STEP_WORK_FIELDS = (
    "data", "scratch", "points", "mass", "inv_mass", "free", "per_dof", "fext", "tools", "bound", "f", "w", "vt",
    "reaction", "parts", "contacts", "creaction",
)  # fmt: skip
structref.define_proxy(StepWork, StepWorkType, list(STEP_WORK_FIELDS))


@nb.njit(**_JIT)
def step_work(
    data,
    scratch,
    points,
    mass,
    inv_mass,
    free,
    per_dof,
    fext,
    tools,
    bound,
    f,
    w,
    vt,
    reaction,
    parts,
    contacts,
    creaction,
):
    """A StepWork holding these arrays (not copies), in the order of STEP_WORK_FIELDS."""
    return StepWork(
        data, scratch, points, mass, inv_mass, free, per_dof, fext, tools, bound, f, w, vt, reaction, parts, contacts,
        creaction,
    )  # fmt: skip


@nb.njit(inline="always", **_JIT)
def _se_update(p1, u1, v1, f1, dt, damp, bound, lo, hi):
    """Symplectic Euler's update of the components lo .. hi - 1 under the force f1 (3N,) N: v = (v + dt
    a) damp, u += dt v, with u1, v1 (3N,) the flat state (m, m/s) and p1 (6N,) the flat per_dof (3N,
    2): per component, the free mask / m (1/kg) and the external acceleration f_ext / m on free
    components (m/s^2). A constrained component (1/m masked to 0) keeps v = 0 and does not move
    (tools overwrite theirs afterwards). Returns how many of them left |u| < bound (NaN counts).

    One branch-free loop that reads four arrays and writes two, which LLVM vectorises (more arrays,
    and it would need more run-time overlap checks than it is willing to emit). Its indices are
    unsigned and per_dof is read flat (blocks.U1 ...: 50 against 30 us for the 33 861 components of
    liver-x10, same bits). per_dof holds two numbers a component, not three (a free mask besides
    1/m): the update streams it after the force has pushed it out of the caches, and on liver-x10,
    after linear-tm's force, it took 48 us instead of 57 (medians of 300 calls alternated with the
    three-number loop, three processes)."""
    out = 0
    for k in range(np.uint64(lo), np.uint64(hi)):
        b = U2 * k
        im = p1[b]
        vk = (v1[k] + dt * (im * f1[k] + p1[b + U1])) * damp
        vk = vk if im != 0.0 else 0.0
        uk = u1[k] + dt * vk
        v1[k] = vk
        u1[k] = uk
        out += not abs(uk) < bound
    return out


@nb.njit(**_JIT)
def se_update(p1, scratch, u1, v1, f1, dt, damp, bound, parts):
    """_se_update of all components, on this thread, after a serial force kernel (``scratch`` and
    ``parts`` unused)."""
    return _se_update(p1, u1, v1, f1, dt, damp, bound, 0, u1.shape[0])


@nb.njit(**_JIT)
def _se_sum_update_part(p1, spans, F, u1, v1, f1, dt, damp, bound, lo, hi):
    """f1[k] = the sum over t of F[t, k] inside t's span (threaded.sum_range), then _se_update, for k =
    lo .. hi - 1; F (T, M) the threads' flat forces (M >= 3N), spans (T, 2) int64
    (threaded.force_spans). Two plain loops: one that summed as it updated was slower (on liver-x10,
    two threads, the update alone in a loop: 38 us a step, against 26 for the sum and then the update;
    its reads and writes of seven arrays at once against three and five). A compiled call of its own,
    for se_sum_update_threads' parallel loop (the threaded force kernels' chunks are called the same
    way)."""
    sum_range(spans, F, f1, lo, hi)
    return _se_update(p1, u1, v1, f1, dt, damp, bound, lo, hi)


@nb.njit(nogil=True, cache=True, parallel=True)
def se_sum_update_threads(p1, scratch, u1, v1, f1, dt, damp, bound, parts):
    """The update after a threaded model's unsummed force (threaded.UNSUMMED): each of ``parts``
    threads adds the threads' forces (scratch[-1], (T, N + pad, 3), each inside its span scratch[-2])
    over its range of components (threaded.thread_range), writes them to f1 and updates them. The
    ranges are threaded.sum_threads', so each thread works on numbers it has just summed, in its
    core's cache (the serial update of a threaded model's force cost 53 us on liver-x10, against 25
    after a serial force, reading the half the other core wrote)."""
    n = u1.shape[0]
    spans, F = scratch[-2], scratch[-1]
    Fs = F.reshape(F.shape[0], F.shape[1] * 3)
    out = 0
    for p in nb.prange(parts):
        lo, hi = thread_range(spans, n, p, parts)
        out += _se_sum_update_part(p1, spans, Fs, u1, v1, f1, dt, damp, bound, lo, hi)
    return out


@nb.njit(**_JIT)
def _run_symplectic_euler(n, dt, t0, force, update, work, alpha, beta, u, v):
    """n steps of v = (v + dt a(u)) / (1 + dt alpha); u += dt v. Returns -1 or the index of the step that blew up.
    ``work``: a StepWork; its ``reaction`` (L, 3) N receives the tools' force on the body in the last
    step (_tool_reaction), with the scheme's own discrete equation m (v_new - v_old) / dt = f(u_old) +
    f_ext - alpha m v_new + R.

    ``force`` and ``update``: the model's force kernel and se_update, or for a threaded model its
    unsummed force (threaded.UNSUMMED) and se_sum_update_threads, which adds the threads' forces into f
    and updates (on ``work.parts`` threads). ``update`` is an argument, as the force kernel is,
    rather than a function this loop calls: a cached loop that calls a parallel function crashed when
    loaded in a process that had not started numba's threads.
    """
    data, scratch, points, per_dof = work.data, work.scratch, work.points, work.per_dof
    mass, fext, tools, bound = work.mass, work.fext, work.tools, work.bound
    f, w, vt, reaction, parts = work.f, work.w, work.vt, work.reaction, work.parts
    contacts, creaction, free = work.contacts, work.creaction, work.free
    tmp = np.empty(3)
    u1, v1, f1, p1 = u.reshape(-1), v.reshape(-1), f.reshape(-1), per_dof.reshape(-1)
    damp = 1.0 / (1.0 + dt * alpha)  # mass damping treated implicitly: stable for any alpha
    for s in range(n):
        _tool_velocities(tools, v, vt)
        if beta != 0.0:
            _damped_arg(u, v, beta, w)
            force(data, scratch, w, f)
        else:
            force(data, scratch, u, f)
        contact_kick(contacts, points, u, t0 + s * dt, v, f, fext, free, mass, dt, damp, creaction)
        out = update(p1, scratch, u1, v1, f1, dt, damp, bound, parts)
        _apply_tools(points, tools, t0 + (s + 1) * dt, dt, u, v, tmp)
        if out:
            return s
    _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, reaction)
    return -1


@nb.njit(**_JIT)
def _run_central_difference(n, dt, t0, force, work, alpha, beta, u, v, a):
    """n steps of velocity Verlet (central difference): half kick, drift, force, half kick.
    ``work``: a StepWork; its ``reaction`` (L, 3) N receives the tools' force on the body at the end of
    the last step (_tool_reaction, with the force at the new u and the tools' last velocity increment).

    a (N, 3) holds the undamped acceleration (f_int + f_ext) / m at entry and at exit. Mass damping
    -alpha v is explicit in the first half kick and implicit in the second, v <- (v (1 - h alpha) +
    h a), then v <- (v + h a) / (1 + h alpha): together the trapezoidal rule, second order like the
    rest of the scheme (implicit in both halves, it was first order in alpha dt), and stable for any
    alpha (spectral radius <= 1 for omega dt < 2 and every alpha dt >= 0, checked on the 2x2
    amplification matrix).
    """
    data, scratch, points, mass, inv_mass = work.data, work.scratch, work.points, work.mass, work.inv_mass
    free, fext, tools, bound = work.free, work.fext, work.tools, work.bound
    f, w, vt, reaction = work.f, work.w, work.vt, work.reaction
    contacts, creaction = work.contacts, work.creaction
    tmp = np.empty(3)
    h = 0.5 * dt
    keep = 1.0 - h * alpha
    damp = 1.0 / (1.0 + h * alpha)
    for s in range(n):
        _tool_velocities(tools, v, vt)
        for i in range(u.shape[0]):
            for c in range(3):
                if free[i, c] != 0.0:
                    v[i, c] = v[i, c] * keep + h * a[i, c]
                    u[i, c] += dt * v[i, c]
        _apply_tools(points, tools, t0 + (s + 1) * dt, dt, u, v, tmp)
        if beta != 0.0:
            _damped_arg(u, v, beta, w)
            force(data, scratch, w, f)
        else:
            force(data, scratch, u, f)
        contact_kick(contacts, points, u, t0 + (s + 1) * dt, v, f, fext, free, mass, dt, 1.0, creaction)
        ok = True
        for i in range(u.shape[0]):
            im = inv_mass[i]
            for c in range(3):
                if free[i, c] != 0.0:
                    ai = (f[i, c] + fext[i, c]) * im
                    a[i, c] = ai
                    v[i, c] = (v[i, c] + h * ai) * damp
                    if not abs(u[i, c]) < bound:
                        ok = False
        if not ok:
            return s
    _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, reaction)
    return -1


@nb.njit(**_JIT)
def _tangent_product(force, data, scratch, u, y, linear, out, t1, t2):
    """out = K(u) y: -f(y) for a linear model, else -(f(u + h y) - f(u - h y)) / (2 h)."""
    if linear:
        force(data, scratch, y, out)
        for i in range(y.shape[0]):
            for c in range(3):
                out[i, c] = -out[i, c]
        return
    ymax = 0.0
    umax = 0.0
    for i in range(y.shape[0]):
        for c in range(3):
            ymax = max(ymax, abs(y[i, c]))
            umax = max(umax, abs(u[i, c]))
    if ymax == 0.0:
        out[:] = 0.0
        return
    h = 1e-7 * (umax + 1e-3) / ymax
    for i in range(y.shape[0]):
        for c in range(3):
            t1[i, c] = u[i, c] + h * y[i, c]
    force(data, scratch, t1, out)
    for i in range(y.shape[0]):
        for c in range(3):
            t1[i, c] = u[i, c] - h * y[i, c]
    force(data, scratch, t1, t2)
    for i in range(y.shape[0]):
        for c in range(3):
            out[i, c] = -(out[i, c] - t2[i, c]) / (2.0 * h)


@nb.njit(**_JIT)
def _precondition(factored, fac, cm, mass, r, z):
    """z = B^-1 r and returns r . z: B the factored rest-state system, or the mass term cm M."""
    if factored:
        factor_solve(fac, r, z)
    else:
        for i in range(r.shape[0]):
            for c in range(3):
                z[i, c] = r[i, c] / (cm * mass[i])
    rz = 0.0
    for i in range(r.shape[0]):
        for c in range(3):
            rz += r[i, c] * z[i, c]
    return rz


@nb.njit(**_JIT)
def _implicit_cg(force, data, scratch, u, linear, cm, ck, cg, fac, mass, free, cgw, contacts, points, t):
    """Preconditioned CG for implicit Euler's step: (cm M + ck K) x = r on the free components, K the
    tangent at ``u`` (N, 3) m (the rigid tools' ``contacts`` at time t s included), from x = 0 (``cgw``'s
    r holds the right-hand side, its x the answer), to ``cg.tol`` of the first preconditioned residual or
    ``cg.maxit`` iterations. Returns (the
    iterations, the last preconditioned residual rr, the first one's square root r0)."""
    f, kv, r, z, p, ap, x, t1, t2 = cgw
    nv = u.shape[0]
    rr = _precondition(cg.factored, fac, cm, mass, r, z)
    for i in range(nv):
        for c in range(3):
            p[i, c] = z[i, c]
    r0 = np.sqrt(rr)
    it = 0
    while it < cg.maxit and np.sqrt(rr) > cg.tol * r0 and rr > 0.0:
        _tangent_product(force, data, scratch, u, p, linear, ap, t1, t2)
        contact_tangent(contacts, points, u, t, p, ap)
        pap = 0.0
        for i in range(nv):
            for c in range(3):
                ap[i, c] = (cm * mass[i] * p[i, c] + ck * ap[i, c]) * free[i, c]
                pap += p[i, c] * ap[i, c]
        a = rr / pap
        for i in range(nv):
            for c in range(3):
                x[i, c] += a * p[i, c]
                r[i, c] -= a * ap[i, c]
        rr_new = _precondition(cg.factored, fac, cm, mass, r, z)
        b = rr_new / rr
        rr = rr_new
        for i in range(nv):
            for c in range(3):
                p[i, c] = z[i, c] + b * p[i, c]
        it += 1
    return it, rr, r0


@nb.njit(**_JIT)
def _run_implicit_euler(n, dt, t0, force, work, linear, alpha, beta, cg, fac, u, v, cgw):
    """n steps of linearised implicit Euler (``work`` a StepWork, of which this loop uses neither f nor w:
    its force and CG's vectors are ``cgw``'s, a CGWork); returns (status, the step it stopped after or -1, total CG
    iterations, the most CG iterations one step took, the steps whose CG stopped at maxit). Status 0:
    all n steps done; 1: the step blew up; 2: its CG stopped at ``maxit`` above ``tol`` (the step is
    taken; the loop stops after it unless ``budget``, a fixed iteration budget as real-time simulators
    run CG).

    (M (1 + dt alpha) + (dt beta + dt^2) K) dv = dt (f(u) + f_ext - alpha M v - (beta + dt) K v), K the tangent at
    u_n (the rigid tools' contact at t_n included: their force and stiffness), solved by preconditioned CG on the
    free components to a relative residual ``tol`` (the preconditioner: the factored system with the rest stiffness
    if ``factored``, else the mass term); then v += dv, u += dt v. ``reaction`` (L, 3) N: the tools' force on the
    body in the last step, from the same equation on their components: m (v_new - v_old) / dt + alpha m v_new +
    (beta + dt) K v - f(u_old) - f_ext, with K v one more tangent product (at the step's u_old) of the velocities
    the solve used (the new ones on the free components, the tools' old ones: the solve moved the tools' neighbours
    with those), so that the body's momentum balance closes.
    """
    data, scratch, points, mass = work.data, work.scratch, work.points, work.mass
    free, fext, tools, bound = work.free, work.fext, work.tools, work.bound
    vt, reaction, contacts, creaction = work.vt, work.reaction, work.contacts, work.creaction
    f, kv, r, z, p, ap, x, t1, t2 = cgw
    tol, maxit, budget = cg.tol, cg.maxit, cg.budget
    tmp = np.empty(3)
    cm = 1.0 + dt * alpha
    ck = dt * beta + dt * dt
    total = 0
    worst = 0
    spent = 0
    nv = u.shape[0]
    for s in range(n):
        _tool_velocities(tools, v, vt)
        ts = t0 + s * dt
        force(data, scratch, u, f)
        contact_force(contacts, points, u, ts, f, creaction)
        _tangent_product(force, data, scratch, u, v, linear, kv, t1, t2)
        contact_tangent(contacts, points, u, ts, v, kv)
        for i in range(nv):
            for c in range(3):
                r[i, c] = dt * (f[i, c] + fext[i, c] - alpha * mass[i] * v[i, c] - (beta + dt) * kv[i, c]) * free[i, c]
                x[i, c] = 0.0
        it, rr, r0 = _implicit_cg(
            force, data, scratch, u, linear, cm, ck, cg, fac, mass, free, cgw, contacts, points, ts
        )
        total += it
        worst = max(worst, it)
        unconverged = it >= maxit and np.sqrt(rr) > tol * r0
        spent += unconverged
        ok = True
        last = s == n - 1 or (unconverged and not budget)
        if last:
            z[:] = u  # u_old, where the step's tangent was taken
        for i in range(nv):
            for c in range(3):
                if free[i, c] != 0.0:
                    v[i, c] += x[i, c]
                    u[i, c] += dt * v[i, c]
                    if not abs(u[i, c]) < bound:
                        ok = False
        if last and ok:  # the implicit part of the step's force, with the velocities the solve used
            _tangent_product(force, data, scratch, z, v, linear, kv, t1, t2)
            contact_tangent(contacts, points, z, ts, v, kv)
            for i in range(nv):
                for c in range(3):
                    f[i, c] -= (beta + dt) * kv[i, c]
        _apply_tools(points, tools, t0 + (s + 1) * dt, dt, u, v, tmp)
        if not ok:
            return 1, s, total, worst, spent
        if last:
            _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, reaction)
        if unconverged and not budget:
            return 2, s, total, worst, spent
    return 0, -1, total, worst, spent
