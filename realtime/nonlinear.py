"""Per-tetrahedron kernels of the non-linear models: StVK tensor-mass, corotational, hybrid.

All three evaluate, on each tetrahedron e with rest shape-function gradients g_a and volume V_e,

    H = sum_a u_a (x) g_a,   F = I + H,   f_a -= V_e P(F) g_a

with P the first Piola-Kirchhoff stress of the model's law. This is the exact negative gradient of the
P1 energy sum_e V_e W(F_e): for StVK it is the same force as Picinbono's non-linear tensor-mass (2003),
whose vertex, edge, triangle and tetrahedron tensors are the expansion of this expression in powers
of u; evaluating P per element is the cheaper way to the same numbers (about 130 flops a tetrahedron
against a few hundred for the tensor sums), and the cross-solver test checks it against dolfinx's
P1 StVK residual.

Data tuples are documented at each kernel; all arrays are float64 unless said, and scratch arrays
passed in the tuple keep the kernels free of allocation.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .geometry import shape_gradients
from .material import Material
from .tensor_mass import linear_tm_energy, linear_tm_force

_JIT = dict(nogil=True, cache=True)
#: The force kernels of the step loop: contraction to fused multiply-adds and reassociation change
#: results at round-off level only (the cross-solver tests hold at 1e-10); no NaN/inf assumptions, so
#: the blow-up check still sees a NaN.
_HOT = dict(nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz", "arcp"})


def tet_data(points: np.ndarray, tets: np.ndarray):
    """tets (M, 4) int64, grads (M, 3, 3) (rows g_1..g_3; g_0 = -(g_1 + g_2 + g_3)), vol (M,) m^3."""
    g, vol = shape_gradients(points, tets)
    return np.ascontiguousarray(tets, dtype=np.int64), np.ascontiguousarray(g[:, 1:, :]), np.ascontiguousarray(vol)


def law_params(material: Material) -> np.ndarray:
    """(8,) float64: lam, mu, a_x, a_y, a_z, dlam, dmu, kappa (Pa, unit fibre, Pa, Pa, Pa)."""
    a = material.fiber_vector
    return np.array([material.lam, material.mu, a[0], a[1], a[2], material.dlam, material.dmu, material.volume_penalty])


@nb.njit(inline="always", **_JIT)
def _grad_u(tets, g, e, u, H):
    """H (3, 3) = sum_a u_a (x) g_a on tetrahedron e."""
    i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    for r in range(3):
        d1 = u[i1, r] - u[i0, r]
        d2 = u[i2, r] - u[i0, r]
        d3 = u[i3, r] - u[i0, r]
        for c in range(3):
            H[r, c] = d1 * g[e, 0, c] + d2 * g[e, 1, c] + d3 * g[e, 2, c]


@nb.njit(inline="always", **_JIT)
def _scatter(tets, g, e, vol, P, f):
    """f_a -= V P g_a for the four vertices of tetrahedron e (g_0 = -(g_1 + g_2 + g_3))."""
    i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    for r in range(3):
        f1 = vol * (P[r, 0] * g[e, 0, 0] + P[r, 1] * g[e, 0, 1] + P[r, 2] * g[e, 0, 2])
        f2 = vol * (P[r, 0] * g[e, 1, 0] + P[r, 1] * g[e, 1, 1] + P[r, 2] * g[e, 1, 2])
        f3 = vol * (P[r, 0] * g[e, 2, 0] + P[r, 1] * g[e, 2, 1] + P[r, 2] * g[e, 2, 2])
        f[i1, r] -= f1
        f[i2, r] -= f2
        f[i3, r] -= f3
        f[i0, r] += f1 + f2 + f3


@nb.njit(inline="always", **_HOT)
def _stvk_element(tets, g, vol, e, u, lam, mu2, a0, a1, a2, dlam, dmu, kappa, fibre, f, sign):
    """Add sign x (the StVK force of tetrahedron e) to f, all in scalars (registers, no scratch)."""
    i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
    g10, g11, g12 = g[e, 0, 0], g[e, 0, 1], g[e, 0, 2]
    g20, g21, g22 = g[e, 1, 0], g[e, 1, 1], g[e, 1, 2]
    g30, g31, g32 = g[e, 2, 0], g[e, 2, 1], g[e, 2, 2]
    ux0, uy0, uz0 = u[i0, 0], u[i0, 1], u[i0, 2]
    ax, ay, az = u[i1, 0] - ux0, u[i1, 1] - uy0, u[i1, 2] - uz0
    bx, by, bz = u[i2, 0] - ux0, u[i2, 1] - uy0, u[i2, 2] - uz0
    cx, cy, cz = u[i3, 0] - ux0, u[i3, 1] - uy0, u[i3, 2] - uz0
    h00 = ax * g10 + bx * g20 + cx * g30
    h01 = ax * g11 + bx * g21 + cx * g31
    h02 = ax * g12 + bx * g22 + cx * g32
    h10 = ay * g10 + by * g20 + cy * g30
    h11 = ay * g11 + by * g21 + cy * g31
    h12 = ay * g12 + by * g22 + cy * g32
    h20 = az * g10 + bz * g20 + cz * g30
    h21 = az * g11 + bz * g21 + cz * g31
    h22 = az * g12 + bz * g22 + cz * g32
    # Green-Lagrange E = (H + H^T + H^T H) / 2
    e00 = h00 + 0.5 * (h00 * h00 + h10 * h10 + h20 * h20)
    e11 = h11 + 0.5 * (h01 * h01 + h11 * h11 + h21 * h21)
    e22 = h22 + 0.5 * (h02 * h02 + h12 * h12 + h22 * h22)
    e01 = 0.5 * (h01 + h10 + h00 * h01 + h10 * h11 + h20 * h21)
    e02 = 0.5 * (h02 + h20 + h00 * h02 + h10 * h12 + h20 * h22)
    e12 = 0.5 * (h12 + h21 + h01 * h02 + h11 * h12 + h21 * h22)
    ltr = lam * (e00 + e11 + e22)
    s00 = mu2 * e00 + ltr
    s11 = mu2 * e11 + ltr
    s22 = mu2 * e22 + ltr
    s01 = mu2 * e01
    s02 = mu2 * e02
    s12 = mu2 * e12
    if fibre:
        q0 = e00 * a0 + e01 * a1 + e02 * a2
        q1 = e01 * a0 + e11 * a1 + e12 * a2
        q2 = e02 * a0 + e12 * a1 + e22 * a2
        c = dlam * (a0 * q0 + a1 * q1 + a2 * q2)
        s00 += c * a0 * a0 + 2.0 * dmu * a0 * q0
        s11 += c * a1 * a1 + 2.0 * dmu * a1 * q1
        s22 += c * a2 * a2 + 2.0 * dmu * a2 * q2
        s01 += c * a0 * a1 + dmu * (a0 * q1 + q0 * a1)
        s02 += c * a0 * a2 + dmu * (a0 * q2 + q0 * a2)
        s12 += c * a1 * a2 + dmu * (a1 * q2 + q1 * a2)
    # P = (I + H) S
    p00 = s00 + h00 * s00 + h01 * s01 + h02 * s02
    p01 = s01 + h00 * s01 + h01 * s11 + h02 * s12
    p02 = s02 + h00 * s02 + h01 * s12 + h02 * s22
    p10 = s01 + h10 * s00 + h11 * s01 + h12 * s02
    p11 = s11 + h10 * s01 + h11 * s11 + h12 * s12
    p12 = s12 + h10 * s02 + h11 * s12 + h12 * s22
    p20 = s02 + h20 * s00 + h21 * s01 + h22 * s02
    p21 = s12 + h20 * s01 + h21 * s11 + h22 * s12
    p22 = s22 + h20 * s02 + h21 * s12 + h22 * s22
    if kappa != 0.0:
        f00, f01, f02 = 1.0 + h00, h01, h02
        f10, f11, f12 = h10, 1.0 + h11, h12
        f20, f21, f22 = h20, h21, 1.0 + h22
        c00 = f11 * f22 - f12 * f21
        c01 = f12 * f20 - f10 * f22
        c02 = f10 * f21 - f11 * f20
        k = kappa * (f00 * c00 + f01 * c01 + f02 * c02 - 1.0)
        p00 += k * c00
        p01 += k * c01
        p02 += k * c02
        p10 += k * (f02 * f21 - f01 * f22)
        p11 += k * (f00 * f22 - f02 * f20)
        p12 += k * (f01 * f20 - f00 * f21)
        p20 += k * (f01 * f12 - f02 * f11)
        p21 += k * (f02 * f10 - f00 * f12)
        p22 += k * (f00 * f11 - f01 * f10)
    v = sign * vol[e]
    fx1 = v * (p00 * g10 + p01 * g11 + p02 * g12)
    fy1 = v * (p10 * g10 + p11 * g11 + p12 * g12)
    fz1 = v * (p20 * g10 + p21 * g11 + p22 * g12)
    fx2 = v * (p00 * g20 + p01 * g21 + p02 * g22)
    fy2 = v * (p10 * g20 + p11 * g21 + p12 * g22)
    fz2 = v * (p20 * g20 + p21 * g21 + p22 * g22)
    fx3 = v * (p00 * g30 + p01 * g31 + p02 * g32)
    fy3 = v * (p10 * g30 + p11 * g31 + p12 * g32)
    fz3 = v * (p20 * g30 + p21 * g31 + p22 * g32)
    f[i1, 0] -= fx1
    f[i1, 1] -= fy1
    f[i1, 2] -= fz1
    f[i2, 0] -= fx2
    f[i2, 1] -= fy2
    f[i2, 2] -= fz2
    f[i3, 0] -= fx3
    f[i3, 1] -= fy3
    f[i3, 2] -= fz3
    f[i0, 0] += fx1 + fx2 + fx3
    f[i0, 1] += fy1 + fy2 + fy3
    f[i0, 2] += fz1 + fz2 + fz3


@nb.njit(**_HOT)
def stvk_force(data, u, f):
    """StVK tensor-mass force (Picinbono et al. 2003), with fibre terms and the volume penalty.

    Written out in scalars (_stvk_element): the 3x3 algebra stays in registers (scratch arrays could
    alias u and f, which forces the compiler to store and reload them).
    data: (tets (M,4) int64, grads (M,3,3) 1/m, vol (M,) m^3, prm (8,) law_params, 3 scratch (3,3))
    u: (N, 3) displacement, m.   f: (N, 3) force, N (overwritten).
    """
    tets, g, vol, prm = data[0], data[1], data[2], data[3]
    lam, mu, a0, a1, a2, dlam, dmu, kappa = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6], prm[7]
    fibre = dlam != 0.0 or dmu != 0.0
    f[:] = 0.0
    for e in range(tets.shape[0]):
        _stvk_element(tets, g, vol, e, u, lam, 2.0 * mu, a0, a1, a2, dlam, dmu, kappa, fibre, f, 1.0)


@nb.njit(**_JIT)
def _stvk_density(H, prm):
    """StVK energy density (J/m^3) at F = I + H with the law_params prm: lam/2 tr(E)^2 + mu E:E
    + dlam/2 (a.Ea)^2 + dmu |Ea|^2 + kappa/2 (J - 1)^2 (the energy stvk_force differentiates)."""
    lam, mu, dlam, dmu, kappa = prm[0], prm[1], prm[5], prm[6], prm[7]
    a = prm[2:5]
    F = np.eye(3) + H
    E = 0.5 * (F.T @ F - np.eye(3))
    tr = E[0, 0] + E[1, 1] + E[2, 2]
    ea = E @ a
    aea = a @ ea
    J = np.linalg.det(F)
    return (
        0.5 * lam * tr * tr
        + mu * np.sum(E * E)
        + 0.5 * dlam * aea * aea
        + dmu * (ea @ ea)
        + 0.5 * kappa * (J - 1.0) ** 2
    )


@nb.njit(**_JIT)
def stvk_energy(data, u):
    """sum_e V_e W(F_e), J: lam/2 tr(E)^2 + mu E:E + dlam/2 (a.Ea)^2 + dmu |Ea|^2 + kappa/2 (J-1)^2."""
    tets, g, vol, prm, H, S, P = data
    w = 0.0
    for e in range(tets.shape[0]):
        _grad_u(tets, g, e, u, H)
        w += vol[e] * _stvk_density(H, prm)
    return w


# ---------------------------------------------------------------------------------------------
# corotational


@nb.njit(inline="always", **_HOT)
def _polar(f00, f01, f02, f10, f11, f12, f20, f21, f22):
    """Rotation (9-tuple, row-major) of the polar decomposition F = R U.

    Scaled Newton iteration R <- (g R + R^-T / g) / 2, g = (|R^-1|_F / |R|_F)^(1/2) (Higham 1986):
    quadratic convergence for det F > 0, in registers; the scaling is dropped near convergence and
    the loop stops when a step changes R by less than 1e-9 (the next error is its square). An inverted or flat element (det F <= 1e-12)
    takes the SVD instead, with the sign of the smallest singular direction flipped so that R stays
    a rotation (Irving, Teran & Fedkiw 2004).
    """
    d = f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20)
    if d <= 1e-12:
        F = np.empty((3, 3))
        F[0, 0], F[0, 1], F[0, 2] = f00, f01, f02
        F[1, 0], F[1, 1], F[1, 2] = f10, f11, f12
        F[2, 0], F[2, 1], F[2, 2] = f20, f21, f22
        U, _, Vt = np.linalg.svd(F)
        if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
            U[:, 2] = -U[:, 2]
        Q = U @ Vt
        return Q[0, 0], Q[0, 1], Q[0, 2], Q[1, 0], Q[1, 1], Q[1, 2], Q[2, 0], Q[2, 1], Q[2, 2]
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = f00, f01, f02, f10, f11, f12, f20, f21, f22
    change = 1.0
    for _ in range(30):
        c00 = r11 * r22 - r12 * r21
        c01 = r12 * r20 - r10 * r22
        c02 = r10 * r21 - r11 * r20
        c10 = r02 * r21 - r01 * r22
        c11 = r00 * r22 - r02 * r20
        c12 = r01 * r20 - r00 * r21
        c20 = r01 * r12 - r02 * r11
        c21 = r02 * r10 - r00 * r12
        c22 = r00 * r11 - r01 * r10
        det = r00 * c00 + r01 * c01 + r02 * c02
        gam = 1.0
        if change > 1e-4:  # far from orthogonal: Higham's scaling; near it, gamma -> 1 and costs two roots
            nr = (
                r00 * r00
                + r01 * r01
                + r02 * r02
                + r10 * r10
                + r11 * r11
                + r12 * r12
                + r20 * r20
                + r21 * r21
                + r22 * r22
            )
            nc = (
                c00 * c00
                + c01 * c01
                + c02 * c02
                + c10 * c10
                + c11 * c11
                + c12 * c12
                + c20 * c20
                + c21 * c21
                + c22 * c22
            )
            gam = np.sqrt(np.sqrt(nc / (det * det * nr)))
        a = 0.5 * gam
        b = 0.5 / (gam * det)  # R^-T = cof(R) / det(R)
        n00, n01, n02 = a * r00 + b * c00, a * r01 + b * c01, a * r02 + b * c02
        n10, n11, n12 = a * r10 + b * c10, a * r11 + b * c11, a * r12 + b * c12
        n20, n21, n22 = a * r20 + b * c20, a * r21 + b * c21, a * r22 + b * c22
        change = (
            (n00 - r00) ** 2
            + (n01 - r01) ** 2
            + (n02 - r02) ** 2
            + (n10 - r10) ** 2
            + (n11 - r11) ** 2
            + (n12 - r12) ** 2
            + (n20 - r20) ** 2
            + (n21 - r21) ** 2
            + (n22 - r22) ** 2
        )
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = n00, n01, n02, n10, n11, n12, n20, n21, n22
        if change < 1e-18:  # |dR|_F < 1e-9: quadratic convergence puts this iterate at round-off
            break
    return r00, r01, r02, r10, r11, r12, r20, r21, r22


@nb.njit(**_HOT)
def corotational_force(data, u, f):
    """Corotational linear force: f_a -= V R sigma(sym(R^T F) - I) g_a, R the polar rotation of F.

    This is the exact gradient of W(F) = lam/2 tr(S - I)^2 + mu |S - I|^2, S = R^T F the polar stretch
    (the "corotated" energy; SOFA's TetrahedronFEMForceField, method "polar").
    data: (tets (M,4) int64, grads (M,3,3), vol (M,), prm (8,) law_params, 4 scratch (3,3))
    """
    tets, g, vol, prm, H = data[0], data[1], data[2], data[3], data[4]
    lam, mu = prm[0], prm[1]
    f[:] = 0.0
    for e in range(tets.shape[0]):
        _grad_u(tets, g, e, u, H)
        f00, f01, f02 = 1.0 + H[0, 0], H[0, 1], H[0, 2]
        f10, f11, f12 = H[1, 0], 1.0 + H[1, 1], H[1, 2]
        f20, f21, f22 = H[2, 0], H[2, 1], 1.0 + H[2, 2]
        r00, r01, r02, r10, r11, r12, r20, r21, r22 = _polar(f00, f01, f02, f10, f11, f12, f20, f21, f22)
        # strain in the rotated frame: sym(R^T F) - I
        s00 = r00 * f00 + r10 * f10 + r20 * f20 - 1.0
        s11 = r01 * f01 + r11 * f11 + r21 * f21 - 1.0
        s22 = r02 * f02 + r12 * f12 + r22 * f22 - 1.0
        s01 = 0.5 * (r00 * f01 + r10 * f11 + r20 * f21 + r01 * f00 + r11 * f10 + r21 * f20)
        s02 = 0.5 * (r00 * f02 + r10 * f12 + r20 * f22 + r02 * f00 + r12 * f10 + r22 * f20)
        s12 = 0.5 * (r01 * f02 + r11 * f12 + r21 * f22 + r02 * f01 + r12 * f11 + r22 * f21)
        ltr = lam * (s00 + s11 + s22)
        t00, t11, t22 = 2.0 * mu * s00 + ltr, 2.0 * mu * s11 + ltr, 2.0 * mu * s22 + ltr
        t01, t02, t12 = 2.0 * mu * s01, 2.0 * mu * s02, 2.0 * mu * s12
        # P = R sigma
        P = H
        P[0, 0] = r00 * t00 + r01 * t01 + r02 * t02
        P[0, 1] = r00 * t01 + r01 * t11 + r02 * t12
        P[0, 2] = r00 * t02 + r01 * t12 + r02 * t22
        P[1, 0] = r10 * t00 + r11 * t01 + r12 * t02
        P[1, 1] = r10 * t01 + r11 * t11 + r12 * t12
        P[1, 2] = r10 * t02 + r11 * t12 + r12 * t22
        P[2, 0] = r20 * t00 + r21 * t01 + r22 * t02
        P[2, 1] = r20 * t01 + r21 * t11 + r22 * t12
        P[2, 2] = r20 * t02 + r21 * t12 + r22 * t22
        _scatter(tets, g, e, vol[e], P, f)


@nb.njit(**_JIT)
def corotational_energy(data, u):
    """sum_e V_e (lam/2 tr(S - I)^2 + mu |S - I|^2), S = R^T F."""
    tets, g, vol, prm, H = data[0], data[1], data[2], data[3], data[4]
    lam, mu = prm[0], prm[1]
    w = 0.0
    for e in range(tets.shape[0]):
        _grad_u(tets, g, e, u, H)
        F = np.eye(3) + H
        r = _polar(F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2], F[2, 0], F[2, 1], F[2, 2])
        R = np.array(r).reshape(3, 3)
        S = R.T @ F - np.eye(3)
        S = 0.5 * (S + S.T)
        tr = S[0, 0] + S[1, 1] + S[2, 2]
        w += vol[e] * (0.5 * lam * tr * tr + mu * np.sum(S * S))
    return w


# ---------------------------------------------------------------------------------------------
# hybrid: linear tensor-mass everywhere, corrected to StVK on the tetrahedra that moved


@nb.njit(**_HOT)
def hybrid_force(data, u, f):
    """f = f_linear-tm(u) + sum over flagged tetrahedra of (f_stvk,e(u) - f_linear,e(u)).

    A tetrahedron is non-linear when one of its vertices moved more than ``threshold`` (m) from rest
    (Picinbono et al. 2003, section 5). Threshold 0: every tetrahedron, the stvk-tm force (to
    round-off). Threshold infinity: none, exactly the linear-tm force.
    data: (linear-tm data tuple, tets, grads, vol, prm, ke (M,4,4,3,3) element blocks,
           threshold (1,) m, flags (M,) bool scratch, H, S, P scratch (3,3))
    """
    lin, tets, g, vol, prm, ke, threshold, flags, H, S, P = data
    lam, mu, a0, a1, a2, dlam, dmu, kappa = prm[0], prm[1], prm[2], prm[3], prm[4], prm[5], prm[6], prm[7]
    fibre = dlam != 0.0 or dmu != 0.0
    linear_tm_force(lin, u, f)
    thr2 = threshold[0] * threshold[0]
    for e in range(tets.shape[0]):
        nonlinear = False
        for a in range(4):
            i = tets[e, a]
            if u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2:
                nonlinear = True
        flags[e] = nonlinear
        if not nonlinear:
            continue
        _stvk_element(tets, g, vol, e, u, lam, 2.0 * mu, a0, a1, a2, dlam, dmu, kappa, fibre, f, 1.0)
        # remove the element's linear contribution: f_a += K_ab u_b
        for a in range(4):
            ia = tets[e, a]
            for b in range(4):
                ib = tets[e, b]
                for r in range(3):
                    f[ia, r] += (
                        ke[e, a, b, r, 0] * u[ib, 0] + ke[e, a, b, r, 1] * u[ib, 1] + ke[e, a, b, r, 2] * u[ib, 2]
                    )


@nb.njit(**_JIT)
def hybrid_energy(data, u):
    """Energy of the same split, with the flags of the current u."""
    lin, tets, g, vol, prm, ke, threshold, flags, H, S, P = data
    w = linear_tm_energy(lin, u)
    thr2 = threshold[0] * threshold[0]
    for e in range(tets.shape[0]):
        nonlinear = False
        for k in range(4):
            i = tets[e, k]
            if u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2:
                nonlinear = True
        if not nonlinear:
            continue
        _grad_u(tets, g, e, u, H)
        w += vol[e] * _stvk_density(H, prm)
        for p in range(4):
            for q in range(4):
                w -= 0.5 * (u[tets[e, p]] @ (ke[e, p, q] @ u[tets[e, q]]))
    return w


# ---------------------------------------------------------------------------------------------
# mass-spring


@nb.njit(**_HOT)
def spring_force(data, u, f):
    """Edge springs: f_i += k_ij (|x_j - x_i| - L_ij) (x_j - x_i) / |x_j - x_i| (Delingette 1998).

    data: (points (N,3) m, edges (E,2) int64, stiffness (E,) N/m, rest_length (E,) m)
    """
    X, edges, k, L = data
    f[:] = 0.0
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        d0 = X[j, 0] + u[j, 0] - X[i, 0] - u[i, 0]
        d1 = X[j, 1] + u[j, 1] - X[i, 1] - u[i, 1]
        d2 = X[j, 2] + u[j, 2] - X[i, 2] - u[i, 2]
        length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
        s = k[e] * (length - L[e]) / length
        f[i, 0] += s * d0
        f[i, 1] += s * d1
        f[i, 2] += s * d2
        f[j, 0] -= s * d0
        f[j, 1] -= s * d1
        f[j, 2] -= s * d2


@nb.njit(**_JIT)
def spring_energy(data, u):
    """sum_e k_e (|x_j - x_i| - L_e)^2 / 2, J."""
    X, edges, k, L = data
    w = 0.0
    for e in range(edges.shape[0]):
        i = edges[e, 0]
        j = edges[e, 1]
        d = X[j] + u[j] - X[i] - u[i]
        w += 0.5 * k[e] * (np.sqrt(d @ d) - L[e]) ** 2
    return w
