"""Time integrators, critical time steps, and static equilibrium by damped dynamics.

Every integrator advances a ``State`` by n steps of size dt in one compiled call
(``integrator.step(model, state, dt, n)``): the loop, the model's force kernel, the tools and the
blow-up check all run in numba with the GIL released, so a haptic thread can call it.

Equations of motion, with lumped masses m_i and Rayleigh damping C = alpha M + beta K:

    m_i a_i = f_int(u + beta v)_i + f_ext_i - alpha m_i v_i

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
from dataclasses import dataclass, field

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import InputError
from .geometry import shape_gradients
from .model import TOOL_ROTATION, Model, State, _tool_value
from .tensor_mass import TensorMass, assemble_blocks, element_elasticity

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
    """Damped dynamics did not reach static equilibrium within the step budget."""


@nb.njit(**_JIT)
def _apply_tools(points, tools, t, dt, u, v, tmp):
    """Set the prescribed components to their value at t and their velocity to the last increment."""
    vert, mask, tid, kind, vector, axis, center, angle, ramp, shape = tools
    for p in range(vert.shape[0]):
        k = tid[p]
        i = vert[p]
        _tool_value(points[i], kind[k], vector[k], axis[k], center[k], angle[k], ramp[k], shape[k], t, tmp)
        for c in range(3):
            if mask[p, c] != 0.0:
                v[i, c] = (tmp[c] - u[i, c]) / dt
                u[i, c] = tmp[c]


@nb.njit(**_JIT)
def _tool_velocities(tools, v, vt):
    """vt (P, 3) = the velocities of the tool vertices, before a step moves them."""
    vert = tools[0]
    for p in range(vert.shape[0]):
        for c in range(3):
            vt[p, c] = v[vert[p], c]


@nb.njit(**_JIT)
def _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, out):
    """out (L, 3) N = the force each tool exerts on the body, from the equation of motion on its
    prescribed components: R = m (v - vt) / dt + alpha m v - f - f_ext, with v their velocity after the
    step, vt before it, and f the internal force (N, 3) the integrator used for it (damping included).
    This is what holds the vertices on the tool's path, inertia included: what a haptic device renders
    (with the opposite sign: the body's force on the tool). At rest it is model.reaction's static force."""
    vert, mask, tid = tools[0], tools[1], tools[2]
    out[:] = 0.0
    for p in range(vert.shape[0]):
        i, k = vert[p], tid[p]
        for c in range(3):
            if mask[p, c] != 0.0:
                out[k, c] += mass[i] * ((v[i, c] - vt[p, c]) / dt + alpha * v[i, c]) - f[i, c] - fext[i, c]


@nb.njit(**_JIT)
def _damped_arg(u, v, beta, w):
    """w = u + beta v: where the internal force is evaluated (Rayleigh stiffness damping)."""
    for i in range(u.shape[0]):
        for c in range(3):
            w[i, c] = u[i, c] + beta * v[i, c]


@nb.njit(**_JIT)
def _run_symplectic_euler(
    n, dt, t0, force, data, scratch, points, per_dof, mass, fext, tools, alpha, beta, bound, u, v, f, w, vt, reaction
):  # fmt: skip
    """n steps of v = (v + dt a(u)) / (1 + dt alpha); u += dt v. Returns -1 or the index of the step that blew up.
    ``reaction`` (L, 3) N: the tools' force on the body in the last step (_tool_reaction), with the
    scheme's own discrete equation m (v_new - v_old) / dt = f(u_old) + f_ext - alpha m v_new + R.

    per_dof (3N, 3): per component, the free mask, the free mask / m (1/kg) and the external
    acceleration f_ext / m on free components (m/s^2). Constrained components keep v = 0 and do not
    move (tools overwrite theirs afterwards). The update is one branch-free loop over 3N components
    that reads two arrays and writes two, which LLVM vectorises (more arrays, and it would need more
    run-time overlap checks than it is willing to emit).
    """
    tmp = np.empty(3)
    u1, v1, f1 = u.reshape(-1), v.reshape(-1), f.reshape(-1)
    damp = 1.0 / (1.0 + dt * alpha)  # mass damping treated implicitly: stable for any alpha
    for s in range(n):
        _tool_velocities(tools, v, vt)
        if beta != 0.0:
            _damped_arg(u, v, beta, w)
            force(data, scratch, w, f)
        else:
            force(data, scratch, u, f)
        out = 0
        for k in range(u1.shape[0]):
            vk = (per_dof[k, 0] * v1[k] + dt * (per_dof[k, 1] * f1[k] + per_dof[k, 2])) * damp
            uk = u1[k] + dt * vk
            v1[k] = vk
            u1[k] = uk
            out += not abs(uk) < bound  # NaN counts too
        _apply_tools(points, tools, t0 + (s + 1) * dt, dt, u, v, tmp)
        if out:
            return s
    _tool_reaction(tools, mass, f, fext, v, vt, alpha, dt, reaction)
    return -1


@nb.njit(**_JIT)
def _run_central_difference(
    n, dt, t0, force, data, scratch, points, mass, inv_mass, free, fext, tools, alpha, beta, bound, u, v, a, f, w,
    vt, reaction,
):  # fmt: skip
    """n steps of velocity Verlet (central difference): half kick, drift, force, half kick.
    ``reaction`` (L, 3) N: the tools' force on the body at the end of the last step (_tool_reaction, with
    the force at the new u and the tools' last velocity increment).

    a (N, 3) holds the undamped acceleration (f_int + f_ext) / m at entry and at exit. Mass damping
    -alpha v is explicit in the first half kick and implicit in the second, v <- (v (1 - h alpha) +
    h a), then v <- (v + h a) / (1 + h alpha): together the trapezoidal rule, second order like the
    rest of the scheme (implicit in both halves, it was first order in alpha dt), and stable for any
    alpha (spectral radius <= 1 for omega dt < 2 and every alpha dt >= 0, checked on the 2x2
    amplification matrix).
    """
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
def _factor_solve(fac, r, z):
    """z = A0^-1 r on the free components, zero on the others, with A0's sparse LU factors (_factorise).

    SuperLU factors Pr A0 Pc = L U; then A0 x = b is L U y = Pr b, x = Pc y.
    fac: (fidx (F,) the free flat dofs, perm_r, perm_c (F,) int64, the strictly lower part of L and
    the strictly upper part of U in CSC (indptr, indices, data), their diagonals (F,), scratch (F,)).
    r, z: (N, 3) float64.
    """
    fidx, pr, pc, lp, li, lx, ld, up, ui, ux, ud, w = fac
    r1, z1 = r.reshape(-1), z.reshape(-1)
    n = fidx.shape[0]
    for j in range(n):
        w[pr[j]] = r1[fidx[j]]
    for j in range(n):  # forward: L
        wj = w[j] / ld[j]
        w[j] = wj
        for k in range(lp[j], lp[j + 1]):
            w[li[k]] -= lx[k] * wj
    for j in range(n - 1, -1, -1):  # backward: U
        wj = w[j] / ud[j]
        w[j] = wj
        for k in range(up[j], up[j + 1]):
            w[ui[k]] -= ux[k] * wj
    z1[:] = 0.0
    for j in range(n):
        z1[fidx[j]] = w[pc[j]]


@nb.njit(**_JIT)
def _precondition(factored, fac, cm, mass, r, z):
    """z = B^-1 r and returns r . z: B the factored rest-state system, or the mass term cm M."""
    if factored:
        _factor_solve(fac, r, z)
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
def _run_implicit_euler(
    n, dt, t0, force, data, scratch, linear, points, mass, free, fext, tools, alpha, beta, bound, tol, maxit,
    factored, fac, u, v, work, budget, vt, reaction,
):  # fmt: skip
    """n steps of linearised implicit Euler; returns (status, the step it stopped after or -1, total CG
    iterations, the most CG iterations one step took, the steps whose CG stopped at maxit). Status 0:
    all n steps done; 1: the step blew up; 2: its CG stopped at ``maxit`` above ``tol`` (the step is
    taken; the loop stops after it unless ``budget``, a fixed iteration budget as real-time simulators
    run CG).

    (M (1 + dt alpha) + (dt beta + dt^2) K) dv = dt (f(u) + f_ext - alpha M v - (beta + dt) K v), K the
    tangent at u_n, solved by preconditioned CG on the free components to a relative residual
    ``tol`` (the preconditioner: the factored system with the rest stiffness if ``factored``, else
    the mass term); then v += dv, u += dt v. ``reaction`` (L, 3) N: the tools' force on the body in the
    last step, from the same equation on their components: m (v_new - v_old) / dt + alpha m v_new +
    (beta + dt) K v - f(u_old) - f_ext, with K v one more tangent product (at the step's u_old) of the
    velocities the solve used (the new ones on the free components, the tools' old ones: the solve
    moved the tools' neighbours with those), so that the body's momentum balance closes.
    """
    f, kv, r, z, p, ap, x, t1, t2 = work[0], work[1], work[2], work[3], work[4], work[5], work[6], work[7], work[8]
    tmp = np.empty(3)
    cm = 1.0 + dt * alpha
    ck = dt * beta + dt * dt
    total = 0
    worst = 0
    spent = 0
    nv = u.shape[0]
    for s in range(n):
        _tool_velocities(tools, v, vt)
        force(data, scratch, u, f)
        _tangent_product(force, data, scratch, u, v, linear, kv, t1, t2)
        for i in range(nv):
            for c in range(3):
                r[i, c] = dt * (f[i, c] + fext[i, c] - alpha * mass[i] * v[i, c] - (beta + dt) * kv[i, c]) * free[i, c]
                x[i, c] = 0.0
        rr = _precondition(factored, fac, cm, mass, r, z)
        for i in range(nv):
            for c in range(3):
                p[i, c] = z[i, c]
        r0 = np.sqrt(rr)
        it = 0
        while it < maxit and np.sqrt(rr) > tol * r0 and rr > 0.0:
            _tangent_product(force, data, scratch, u, p, linear, ap, t1, t2)
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
            rr_new = _precondition(factored, fac, cm, mass, r, z)
            b = rr_new / rr
            rr = rr_new
            for i in range(nv):
                for c in range(3):
                    p[i, c] = z[i, c] + b * p[i, c]
            it += 1
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


def blowup_bound(model: Model) -> float:
    """Displacement beyond which a run is declared diverged: 10 x the bounding-box diagonal, m."""
    return 10.0 * float(np.linalg.norm(model.points.max(axis=0) - model.points.min(axis=0)))


def _scaled_stiffness(model: Model, u: np.ndarray | None = None) -> spla.LinearOperator:
    """M^-1/2 K M^-1/2 on the free components as a LinearOperator, K the stiffness at displacement u
    (default: rest), applied through the force kernel: exactly for a linear model, by a central
    difference of the force for a non-linear one."""
    n = model.n_vertices
    u0 = np.zeros((n, 3)) if u is None else np.asarray(u, dtype=float)
    free = model.loading.free.ravel() != 0.0
    s = 1.0 / np.sqrt(np.repeat(model.mass, 3))[free]
    scale = 1e-6 * max(float(np.ptp(model.points, axis=0).max()), 1e-12)

    def matvec(x):
        z = np.zeros(3 * n)
        z[free] = s * np.ravel(x)
        if model.linear and u is None:
            kz = -model.internal_force(z.reshape(n, 3)).ravel()
        else:
            dz = scale / max(float(np.abs(z).max()), 1e-300)
            fp = model.internal_force(u0 + dz * z.reshape(n, 3))
            fm = model.internal_force(u0 - dz * z.reshape(n, 3))
            kz = -(fp - fm).ravel() / (2.0 * dz)
        return s * kz[free]

    m = int(free.sum())
    return spla.LinearOperator((m, m), matvec=matvec, dtype=float)


def max_eigenvalue(model: Model, u: np.ndarray | None = None, tol: float = 1e-8) -> float:
    """Largest eigenvalue omega_max^2 (1/s^2) of M^-1 K on the free components (K at u, default rest).

    The symmetric form M^-1/2 K M^-1/2 is handed to ARPACK's Lanczos (scipy eigsh), which converges in
    a few dozen products where plain power iteration needs hundreds and stops below the true value.
    """
    op = _scaled_stiffness(model, u)
    v0 = np.random.default_rng(0).standard_normal(op.shape[0])
    return float(spla.eigsh(op, k=1, which="LA", tol=tol, v0=v0, return_eigenvectors=False)[0])


def min_eigenvalue(model: Model, tol: float = 1e-3) -> float:
    """Smallest eigenvalue omega_1^2 (1/s^2) of M^-1 K on the free components, at rest, to a relative
    tolerance ``tol`` (enough to choose a time step): the slowest mode, the one a static relaxation
    must settle.

    Where the rest stiffness is known as a matrix (rest_stiffness: exact at rest for every model
    without the volume penalty) and small enough to factor, by shift-invert Lanczos about 0 (a few
    iterations whatever the conditioning); otherwise by Lanczos on the force kernel, whose iterations
    grow with the condition number (2e5 products on the cantilever at nu = 0.4999, 20 s).
    """
    fidx = np.flatnonzero(model.loading.free.reshape(-1) != 0.0)
    v0 = np.random.default_rng(0).standard_normal(len(fidx))
    if model.material.volume_penalty == 0.0 and len(fidx) <= FACTOR_LIMIT:
        K = rest_stiffness(model)[fidx][:, fidx].tocsc()
        M = sp.diags(np.repeat(model.mass, 3)[fidx]).tocsc()
        try:
            lam = spla.eigsh(K, k=1, M=M, sigma=0.0, which="LM", tol=tol, v0=v0, return_eigenvectors=False)
            return float(lam[0])
        except RuntimeError:  # K singular (a free body): its smallest eigenvalue is 0, which Lanczos finds
            pass
    op = _scaled_stiffness(model)
    return float(
        spla.eigsh(op, k=1, which="SA", tol=tol, v0=v0, maxiter=100 * op.shape[0], return_eigenvectors=False)[0]
    )


def element_critical_dt(model: Model) -> float:
    """A proven lower bound, s, on the undamped explicit critical step 2 / omega_max at rest.

    With lumped masses, M = sum of the elements' shares M_e and K = sum of K_e, the Rayleigh quotient
    gives omega_max^2 <= max over elements of lambda_max(K_e, M_e) (the element eigenvalue inequality,
    Irons and Treharne 1971), so 2 / sqrt(max_e lambda_max(K_e, M_e)) <= 2 / omega_max. Elements are the
    tetrahedra (the P1 stiffness of the material's rest linearisation, fibres and volume penalty
    included, with rho V / 4 at each vertex) or, for mass-spring, the springs (each vertex's mass
    shared equally among its springs: lambda = k (1/m_a + 1/m_b)). Measured: 0.31 to 0.37 of the
    Lanczos value for tetrahedra, 0.45 for springs; runs record both (dt_crit_element, dt_crit).
    """
    if model.name == "mass-spring":
        _, edges, k, _ = model.data
        degree = np.bincount(edges.ravel(), minlength=model.n_vertices)
        share = model.mass / np.maximum(degree, 1)
        lam_max = float(np.max(k * (1.0 / share[edges[:, 0]] + 1.0 / share[edges[:, 1]])))
        return 2.0 / math.sqrt(lam_max)
    m = model.material
    grads, vol = shape_gradients(model.points, model.tets)
    lam_max = 0.0
    for start in range(0, len(vol), 4096):  # bounded memory: (4096, 12, 12) at a time
        g, v = grads[start : start + 4096], vol[start : start + 4096]
        C = element_elasticity(model.points, model.tets[start : start + 4096], m, extra_lam=m.volume_penalty)
        ke = np.einsum("maj,mijkl,mbl->maibk", g, C, g).reshape(len(v), 12, 12) * v[:, None, None]
        ev = np.linalg.eigvalsh(ke)[:, -1] / (m.density * v / 4.0)
        lam_max = max(lam_max, float(ev.max()))
    return 2.0 / math.sqrt(lam_max)


@dataclass
class _Prepared:
    """Per-model arrays of the step kernels (see Integrator._prepare): the integrator's workspace, which
    also holds what a simulator changes between frames (``set_forces``, ``set_tool``)."""

    model: Model
    inv_mass: np.ndarray  # (N,) 1/kg
    per_dof: np.ndarray  # (3N, 3): free mask, free mask / m (1/kg), free f_ext / m (m/s^2)
    fext: np.ndarray  # (N, 3) N, the external forces applied: the Loading's until set_forces
    tools: tuple  # the Loading's tool arrays, with the targets (vector, angle, ramp) copied for set_tool
    bound: float  # m, the blow-up bound
    f: np.ndarray  # (N, 3) force buffer
    w: np.ndarray  # (N, 3) buffer for u + beta v
    scratch: tuple  # the force kernel's own scratch (Model.new_scratch): this workspace's alone
    vt: np.ndarray  # (P, 3) m/s, the tool vertices' velocities before the last step
    reaction: np.ndarray  # (L, 3) N, the tools' force on the body in the last step
    version: int = 0  # set_forces calls: a stored acceleration from an older version is stale
    entries: dict = field(default_factory=dict)  # step loop -> its compiled entry point (_call)

    @staticmethod
    def of(model: Model) -> _Prepared:
        lo = model.loading
        inv_mass = 1.0 / model.mass
        free = lo.free.reshape(-1)
        im = np.repeat(inv_mass, 3) * free
        fext = lo.external_force.copy()
        per_dof = np.ascontiguousarray(np.stack([free, im, fext.reshape(-1) * im], axis=1))
        vert, mask, tid, kind, vector, axis, center, angle, ramp, shape = lo.tools_tuple()
        tools = (vert, mask, tid, kind, vector.copy(), axis, center, angle.copy(), ramp.copy(), shape)
        n = model.n_vertices
        return _Prepared(
            model,
            inv_mass,
            per_dof,
            fext,
            tools,
            blowup_bound(model),
            np.empty((n, 3)),
            np.empty((n, 3)),
            model.new_scratch(),
            np.zeros((len(vert), 3)),
            np.zeros((len(kind), 3)),
        )


@dataclass
class Integrator:
    """Base of the explicit integrators: Rayleigh damping coefficients alpha (1/s), beta (s)."""

    alpha: float = 0.0
    beta: float = 0.0
    _prepared: _Prepared | None = field(default=None, init=False, repr=False, compare=False)
    name = "base"

    def critical_dt(self, model: Model, omega2: float | None = None) -> float:
        """dt_crit = (2 / omega_max)(sqrt(1 + xi^2) - xi), s. Pass omega2 if already known."""
        w2 = max_eigenvalue(model) if omega2 is None else omega2
        w = math.sqrt(w2)
        xi = 0.5 * self.beta * w  # mass damping (implicit or trapezoidal in the updates) costs no stability
        return 2.0 / w * (math.sqrt(1.0 + xi * xi) - xi)

    def _prepare(self, model: Model) -> _Prepared:
        """What every call on ``model`` needs, computed on the first call and kept while the model
        stays the same object (a Model is immutable): a haptic loop calling ``step`` with n = 1 then
        pays only the compiled call. Two threads may step one model, each with its own integrator: the
        buffers and the kernel's scratch are the integrator's."""
        model.check_current()
        if self._prepared is None or self._prepared.model is not model:
            self._prepared = _Prepared.of(model)
        return self._prepared

    def set_forces(self, model: Model, forces: np.ndarray) -> None:
        """Apply the external nodal forces ``forces`` (N, 3) float64, N, from the next step on, in place of
        the model's ``loading.external_force`` (the model does not change; the forces live in this
        integrator's workspace for this model, and every integrator reads them the same way)."""
        f = _frame_array("forces", forces, (model.n_vertices, 3))
        p = self._prepare(model)
        p.fext[:] = f
        p.per_dof[:, 2] = p.fext.reshape(-1) * p.per_dof[:, 1]
        p.version += 1

    def set_tool(self, model: Model, tool: int, translation=None, angle: float | None = None) -> None:
        """Hold tool ``tool`` at a new target from the next step on, without a ramp: ``translation``
        (3,) m for a translating tool, ``angle`` (rad, about its axis through its centre) for a rotating
        one. The vertices jump there in one step, their velocity the jump over dt, as a haptic device's
        frame moves them."""
        p = self._prepare(model)
        kind = p.tools[3]
        if not isinstance(tool, (int, np.integer)) or not 0 <= tool < len(kind):
            raise InputError(f"set_tool: tool = {tool!r}: must be an index in 0..{len(kind) - 1}")
        if kind[tool] == TOOL_ROTATION:
            if translation is not None or angle is None:
                raise InputError(f"set_tool: tool {tool} rotates: give angle (rad), got translation = {translation!r}")
            p.tools[7][tool] = float(_frame_array("angle", angle, ()))
        else:
            if angle is not None or translation is None:
                raise InputError(f"set_tool: tool {tool} translates: give translation (3,) m, got angle = {angle!r}")
            p.tools[4][tool] = _frame_array("translation", translation, (3,))
        p.tools[8][tool] = 0.0  # held at the target from now on

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
    C-contiguous (N, 3) float64 arrays of this model's N vertices (the kernels index them without bounds
    checks, so a shorter array would be written past its end), its t a finite number, dt a positive
    finite number of s and n a whole number of steps >= 0. Raises InputError naming what is wrong."""
    shape = (model.n_vertices, 3)
    for name in ("u", "v"):
        a = getattr(state, name, None)
        if not (
            isinstance(a, np.ndarray)
            and a.dtype == np.float64
            and a.shape == shape
            and a.flags.c_contiguous
            and a.flags.writeable
        ):
            got = f"{a.shape} {a.dtype} array" if isinstance(a, np.ndarray) else type(a).__name__
            if isinstance(a, np.ndarray) and a.shape == shape and a.dtype == np.float64:
                got += " that is not C-contiguous and writable"
            raise InputError(f"State.{name}: must be a writable C-contiguous {shape} float64 array, got a {got}")
    if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or n < 0:
        raise InputError(f"step: n = {n!r}: must be a whole number of steps >= 0")
    if isinstance(dt, bool) or not isinstance(dt, (int, float, np.number)) or not (math.isfinite(dt) and dt > 0):
        raise InputError(f"step: dt = {dt!r}: must be a positive number of s")
    if isinstance(state.t, bool) or not isinstance(state.t, (int, float, np.number)) or not math.isfinite(state.t):
        raise InputError(f"State.t = {state.t!r}: must be a finite number of s")
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
    try:
        a = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"{name}: must be a {shape} array of numbers, got {type(value).__name__}") from None
    if a.shape != shape:
        raise InputError(f"{name}: must have shape {shape}, got {a.shape}")
    if not np.all(np.isfinite(a)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
        raise InputError(f"{name}{list(bad)}: must be finite, got {a[bad]}")
    return a


class SymplecticEuler(Integrator):
    """Semi-implicit (symplectic) Euler: v_{n+1} = (v_n + dt a(u_n)) / (1 + dt alpha), u_{n+1} = u_n + dt v_{n+1}."""

    name = "symplectic-euler"

    def step(self, model: Model, state: State, dt: float, n: int = 1, dt_crit: float | None = None) -> np.ndarray:
        """Advance ``state`` in place by n steps of dt (s); raises DivergenceError on blow-up. Returns the
        tools' force on the body in the last step, (L, 3) float64 N (``_tool_reaction``)."""
        p = self._prepare(model)
        dt, n = _check_step(model, state, dt, n)
        bad = _call(p, _run_symplectic_euler, (
            n, dt, float(state.t), model.force_kernel, model.data, p.scratch, model.points, p.per_dof, model.mass,
            p.fext, p.tools, float(self.alpha), float(self.beta), p.bound, state.u, state.v, p.f, p.w, p.vt,
            p.reaction,
        ))  # fmt: skip
        if bad >= 0:
            self._diverged(model, state, bad, dt, dt_crit)
        state.t += n * dt
        state.steps += n
        return p.reaction.copy()


class CentralDifference(Integrator):
    """Central difference in velocity-Verlet form (second order, explicit)."""

    name = "central-difference"

    def step(self, model: Model, state: State, dt: float, n: int = 1, dt_crit: float | None = None) -> np.ndarray:
        """Advance ``state`` in place by n steps of dt (s); raises DivergenceError on blow-up. Returns the
        tools' force on the body at the end of the last step, (L, 3) float64 N (``_tool_reaction``)."""
        p = self._prepare(model)
        dt, n = _check_step(model, state, dt, n)
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
            acc = (f0 + p.fext) * p.inv_mass[:, None] * lo.free
            state.acc = acc
        state.acc_key = key
        bad = _call(p, _run_central_difference, (
            n, dt, float(state.t), model.force_kernel, model.data, p.scratch, model.points, model.mass, p.inv_mass,
            lo.free, p.fext, p.tools, float(self.alpha), float(self.beta), p.bound, state.u, state.v, acc, p.f,
            p.w, p.vt, p.reaction,
        ))  # fmt: skip
        if bad >= 0:
            self._diverged(model, state, bad, dt, dt_crit)
        state.t += n * dt
        state.steps += n
        return p.reaction.copy()


def rest_stiffness(model: Model) -> sp.csr_matrix:
    """The model's stiffness at rest, (3N, 3N) N/m (dof 3 i + c): the springs' for mass-spring; for
    every other model the P1 linear stiffness of its material (linear-tm's own tensors, or what the
    element models linearise to at rest; the volume penalty left out)."""
    n = model.n_vertices
    if model.name == "mass-spring":
        X, edges, k, _ = model.data
        d = X[edges[:, 1]] - X[edges[:, 0]]
        d /= np.linalg.norm(d, axis=1)[:, None]
        b = k[:, None, None] * d[:, :, None] * d[:, None, :]  # k e e^T on each edge
        i, j = edges[:, 0], edges[:, 1]
        rows = np.concatenate([i, j, i, j])
        cols = np.concatenate([i, j, j, i])
        blocks = np.concatenate([b, b, -b, -b])
        return assemble_blocks(rows, cols, blocks, n)
    tm = model.extra.get("tensors") or TensorMass(model.points, model.tets, model.material)
    return tm.matrix()


def _factorise(model: Model, cm: float, ck: float) -> tuple:
    """Sparse LU (SuperLU, minimum degree on A + A^T) of A0 = cm M + ck K0 on the free components, K0
    the rest stiffness, as the tuple _factor_solve takes."""
    fidx = np.flatnonzero(model.loading.free.reshape(-1) != 0.0)
    a = sp.diags(cm * np.repeat(model.mass, 3)) + ck * rest_stiffness(model)
    lu = spla.splu(a.tocsr()[fidx][:, fidx].tocsc(), permc_spec="MMD_AT_PLUS_A")
    lower, upper = sp.tril(lu.L, -1).tocsc(), sp.triu(lu.U, 1).tocsc()
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    return (
        i64(fidx), i64(lu.perm_r), i64(lu.perm_c),
        i64(lower.indptr), i64(lower.indices), np.ascontiguousarray(lower.data), np.ascontiguousarray(lu.L.diagonal()),
        i64(upper.indptr), i64(upper.indices), np.ascontiguousarray(upper.data), np.ascontiguousarray(lu.U.diagonal()),
        np.zeros(len(fidx)),
    )  # fmt: skip


#: The mass preconditioner's stand-in for the factor tuple (same types, nothing in it).
_NO_FACTOR = (
    tuple(np.zeros(0, dtype=np.int64) for _ in range(5))
    + (np.zeros(0), np.zeros(0))
    + tuple(np.zeros(0, dtype=np.int64) for _ in range(2))
    + (np.zeros(0), np.zeros(0), np.zeros(0))
)

#: ImplicitEuler's preconditioners. "factored": A0 = M (1 + dt alpha) + (dt beta + dt^2) K0 with the
#: rest stiffness K0, factored once per model and dt by SuperLU: exact for a linear model (CG takes
#: one iteration), close for a non-linear one near rest. "mass": the mass term, free but weak (CG's
#: iterations grow with dt^2 K / M and with lambda / mu). "auto": factored up to FACTOR_LIMIT free
#: components, beyond which the fill-in of a 3D mesh's factor makes it too costly.
PRECONDITIONERS = ("auto", "factored", "mass")
FACTOR_LIMIT = 20_000


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
        if preconditioner not in PRECONDITIONERS:
            raise InputError(f"preconditioner = {preconditioner!r}: must be one of {', '.join(PRECONDITIONERS)}")
        self.tol, self.maxit, self.iterations, self.worst_iterations = tol, maxit, 0, 0
        self.preconditioner = preconditioner
        self._factor = None  # (model, (dt, alpha, beta), factor tuple)

    def preconditioner_for(self, model: Model) -> str:
        """The preconditioner this integrator uses on ``model``: "factored" or "mass"."""
        if self.preconditioner != "auto":
            return self.preconditioner
        return "factored" if int(np.count_nonzero(model.loading.free)) <= FACTOR_LIMIT else "mass"

    def _factored(self, model: Model, dt: float) -> tuple:
        key = (dt, self.alpha, self.beta)
        if self._factor is None or self._factor[0] is not model or self._factor[1] != key:
            self._factor = (model, key, _factorise(model, 1.0 + dt * self.alpha, dt * self.beta + dt * dt))
        return self._factor[2]

    def critical_dt(self, model: Model, omega2: float | None = None) -> float:
        return math.inf  # A-stable for linear models; the non-linear ones are checked by the blow-up bound

    def step(self, model: Model, state: State, dt: float, n: int = 1, dt_crit: float | None = None) -> np.ndarray:
        """Advance ``state`` in place by n steps of dt (s); raises DivergenceError on blow-up. Returns the
        tools' force on the body in the last step, (L, 3) float64 N (``_run_implicit_euler``)."""
        lo = model.loading
        p = self._prepare(model)
        dt, n = _check_step(model, state, dt, n)
        factored = self.preconditioner_for(model) == "factored"
        fac = self._factored(model, dt) if factored else _NO_FACTOR
        work = tuple(np.zeros_like(state.u) for _ in range(9))
        status, last, its, worst, spent = _call(p, _run_implicit_euler, (
            n, dt, float(state.t), model.force_kernel, model.data, p.scratch, bool(model.linear), model.points,
            model.mass, lo.free, p.fext, p.tools, float(self.alpha), float(self.beta), p.bound, float(self.tol),
            int(self.maxit), bool(factored), fac, state.u, state.v, work, bool(self.budget), p.vt, p.reaction,
        ))  # fmt: skip
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


@dataclass
class StaticResult:
    """Outcome of ``solve_static``: state at equilibrium, steps taken, final relative residual."""

    state: State
    steps: int
    residual: float
    dt: float


def solve_static(
    model: Model,
    dt: float | None = None,
    rtol: float = 1e-10,
    max_steps: int = 2_000_000,
    chunk: int = 200,
    safety: float = 0.9,
) -> StaticResult:
    """Static equilibrium under the full loads by damped explicit dynamics (dynamic relaxation).

    Symplectic Euler with mass damping alpha = 2 omega_1, near critical for the slowest mode.
    omega_1^2 is re-estimated every ``chunk`` steps by the Rayleigh quotient u_f.K u_f / u_f.M u_f
    of the current free displacement, K the tangent stiffness at the current state (Underwood's adaptive dynamic relaxation): the displacement
    under a static load is dominated by the lowest mode, so the quotient tends to it. The tools move
    along their ramps from t = 0 (a load path: a large displacement imposed in one step would crush
    the elements beside the tool before the rest of the body can follow) and then hold. Converged
    when every tool has arrived and the free components' residual |f_int + f_ext| is below rtol
    times the load scale (|f_ext| and the tools' reaction), or has stalled for 50 chunks on a
    round-off floor below 1000 rtol (``StaticResult.residual`` says which).

    With ``dt`` given, every step uses it, and a dt above the critical one raises DivergenceError as
    any explicit run does. With dt = None the step adapts: ``safety`` x dt_crit at rest, and when a
    non-linear model stiffens (tension, compression) and a chunk diverges, the solve returns to the
    last good chunk, re-estimates omega_max there and goes on at ``safety`` times the new critical step.
    ``StaticResult.dt`` is the step in use at the end.
    """
    n = model.n_vertices
    state = State.at_rest(n)
    lo = model.loading
    arrived = float(lo.tool_ramp.max()) if len(lo.tool_ramp) else 0.0
    free = lo.free
    omega2 = max_eigenvalue(model)
    dt_crit = 2.0 / math.sqrt(omega2)
    adaptive = dt is None
    dt = safety * dt_crit if adaptive else dt
    integ = SymplecticEuler(alpha=0.0)
    alpha = 2.0 * math.sqrt(omega2) * 1e-3
    taken = 0
    residual = best = np.inf
    since_best = 0
    fmag = float(np.linalg.norm(lo.external_force * free))
    while taken < max_steps:
        integ.alpha = alpha
        good = state.copy()
        n = min(chunk, max_steps - taken)  # the budget is a number of steps, not of chunks
        try:
            integ.step(model, state, dt, n, dt_crit=dt_crit)
        except DivergenceError:
            if not adaptive or model.linear:
                raise
            state = good
            omega2 = max(omega2, max_eigenvalue(model, state.u))
            new_crit = 2.0 / math.sqrt(omega2)
            if new_crit >= dt_crit:  # the estimate did not move: halve instead of looping
                new_crit = 0.5 * dt_crit
            dt_crit = new_crit
            dt = safety * dt_crit
            state.v[:] = 0.0
            continue
        taken += n
        f = model.internal_force(state.u)
        r = (f + lo.external_force) * free
        scale = max(fmag, float(np.linalg.norm(model.reaction(state.u))), 1e-300)
        residual = float(np.linalg.norm(r)) / scale
        if state.t >= arrived:
            if residual < rtol:
                break
            if residual < 0.9 * best:
                best, since_best = residual, 0
            else:
                since_best += 1
            # a round-off floor (mass-spring lengths lose digits to |x_j - x_i| - L): accept a plateau
            # within 1000 rtol that has not improved for 50 chunks; the residual reached is reported
            if since_best >= 50 and best < 1e3 * rtol:
                break
        uf = state.u * free
        den = float(np.sum(model.mass[:, None] * uf * uf))
        if den > 0.0:
            # u_f.K(u) u_f / u_f.M u_f with K(u) the tangent stiffness at the current state, applied to
            # the free part alone (K_fp u_p is no stiffness of the free system): a central difference
            # of the force along u_f, exact for a linear model
            h = 1e-4 / max(float(np.abs(uf).max()), 1e-300) * float(np.abs(state.u).max() + 1e-12)
            kuf = (model.internal_force(state.u - h * uf) - model.internal_force(state.u + h * uf)) / (2.0 * h)
            rq = float(np.sum(kuf * uf)) / den
            if rq > 0.0:
                alpha = 2.0 * math.sqrt(min(rq, omega2))
    else:
        raise NotConvergedError(
            f"{model.name}: damped dynamics reached a relative residual of {residual:.2e} "
            f"(asked {rtol:.1e}) in {taken} steps of {dt:.3g} s"
        )
    state.v[:] = 0.0
    state.steps = taken
    return StaticResult(state=state, steps=taken, residual=residual, dt=dt)


def solve_static_implicit(
    model: Model, dt: float, rtol: float = 1e-10, max_steps: int = 20_000, integrator: ImplicitEuler | None = None
) -> StaticResult:
    """Static equilibrium by implicit Euler steps of dt (its numerical damping settles every mode a
    large step resolves poorly): the tools follow their ramps, then the loop stops when the free
    residual is below rtol times the load scale. Raises NotConvergedError past ``max_steps``."""
    integ = integrator if integrator is not None else ImplicitEuler(tol=min(1e-10, rtol))
    lo = model.loading
    state = State.at_rest(model.n_vertices)
    arrived = float(lo.tool_ramp.max()) if len(lo.tool_ramp) else 0.0
    fmag = float(np.linalg.norm(lo.external_force * lo.free))
    residual = best = np.inf
    since_best = 0
    for k in range(1, max_steps + 1):
        integ.step(model, state, dt, 1)  # raises NotConvergedError when CG stops short (unless a budget)
        if state.t < arrived:
            continue
        r = (model.internal_force(state.u) + lo.external_force) * lo.free
        scale = max(fmag, float(np.linalg.norm(model.reaction(state.u))), 1e-300)
        residual = float(np.linalg.norm(r)) / scale
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
