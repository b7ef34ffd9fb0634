"""Material laws of the reference as UFL energy densities; the stress is always derived from them.

Each function takes the deformation gradient F (a UFL 3x3 expression) and named coefficients (UFL
constants or floats, Pa) and returns the energy per unit reference volume, J/m^3. The formulas are
those of ``realtime.laws`` (same sources), written once more in UFL because the reference must not
borrow its physics from what it judges: the cross-solver tests compare the two.
"""

from __future__ import annotations

import ufl


def linear_energy(F, lam, mu, a, dlam, dmu):
    """Small strain: eps = sym(F) - I; W = lam/2 tr(eps)^2 + mu eps:eps + dlam/2 (a.eps a)^2 + dmu |eps a|^2
    (Delingette & Ayache 2004; fibre terms of Picinbono et al. 2003)."""
    eps = ufl.sym(F) - ufl.Identity(3)
    ea = eps * a
    return (
        lam / 2 * ufl.tr(eps) ** 2
        + mu * ufl.inner(eps, eps)
        + dlam / 2 * ufl.inner(a, ea) ** 2
        + dmu * ufl.inner(ea, ea)
    )


def stvk_energy(F, lam, mu, a, dlam, dmu):
    """St Venant-Kirchhoff: E = (F^T F - I)/2; W = lam/2 tr(E)^2 + mu E:E + dlam/2 (a.E a)^2 + dmu |E a|^2
    (Picinbono, Delingette & Ayache 2003, eq. 5 and 9)."""
    E = 0.5 * (F.T * F - ufl.Identity(3))
    ea = E * a
    return lam / 2 * ufl.tr(E) ** 2 + mu * ufl.inner(E, E) + dlam / 2 * ufl.inner(a, ea) ** 2 + dmu * ufl.inner(ea, ea)


def volume_penalty_energy(F, kappa):
    """Incompressibility penalty W = kappa/2 (det F - 1)^2 (Picinbono et al. 2003, sec. 4)."""
    return kappa / 2 * (ufl.det(F) - 1) ** 2


def neo_hookean_energy(F, lam, mu, a, dlam, dmu):
    """Compressible neo-Hookean: W = mu/2 (tr(F^T F) - 3) - mu ln J + lam/2 (ln J)^2, J = det F (Bonet &
    Wood, Nonlinear Continuum Mechanics for Finite Element Analysis, 2nd ed., eq. 6.27). Isotropic: the
    fibre coefficients ``a``, ``dlam``, ``dmu`` are taken for the common signature and not used (a
    material with fibres and this law is refused where it is made)."""
    J = ufl.det(F)
    return mu / 2 * (ufl.tr(F.T * F) - 3) - mu * ufl.ln(J) + lam / 2 * ufl.ln(J) ** 2


def stable_neo_hookean_energy(F, lam, mu, a, dlam, dmu):
    """Stable neo-Hookean with its log term (Smith, de Goes & Kim, "Stable Neo-Hookean Flesh Simulation",
    ACM TOG 2018, eq. 14), its constants matched to the Lame constants at rest (section 3.4): k_mu = 4/3
    mu, k_lam = lam + 5/6 mu, alpha = 1 + k_mu / k_lam - k_mu / (4 k_lam);
    W = k_mu/2 (I_C - 3) - k_mu/2 ln(I_C + 1) + k_lam/2 (J - alpha)^2, I_C = tr(F^T F). newton's
    semi-implicit tetrahedra run it. Isotropic (fibre coefficients unused)."""
    k_mu, k_lam = 4 * mu / 3, lam + 5 * mu / 6
    alpha = 1 + k_mu / k_lam - k_mu / (4 * k_lam)
    ic = ufl.tr(F.T * F)
    return k_mu / 2 * (ic - 3) - k_mu / 2 * ufl.ln(ic + 1) + k_lam / 2 * (ufl.det(F) - alpha) ** 2


def stable_neo_hookean_no_log_energy(F, lam, mu, a, dlam, dmu):
    """Stable neo-Hookean without the log term (Smith et al. 2018, eq. 13), its constants matched at rest:
    k_lam = lam + mu, alpha = 1 + mu / k_lam; W = mu/2 (I_C - 3) + k_lam/2 (J - alpha)^2. newton's VBD
    tetrahedra run it. Isotropic (fibre coefficients unused)."""
    k_lam = lam + mu
    alpha = 1 + mu / k_lam
    return mu / 2 * (ufl.tr(F.T * F) - 3) + k_lam / 2 * (ufl.det(F) - alpha) ** 2


LAWS = {
    "linear": linear_energy,
    "stvk": stvk_energy,
    "neo-hookean": neo_hookean_energy,
    "stable-neo-hookean": stable_neo_hookean_energy,
    "stable-neo-hookean-no-log": stable_neo_hookean_no_log_energy,
}
