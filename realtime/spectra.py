"""Spectra of a model at rest or at a state, and the critical time steps they give.

omega_max^2 (``max_eigenvalue``) and omega_1^2 (``min_eigenvalue``) of M^-1 K on the free components,
by Lanczos on the force kernel or shift-invert on the rest stiffness, and ``element_critical_dt``, a
proven lower bound on 2 / omega_max from each model's own element eigenvalue bound.
"""

from __future__ import annotations

import math

import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .model import Model


def _scaled_stiffness(model: Model, u: np.ndarray | None = None) -> spla.LinearOperator:
    """M^-1/2 K M^-1/2 on the free components as a LinearOperator, K the stiffness at displacement u
    (default: rest), applied through the force kernel: exactly for a linear model, by a central
    difference of the force for a non-linear one."""
    n = model.n_vertices
    u0 = np.zeros((n, 3)) if u is None else model.nodal("max_eigenvalue: u", u).astype(float, copy=False)
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
    Rigid tools (Loading.contacts) add nothing: the explicit steps take their contact implicitly
    (``contact.contact_kick``), stable at any step.
    """
    op = _scaled_stiffness(model, u)
    v0 = np.random.default_rng(0).standard_normal(op.shape[0])
    return float(spla.eigsh(op, k=1, which="LA", tol=tol, v0=v0, return_eigenvectors=False)[0])


#: Free components up to which ``min_eigenvalue`` factors the rest stiffness for shift-invert Lanczos:
#: one factor and a few solves, where Lanczos on the force kernel needs more products the finer the
#: mesh. SOFA's liver refined twice (57 987 free components): 10.8 s by shift-invert (scipy's SuperLU,
#: COLAMD), over 4 minutes unfinished by Lanczos on the force kernel.
SHIFT_INVERT_LIMIT = 100_000


def min_eigenvalue(model: Model, tol: float = 1e-3, factored_only: bool = False) -> float | None:
    """Smallest eigenvalue omega_1^2 (1/s^2) of M^-1 K on the free components, at rest, to a relative
    tolerance ``tol`` (enough to choose a time step): the slowest mode, the one a static relaxation
    must settle.

    Where the rest stiffness is known as a matrix (Model.rest_stiffness: exact at rest for every model
    without the volume penalty) and small enough to factor (SHIFT_INVERT_LIMIT), by shift-invert Lanczos about 0 (a few
    iterations whatever the conditioning); otherwise by Lanczos on the force kernel, whose iterations
    grow with the condition number (2e5 products on the cantilever at nu = 0.4999, 20 s).
    ``factored_only``: None instead of that (and of a singular K's 0), for a caller that wants the value
    only where it is cheap (``statics.solve_static``'s damping).
    """
    fidx = np.flatnonzero(model.loading.free.reshape(-1) != 0.0)
    v0 = np.random.default_rng(0).standard_normal(len(fidx))
    if not model.materials.per_tet("volume_penalty").any() and len(fidx) <= SHIFT_INVERT_LIMIT:
        K = model.rest_stiffness()[fidx][:, fidx].tocsc()
        M = sp.diags(np.repeat(model.mass, 3)[fidx]).tocsc()
        try:
            lam = spla.eigsh(K, k=1, M=M, sigma=0.0, which="LM", tol=tol, v0=v0, return_eigenvectors=False)
            return float(lam[0])
        except RuntimeError:  # K singular (a free body): its smallest eigenvalue is 0, which Lanczos finds
            pass
    if factored_only:
        return None
    op = _scaled_stiffness(model)
    return float(
        spla.eigsh(op, k=1, which="SA", tol=tol, v0=v0, maxiter=100 * op.shape[0], return_eigenvectors=False)[0]
    )


def zero_energy_modes(model: Model, tol: float = 1e-10, most: int = 6) -> tuple[int, float]:
    """The held body's modes without stiffness at rest: how many generalised eigenvalues of (K, M) on the
    free components lie below ``tol`` times the largest (counted up to ``most``), and the smallest such
    ratio. A static problem with one has no unique equilibrium: a part held at too few vertices (free to
    turn about them), or tetrahedra joined only at a vertex or an edge (a ball joint, a hinge). Round-off
    leaves such a mode near 1e-16 of the largest; but a slender, finely meshed body's soft bending modes
    can fall below ``tol`` too (SOFA's 16 m raptor: 3e-12), so a count is a reason to look for a cause,
    not a cause (verification.loading.check_held asks for one). K is the model's rest stiffness (Model.rest_stiffness); the largest eigenvalue is taken from
    the element bound (an upper bound, Model.element_eigenvalue_bound). Dense below a few hundred free
    components, else shift-invert Lanczos about a small negative shift (K + s M is then never singular)."""
    fidx = np.flatnonzero(model.loading.free.reshape(-1) != 0.0)
    if len(fidx) == 0:
        return 0, math.inf
    K = model.rest_stiffness()[fidx][:, fidx]
    m = np.repeat(model.mass, 3)[fidx]
    top = model.element_eigenvalue_bound()
    if len(fidx) <= 600:
        s = 1.0 / np.sqrt(m)
        lam = np.linalg.eigvalsh(s[:, None] * K.toarray() * s[None, :])[: min(most, len(fidx))]
    else:
        lam = spla.eigsh(
            K.tocsc(), k=most, M=sp.diags(m).tocsc(), sigma=-1e-6 * top, which="LM", return_eigenvectors=False
        )
    ratio = np.sort(np.asarray(lam)) / top
    return int(np.count_nonzero(ratio < tol)), float(max(ratio[0], 0.0))


def element_critical_dt(model: Model) -> float:
    """A proven lower bound, s, on the undamped explicit critical step 2 / omega_max at rest.

    With lumped masses, M = sum of the elements' shares M_e and K = sum of K_e, the Rayleigh quotient
    gives omega_max^2 <= max over elements of lambda_max(K_e, M_e) (the element eigenvalue inequality,
    Irons and Treharne 1971), so 2 / sqrt(max_e lambda_max(K_e, M_e)) <= 2 / omega_max. Each model
    gives its elements' bound (``Model.element_eigenvalue_bound``): the tetrahedra's or, for
    mass-spring, the springs'. Measured: 0.31 to 0.37 of the Lanczos value for tetrahedra, 0.45 for
    springs; runs record both (dt_crit_element, dt_crit).
    """
    return 2.0 / math.sqrt(model.element_eigenvalue_bound())
