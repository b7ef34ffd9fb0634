"""Hyperelastic material laws: energy density W(F) and first Piola-Kirchhoff stress P(F) = dW/dF.

One law per function, each a pure function of the deformation gradient F (3, 3) float64
(dimensionless) and named coefficients in Pa, returning J/m^3 (energy) or Pa (stress). They are numba
functions so that kernels can call them per element; numpy callers get the same code.

The fibre terms of Picinbono, Delingette & Ayache (2003, eq. 9) are part of the linear and StVK laws: for
an isotropic material pass a = 0 or dlam = dmu = 0. The neo-Hookean law is isotropic.
"""

from __future__ import annotations

import numba as nb
import numpy as np

_JIT = dict(nogil=True, cache=True, fastmath=False)


@nb.njit(**_JIT)
def linear_energy(F, lam, mu, a, dlam, dmu):
    """Linear (small-strain) energy, Delingette & Ayache 2004 eq. (2.4) with Picinbono's fibre terms.

    eps = (F + F^T)/2 - I
    W = lam/2 (tr eps)^2 + mu eps:eps + dlam/2 (a.eps a)^2 + dmu |eps a|^2
    """
    eps = 0.5 * (F + F.T) - np.eye(3)
    tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
    ea = eps @ a
    aea = a @ ea
    return 0.5 * lam * tr * tr + mu * np.sum(eps * eps) + 0.5 * dlam * aea * aea + dmu * (ea @ ea)


@nb.njit(**_JIT)
def linear_pk1(F, lam, mu, a, dlam, dmu):
    """Stress of linear_energy: sigma = lam tr(eps) I + 2 mu eps + dlam (a.eps a) a(x)a
    + dmu (a (x) eps a + eps a (x) a). Small strain: all stress measures coincide.
    """
    eps = 0.5 * (F + F.T) - np.eye(3)
    tr = eps[0, 0] + eps[1, 1] + eps[2, 2]
    ea = eps @ a
    aea = a @ ea
    s = 2.0 * mu * eps + lam * tr * np.eye(3)
    s += dlam * aea * np.outer(a, a) + dmu * (np.outer(a, ea) + np.outer(ea, a))
    return s


@nb.njit(**_JIT)
def stvk_energy(F, lam, mu, a, dlam, dmu):
    """St Venant-Kirchhoff energy (Picinbono et al. 2003 eq. 5 and 9).

    E = (F^T F - I)/2   Green-Lagrange strain
    W = lam/2 (tr E)^2 + mu E:E + dlam/2 (a.E a)^2 + dmu |E a|^2
    """
    E = 0.5 * (F.T @ F - np.eye(3))
    tr = E[0, 0] + E[1, 1] + E[2, 2]
    ea = E @ a
    aea = a @ ea
    return 0.5 * lam * tr * tr + mu * np.sum(E * E) + 0.5 * dlam * aea * aea + dmu * (ea @ ea)


@nb.njit(**_JIT)
def stvk_pk1(F, lam, mu, a, dlam, dmu):
    """P = F S with S = lam tr(E) I + 2 mu E + dlam (a.E a) a(x)a + dmu (a (x) E a + E a (x) a)."""
    E = 0.5 * (F.T @ F - np.eye(3))
    tr = E[0, 0] + E[1, 1] + E[2, 2]
    ea = E @ a
    aea = a @ ea
    S = 2.0 * mu * E + lam * tr * np.eye(3)
    S += dlam * aea * np.outer(a, a) + dmu * (np.outer(a, ea) + np.outer(ea, a))
    return F @ S


@nb.njit(**_JIT)
def neo_hookean_energy(F, lam, mu):
    """Compressible neo-Hookean energy (Bonet & Wood, Nonlinear Continuum Mechanics for Finite Element
    Analysis, 2nd ed., eq. 6.27; Ogden 1984), isotropic:

    W = mu/2 (tr(F^T F) - 3) - mu ln J + lam/2 (ln J)^2,   J = det F

    It linearises to linear elasticity with the same Lame constants lam and mu (Pa). W = +inf where J <= 0:
    an inverted element has no energy, and the force of one is NaN (the integrators stop on it).
    """
    J = det3(F)
    if not J > 0.0:
        return np.inf
    lnj = np.log(J)
    return 0.5 * mu * (np.sum(F * F) - 3.0) - mu * lnj + 0.5 * lam * lnj * lnj


@nb.njit(**_JIT)
def neo_hookean_pk1(F, lam, mu):
    """P = dW/dF of neo_hookean_energy: P = mu (F - F^-T) + lam ln(J) F^-T (Bonet & Wood eq. 6.28)."""
    J = det3(F)
    FinvT = np.linalg.inv(F).T
    return mu * (F - FinvT) + lam * np.log(J) * FinvT


@nb.njit(**_JIT)
def det3(F):
    """det F of a (3, 3) matrix by the rule of Sarrus: NaN for a matrix holding a NaN, where numba's
    np.linalg.det raises LinAlgError (the energy at a NaN displacement was an exception, its force NaN)."""
    return (
        F[0, 0] * (F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1])
        - F[0, 1] * (F[1, 0] * F[2, 2] - F[1, 2] * F[2, 0])
        + F[0, 2] * (F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0])
    )


@nb.njit(**_JIT)
def volume_penalty_energy(F, kappa):
    """Incompressibility penalty W = kappa/2 (J - 1)^2, J = det F (Picinbono et al. 2003, sec. 4)."""
    J = det3(F)
    return 0.5 * kappa * (J - 1.0) ** 2


@nb.njit(**_JIT)
def volume_penalty_pk1(F, kappa):
    """P = kappa (J - 1) cof(F), with cof(F) = dJ/dF = J F^-T."""
    J = det3(F)
    cof = np.empty((3, 3))
    cof[0, 0] = F[1, 1] * F[2, 2] - F[1, 2] * F[2, 1]
    cof[0, 1] = F[1, 2] * F[2, 0] - F[1, 0] * F[2, 2]
    cof[0, 2] = F[1, 0] * F[2, 1] - F[1, 1] * F[2, 0]
    cof[1, 0] = F[0, 2] * F[2, 1] - F[0, 1] * F[2, 2]
    cof[1, 1] = F[0, 0] * F[2, 2] - F[0, 2] * F[2, 0]
    cof[1, 2] = F[0, 1] * F[2, 0] - F[0, 0] * F[2, 1]
    cof[2, 0] = F[0, 1] * F[1, 2] - F[0, 2] * F[1, 1]
    cof[2, 1] = F[0, 2] * F[1, 0] - F[0, 0] * F[1, 2]
    cof[2, 2] = F[0, 0] * F[1, 1] - F[0, 1] * F[1, 0]
    return kappa * (J - 1.0) * cof


def linear_elasticity_tensor(lam: float, mu: float, a: np.ndarray, dlam: float, dmu: float):
    """Fourth-order tensor C_pqrs = d^2 W / d eps_pq d eps_rs of linear_energy, Pa: (3, 3, 3, 3) for
    one fibre direction a (3,), (K, 3, 3, 3, 3) for K directions a (K, 3) (zeros: isotropic).

    C = lam d_pq d_rs + mu (d_pr d_qs + d_ps d_qr) + dlam a_p a_q a_r a_s
        + dmu/2 (d_pr a_q a_s + d_qr a_p a_s + d_ps a_q a_r + d_qs a_p a_r)
    """
    d = np.eye(3)
    a = np.asarray(a, dtype=float)
    aa = np.einsum("...p,...q->...pq", a, a)
    C = lam * np.einsum("pq,rs->pqrs", d, d)
    C = C + mu * (np.einsum("pr,qs->pqrs", d, d) + np.einsum("ps,qr->pqrs", d, d))
    C = C + dlam * np.einsum("...pq,...rs->...pqrs", aa, aa)
    C = C + (
        0.5
        * dmu
        * (
            np.einsum("pr,...qs->...pqrs", d, aa)
            + np.einsum("qr,...ps->...pqrs", d, aa)
            + np.einsum("ps,...qr->...pqrs", d, aa)
            + np.einsum("qs,...pr->...pqrs", d, aa)
        )
    )
    return C
