"""Per-tetrahedron kernels of the non-linear models: StVK tensor-mass, corotational, hybrid.

All three evaluate, on each tetrahedron e with rest shape-function gradients g_a and volume V_e,

    H = sum_a u_a (x) g_a,   F = I + H,   f_a -= V_e P(F) g_a

with P the first Piola-Kirchhoff stress of the model's law. This is the exact negative gradient of the
P1 energy sum_e V_e W(F_e): for StVK it is the same force as Picinbono's non-linear tensor-mass (2003),
whose vertex, edge, triangle and tetrahedron tensors are the expansion of this expression in powers
of u; evaluating P per element is the cheaper way to the same numbers (about 130 flops a tetrahedron
against a few hundred for the tensor sums), and the cross-solver test checks it against dolfinx's
P1 StVK residual. The kernels evaluate blocks of tetrahedra at once, vectorised across tetrahedra (the
block section below); the corotational polar iteration runs on a whole block until its slowest
tetrahedron has converged.

Every force kernel is ``force(data, scratch, u, f)``: ``data`` the model's read-only arrays, ``scratch``
the arrays it writes besides f, which belong to the caller (an integrator's workspace: two threads
stepping one model each pass their own) and keep the kernels free of allocation. Both tuples are
documented at each kernel; all arrays are float64 unless said.
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .geometry import morton_order, shape_gradients
from .laws import linear_energy as linear_density
from .laws import stvk_energy as stvk_density
from .laws import volume_penalty_energy
from .material import Material
from .tensor_mass import linear_tm_energy, linear_tm_force

_JIT = dict(nogil=True, cache=True)
#: The force kernels of the step loop: contraction to fused multiply-adds and reassociation change
#: results at round-off level only (the cross-solver tests hold at 1e-10); no NaN/inf assumptions, so
#: the blow-up check still sees a NaN. Division by zero gives inf as in numpy instead of raising, which
#: would put a branch in the element loops and keep them from vectorising.
_HOT = dict(nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz", "arcp"}, error_model="numpy")


def tet_data(points: np.ndarray, tets: np.ndarray):
    """tets (M, 4) int64, grads (M, 3, 3) (rows g_1..g_3; g_0 = -(g_1 + g_2 + g_3)), vol (M,) m^3."""
    g, vol = shape_gradients(points, tets)
    return np.ascontiguousarray(tets, dtype=np.int64), np.ascontiguousarray(g[:, 1:, :]), np.ascontiguousarray(vol)


def law_params(material: Material) -> np.ndarray:
    """(5,) float64: lam, mu, dlam, dmu, kappa, Pa. The fibre direction is per tetrahedron, in
    ``block_data``'s geometry."""
    return np.array([material.lam, material.mu, material.dlam, material.dmu, material.volume_penalty])


# ---------------------------------------------------------------------------------------------
# Blocks of tetrahedra in struct-of-arrays layout (StVK, corotational, hybrid)
#
# Each kernel walks the mesh in blocks of BLOCK tetrahedra, in three loops per block: gather the
# displacement differences u_a - u_0 into a scratch block (indexed loads), evaluate the elements on
# contiguous rows (no indexing: LLVM turns this loop into SIMD code over 8 tetrahedra at a time with
# AVX-512, 4 with AVX2), scatter the forces (indexed stores). The element loop runs on uint64 offsets:
# numba wraps negative signed indices with a select that LLVM cannot bound, and that alone stops the
# vectoriser.

#: Tetrahedra per block: a block's scratch (9 x 64 float64, 4.6 kB) and geometry stay in L1.
BLOCK = 64
#: Rows of geometry per tetrahedron: 9 shape-gradient components, the volume, the fibre direction.
GEO_ROWS = 13
_ROW = tuple(np.uint64(k * BLOCK) for k in range(GEO_ROWS))
_GEO_ROWS = np.uint64(GEO_ROWS * BLOCK)
_UBLOCK = np.uint64(BLOCK)


def block_data(points: np.ndarray, tets: np.ndarray, material: Material):
    """The element kernels' geometry in blocks of BLOCK tetrahedra.

    points (N, 3) float64 m; tets (M, 4) int64. Returns tets (P, 4) int64 and geo (GEO_ROWS P,)
    float64, P = BLOCK ceil(M / BLOCK): the tetrahedra in Morton order (neighbours share blocks; the
    kernels sum over all of them, so their order is internal), the last block padded with zero-volume
    tetrahedra on vertex 0, which contribute nothing. Block b holds, for its tetrahedron q (row
    b BLOCK + q of the returned tets), with G = GEO_ROWS:
    geo[(G b + 3 a + c) BLOCK + q] = g_{a+1, c} (1/m, a, c = 0..2; g_0 = -(g_1 + g_2 + g_3)),
    geo[(G b + 9) BLOCK + q] = V (m^3) and geo[(G b + 10 + c) BLOCK + q] = a_c, the material's unit
    fibre direction at the centroid (zeros for an isotropic material).
    """
    t, g, vol = tet_data(points, tets[morton_order(points, tets)])
    m = len(t)
    p = BLOCK * -(-m // BLOCK)
    tp = np.zeros((p, 4), dtype=np.int64)
    tp[:m] = t
    rows = np.zeros((GEO_ROWS, p))
    rows[:9, :m] = g.reshape(m, 9).T
    rows[9, :m] = vol
    rows[10:13, :m] = material.fiber_directions(points[t].mean(axis=1)).T
    geo = rows.reshape(GEO_ROWS, p // BLOCK, BLOCK).transpose(1, 0, 2).ravel()
    return tp, np.ascontiguousarray(geo)


@nb.njit(inline="always", **_HOT)
def _gather(tets, e0, u, W):
    """W[(3 r + a) BLOCK + q] = u[i_{a+1}, r] - u[i_0, r] for the tetrahedra e0 .. e0 + BLOCK - 1."""
    for q in range(BLOCK):
        e = e0 + q
        i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        for r in range(3):
            x0 = u[i0, r]
            W[(3 * r) * BLOCK + q] = u[i1, r] - x0
            W[(3 * r + 1) * BLOCK + q] = u[i2, r] - x0
            W[(3 * r + 2) * BLOCK + q] = u[i3, r] - x0


@nb.njit(inline="always", **_HOT)
def _scatter_block(tets, e0, W, f, mask):
    """f_{a+1} -= W[(3 a + r) BLOCK + q], f_0 += their sum, for the tetrahedra whose mask is set."""
    for q in range(BLOCK):
        e = e0 + q
        if not mask[e]:
            continue
        i0, i1, i2, i3 = tets[e, 0], tets[e, 1], tets[e, 2], tets[e, 3]
        for r in range(3):
            f1, f2, f3 = W[r * BLOCK + q], W[(3 + r) * BLOCK + q], W[(6 + r) * BLOCK + q]
            f[i1, r] -= f1
            f[i2, r] -= f2
            f[i3, r] -= f3
            f[i0, r] += f1 + f2 + f3


@nb.njit(inline="always", **_HOT)
def _lane_rows(A, off, q):
    """Rows 0..8 of lane q of the block at uint64 offset ``off`` in A (a row-major 3x3 as a 9-tuple)."""
    return (
        A[off + _ROW[0] + q], A[off + _ROW[1] + q], A[off + _ROW[2] + q],
        A[off + _ROW[3] + q], A[off + _ROW[4] + q], A[off + _ROW[5] + q],
        A[off + _ROW[6] + q], A[off + _ROW[7] + q], A[off + _ROW[8] + q],
    )  # fmt: skip


@nb.njit(inline="always", **_HOT)
def _lane_store(A, q, r):
    """Rows 0..8 of lane q of the block array A (offset 0) = the row-major 9-tuple r."""
    A[_ROW[0] + q], A[_ROW[1] + q], A[_ROW[2] + q] = r[0], r[1], r[2]
    A[_ROW[3] + q], A[_ROW[4] + q], A[_ROW[5] + q] = r[3], r[4], r[5]
    A[_ROW[6] + q], A[_ROW[7] + q], A[_ROW[8] + q] = r[6], r[7], r[8]


@nb.njit(inline="always", **_HOT)
def _lane_in(W, geo, gb, q):
    """H = grad u = sum_a (u_a - u_0) (x) g_a of lane q (row-major 9-tuple, from the displacement
    differences in W), its gradients g_1..g_3 (row-major 9-tuple, 1/m) and its volume V (m^3)."""
    ax, bx, cx, ay, by, cy, az, bz, cz = _lane_rows(W, _ROW[0], q)
    g = _lane_rows(geo, gb, q)
    g10, g11, g12, g20, g21, g22, g30, g31, g32 = g
    H = (
        ax * g10 + bx * g20 + cx * g30, ax * g11 + bx * g21 + cx * g31, ax * g12 + bx * g22 + cx * g32,
        ay * g10 + by * g20 + cy * g30, ay * g11 + by * g21 + cy * g31, ay * g12 + by * g22 + cy * g32,
        az * g10 + bz * g20 + cz * g30, az * g11 + bz * g21 + cz * g31, az * g12 + bz * g22 + cz * g32,
    )  # fmt: skip
    return H, g, geo[gb + _ROW[9] + q]


@nb.njit(inline="always", **_HOT)
def _lane_out(W, q, v, P, g):
    """W[(3 a + r) BLOCK + q] = V (P g_{a+1})_r: the element's forces, P and g row-major 9-tuples."""
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    g10, g11, g12, g20, g21, g22, g30, g31, g32 = g
    W[_ROW[0] + q] = v * (p00 * g10 + p01 * g11 + p02 * g12)
    W[_ROW[1] + q] = v * (p10 * g10 + p11 * g11 + p12 * g12)
    W[_ROW[2] + q] = v * (p20 * g10 + p21 * g11 + p22 * g12)
    W[_ROW[3] + q] = v * (p00 * g20 + p01 * g21 + p02 * g22)
    W[_ROW[4] + q] = v * (p10 * g20 + p11 * g21 + p12 * g22)
    W[_ROW[5] + q] = v * (p20 * g20 + p21 * g21 + p22 * g22)
    W[_ROW[6] + q] = v * (p00 * g30 + p01 * g31 + p02 * g32)
    W[_ROW[7] + q] = v * (p10 * g30 + p11 * g31 + p12 * g32)
    W[_ROW[8] + q] = v * (p20 * g30 + p21 * g31 + p22 * g32)


@nb.njit(inline="always", **_HOT)
def _pk2(e00, e11, e22, e01, e02, e12, lam, mu2, a0, a1, a2, dlam, dmu, fibre):
    """S = lam tr(E) I + 2 mu E + dlam (a.Ea) a (x) a + dmu (a (x) Ea + Ea (x) a), the six components
    (00, 11, 22, 01, 02, 12) of the StVK law (Picinbono et al. 2003, eq. 9) for the strain E."""
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
    return s00, s11, s22, s01, s02, s12


@nb.njit(inline="always", **_HOT)
def _stvk_block(W, geo, gb, prm, minus_linear):
    """Element forces of one block, in place in W: the displacement differences in, and out
    W[(3 a + r) BLOCK + q] = V (P g_{a+1})_r, with P = (I + H) S(E) + kappa (J - 1) cof F the StVK
    stress; with ``minus_linear``, less the linear stress sigma(eps) of the same law (no penalty: the
    linear tensor-mass has none), which is the hybrid model's correction.
    W: (9 BLOCK,) float64 scratch; geo: block_data's geo; gb: uint64 offset of the block in geo.
    """
    lam, mu2, dlam, dmu, kappa = prm[0], 2.0 * prm[1], prm[2], prm[3], prm[4]
    fibre = dlam != 0.0 or dmu != 0.0
    for q in range(_UBLOCK):
        H, g, v = _lane_in(W, geo, gb, q)
        a0, a1, a2 = geo[gb + _ROW[10] + q], geo[gb + _ROW[11] + q], geo[gb + _ROW[12] + q]
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = H
        # Green-Lagrange E = (H + H^T + H^T H) / 2
        e00 = h00 + 0.5 * (h00 * h00 + h10 * h10 + h20 * h20)
        e11 = h11 + 0.5 * (h01 * h01 + h11 * h11 + h21 * h21)
        e22 = h22 + 0.5 * (h02 * h02 + h12 * h12 + h22 * h22)
        e01 = 0.5 * (h01 + h10 + h00 * h01 + h10 * h11 + h20 * h21)
        e02 = 0.5 * (h02 + h20 + h00 * h02 + h10 * h12 + h20 * h22)
        e12 = 0.5 * (h12 + h21 + h01 * h02 + h11 * h12 + h21 * h22)
        s00, s11, s22, s01, s02, s12 = _pk2(e00, e11, e22, e01, e02, e12, lam, mu2, a0, a1, a2, dlam, dmu, fibre)
        # P = (I + H) S
        p00 = h00 * s00 + h01 * s01 + h02 * s02
        p01 = h00 * s01 + h01 * s11 + h02 * s12
        p02 = h00 * s02 + h01 * s12 + h02 * s22
        p10 = h10 * s00 + h11 * s01 + h12 * s02
        p11 = h10 * s01 + h11 * s11 + h12 * s12
        p12 = h10 * s02 + h11 * s12 + h12 * s22
        p20 = h20 * s00 + h21 * s01 + h22 * s02
        p21 = h20 * s01 + h21 * s11 + h22 * s12
        p22 = h20 * s02 + h21 * s12 + h22 * s22
        if minus_linear:
            l00, l11, l22, l01, l02, l12 = _pk2(
                h00, h11, h22, 0.5 * (h01 + h10), 0.5 * (h02 + h20), 0.5 * (h12 + h21),
                lam, mu2, a0, a1, a2, dlam, dmu, fibre,
            )  # fmt: skip
            s00, s11, s22, s01, s02, s12 = s00 - l00, s11 - l11, s22 - l22, s01 - l01, s02 - l02, s12 - l12
        p00 += s00
        p01 += s01
        p02 += s02
        p10 += s01
        p11 += s11
        p12 += s12
        p20 += s02
        p21 += s12
        p22 += s22
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
        _lane_out(W, q, v, (p00, p01, p02, p10, p11, p12, p20, p21, p22), g)


def block_scratch() -> tuple:
    """The scratch of stvk_force: W (9 BLOCK,) float64, one block's displacement differences and forces."""
    return (np.zeros(9 * BLOCK),)


@nb.njit(**_HOT)
def stvk_force(data, scratch, u, f):
    """StVK tensor-mass force (Picinbono et al. 2003), with fibre terms and the volume penalty.

    data: (tets (P, 4) int64 and geo (GEO_ROWS P,) from block_data, prm (5,) law_params,
           everywhere (P,) bool all True).   scratch: block_scratch().
    u: (N, 3) float64 displacement, m.   f: (N, 3) float64 force, N (overwritten).
    """
    tets, geo, prm, everywhere = data
    W = scratch[0]
    f[:] = 0.0
    for b in range(tets.shape[0] // BLOCK):
        _gather(tets, b * BLOCK, u, W)
        _stvk_block(W, geo, np.uint64(b) * _GEO_ROWS, prm, False)
        _scatter_block(tets, b * BLOCK, W, f, everywhere)


@nb.njit(inline="always", **_JIT)
def _block_grad_u(tets, geo, e, u):
    """F = I + grad u (3, 3) on tetrahedron e of block_data's layout, its volume and fibre (3,)."""
    b, q = e // BLOCK, e % BLOCK
    F = np.eye(3)
    for a in range(1, 4):
        for r in range(3):
            d = u[tets[e, a], r] - u[tets[e, 0], r]
            for c in range(3):
                F[r, c] += d * geo[(GEO_ROWS * b + 3 * (a - 1) + c) * BLOCK + q]
    fibre = np.array([geo[(GEO_ROWS * b + 10 + c) * BLOCK + q] for c in range(3)])
    return F, geo[(GEO_ROWS * b + 9) * BLOCK + q], fibre


@nb.njit(**_JIT)
def stvk_energy(data, u):
    """sum_e V_e W(F_e), J, W the StVK energy plus the volume penalty (laws.stvk_energy and
    laws.volume_penalty_energy: the energy stvk_force differentiates)."""
    tets, geo, prm = data[0], data[1], data[2]
    w = 0.0
    for e in range(tets.shape[0]):
        F, vol, a = _block_grad_u(tets, geo, e, u)
        w += vol * (stvk_density(F, prm[0], prm[1], a, prm[2], prm[3]) + volume_penalty_energy(F, prm[4]))
    return w


# ---------------------------------------------------------------------------------------------
# corotational


@nb.njit(inline="always", **_HOT)
def _polar_step(r, scaled):
    """One scaled Newton step of the polar iteration R <- (g R + R^-T / g) / 2 (Higham 1986) on R
    (9-tuple, row-major), with g = (|R^-1|_F / |R|_F)^(1/2) if ``scaled``, else 1 (near convergence g
    -> 1, and it costs two roots). Returns the new R and |dR|_F^2."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
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
    if scaled:
        nr = r00 * r00 + r01 * r01 + r02 * r02 + r10 * r10 + r11 * r11 + r12 * r12 + r20 * r20 + r21 * r21 + r22 * r22
        nc = c00 * c00 + c01 * c01 + c02 * c02 + c10 * c10 + c11 * c11 + c12 * c12 + c20 * c20 + c21 * c21 + c22 * c22
        gam = np.sqrt(np.sqrt(nc / (det * det * nr)))
    a = 0.5 * gam
    b = 0.5 / (gam * det)  # R^-T = cof(R) / det(R)
    n = (
        a * r00 + b * c00, a * r01 + b * c01, a * r02 + b * c02,
        a * r10 + b * c10, a * r11 + b * c11, a * r12 + b * c12,
        a * r20 + b * c20, a * r21 + b * c21, a * r22 + b * c22,
    )  # fmt: skip
    change = (
        (n[0] - r00) ** 2 + (n[1] - r01) ** 2 + (n[2] - r02) ** 2
        + (n[3] - r10) ** 2 + (n[4] - r11) ** 2 + (n[5] - r12) ** 2
        + (n[6] - r20) ** 2 + (n[7] - r21) ** 2 + (n[8] - r22) ** 2
    )  # fmt: skip
    return n, change


#: A Newton step that changes R by less than 1e-6 (Frobenius; the constants are squared changes) ends
#: the polar iteration: convergence is quadratic, so the new iterate is within about 1e-12 of the
#: rotation (a 1e-9 test took one more step, 10% of corotational-tm's force, to confirm round-off).
#: Scaling stops below a change of 1e-2.
_POLAR_DONE = 1e-12
_POLAR_SCALED = 1e-4


@nb.njit(inline="always", **_HOT)
def _polar(F):
    """Rotation (9-tuple, row-major) of the polar decomposition F = R U, F a row-major 9-tuple.

    Scaled Newton iteration (_polar_step): quadratic convergence for det F > 0, in registers. An
    inverted or flat element (det F <= 1e-12) takes the SVD instead, with the sign of the smallest
    singular direction flipped so that R stays a rotation (Irving, Teran & Fedkiw 2004).
    """
    if _det(F) <= 1e-12:
        U, _, Vt = np.linalg.svd(np.array(F).reshape(3, 3))
        if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
            U[:, 2] = -U[:, 2]
        Q = U @ Vt
        return Q[0, 0], Q[0, 1], Q[0, 2], Q[1, 0], Q[1, 1], Q[1, 2], Q[2, 0], Q[2, 1], Q[2, 2]
    r, change = F, 1.0
    for _ in range(30):
        r, change = _polar_step(r, change > _POLAR_SCALED)
        if change < _POLAR_DONE:
            break
    return r


@nb.njit(inline="always", **_HOT)
def _plus_identity(H):
    """F = I + H, row-major 9-tuples."""
    return (1.0 + H[0], H[1], H[2], H[3], 1.0 + H[4], H[5], H[6], H[7], 1.0 + H[8])


@nb.njit(inline="always", **_HOT)
def _det(F):
    """det of a row-major 9-tuple."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = F
    return f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20)


@nb.njit(inline="always", **_HOT)
def _corotated_pk1(F, r, lam, mu):
    """P = R sigma(sym(R^T F) - I), R (row-major 9-tuple) the polar rotation of F: the stress of the
    corotated energy lam/2 tr(S - I)^2 + mu |S - I|^2, S = R^T F."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = F
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    s00 = r00 * f00 + r10 * f10 + r20 * f20 - 1.0
    s11 = r01 * f01 + r11 * f11 + r21 * f21 - 1.0
    s22 = r02 * f02 + r12 * f12 + r22 * f22 - 1.0
    s01 = 0.5 * (r00 * f01 + r10 * f11 + r20 * f21 + r01 * f00 + r11 * f10 + r21 * f20)
    s02 = 0.5 * (r00 * f02 + r10 * f12 + r20 * f22 + r02 * f00 + r12 * f10 + r22 * f20)
    s12 = 0.5 * (r01 * f02 + r11 * f12 + r21 * f22 + r02 * f01 + r12 * f11 + r22 * f21)
    ltr = lam * (s00 + s11 + s22)
    t00, t11, t22 = 2.0 * mu * s00 + ltr, 2.0 * mu * s11 + ltr, 2.0 * mu * s22 + ltr
    t01, t02, t12 = 2.0 * mu * s01, 2.0 * mu * s02, 2.0 * mu * s12
    return (
        r00 * t00 + r01 * t01 + r02 * t02, r00 * t01 + r01 * t11 + r02 * t12, r00 * t02 + r01 * t12 + r02 * t22,
        r10 * t00 + r11 * t01 + r12 * t02, r10 * t01 + r11 * t11 + r12 * t12, r10 * t02 + r11 * t12 + r12 * t22,
        r20 * t00 + r21 * t01 + r22 * t02, r20 * t01 + r21 * t11 + r22 * t12, r20 * t02 + r21 * t12 + r22 * t22,
    )  # fmt: skip


@nb.njit(inline="always", **_HOT)
def _corotational_block(W, R, Fb, geo, gb, lam, mu):
    """Element forces of one block, in place in W (as _stvk_block), for the corotated law.

    The polar iteration runs on all the block's tetrahedra at once, with the rotations in the scratch
    R (10 BLOCK,) float64 (rows 0..8 the rotation), until the slowest has converged; those that
    converged earlier take a few more steps at round-off. The steps are scaled while the block's largest
    change is above _POLAR_SCALED (a block-wide choice, so that unscaled steps take no roots). Inverted
    ones start
    from R = I (which stays put) and take the SVD afterwards, one at a time. Fb (9 BLOCK,) keeps each
    lane's F for the stress, which reads it back instead of forming it again (45 flops a tetrahedron).
    """
    inverted = 0
    for q in range(_UBLOCK):
        F = _plus_identity(_lane_in(W, geo, gb, q)[0])
        _lane_store(Fb, q, F)
        ok = _det(F) > 1e-12
        _lane_store(R, q, F if ok else (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0))
        inverted += not ok
    scaled = True  # one decision for the whole block: a branch per lane would keep both paths' roots
    for _ in range(30):
        active = 0
        far = 0  # lanes still far from orthogonal (an integer count: a max would not vectorise)
        for q in range(_UBLOCK):
            n, change = _polar_step(_lane_rows(R, _ROW[0], q), scaled)
            _lane_store(R, q, n)
            active += change >= _POLAR_DONE
            far += change > _POLAR_SCALED
        if active == 0:
            break
        scaled = far > 0
    if inverted:
        for q in range(_UBLOCK):
            F = _lane_rows(Fb, _ROW[0], q)
            if _det(F) <= 1e-12:
                _lane_store(R, q, _polar(F))
    for q in range(_UBLOCK):
        g = _lane_rows(geo, gb, q)
        v = geo[gb + _ROW[9] + q]
        _lane_out(W, q, v, _corotated_pk1(_lane_rows(Fb, _ROW[0], q), _lane_rows(R, _ROW[0], q), lam, mu), g)


def corotational_scratch() -> tuple:
    """The scratch of corotational_force: W (9 BLOCK,) as block_scratch, R (10 BLOCK,) float64 the
    block's rotations and last polar changes, Fb (9 BLOCK,) float64 its deformation gradients."""
    return (np.zeros(9 * BLOCK), np.zeros(10 * BLOCK), np.zeros(9 * BLOCK))


@nb.njit(**_HOT)
def corotational_force(data, scratch, u, f):
    """Corotational linear force: f_a -= V R sigma(sym(R^T F) - I) g_a, R the polar rotation of F.

    This is the exact gradient of W(F) = lam/2 tr(S - I)^2 + mu |S - I|^2, S = R^T F the polar stretch
    (the "corotated" energy; SOFA's TetrahedronFEMForceField, method "polar").
    data: (tets (P, 4) int64 and geo (GEO_ROWS P,) from block_data, prm (5,) law_params,
           everywhere (P,) bool all True).   scratch: corotational_scratch().
    """
    tets, geo, prm, everywhere = data
    W, R, Fb = scratch
    f[:] = 0.0
    for b in range(tets.shape[0] // BLOCK):
        _gather(tets, b * BLOCK, u, W)
        _corotational_block(W, R, Fb, geo, np.uint64(b) * _GEO_ROWS, prm[0], prm[1])
        _scatter_block(tets, b * BLOCK, W, f, everywhere)


@nb.njit(**_JIT)
def corotational_energy(data, u):
    """sum_e V_e (lam/2 tr(S - I)^2 + mu |S - I|^2), S = R^T F."""
    tets, geo, prm = data[0], data[1], data[2]
    lam, mu = prm[0], prm[1]
    w = 0.0
    for e in range(tets.shape[0]):
        F, vol, _ = _block_grad_u(tets, geo, e, u)
        R = np.array(_polar((F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2], F[2, 0], F[2, 1], F[2, 2])))
        S = R.reshape(3, 3).T @ F - np.eye(3)
        S = 0.5 * (S + S.T)
        tr = S[0, 0] + S[1, 1] + S[2, 2]
        w += vol * (0.5 * lam * tr * tr + mu * np.sum(S * S))
    return w


# ---------------------------------------------------------------------------------------------
# hybrid: linear tensor-mass everywhere, corrected to StVK on the tetrahedra that moved


def hybrid_scratch(n_vertices: int, n_padded: int) -> tuple:
    """The scratch of hybrid_force on N vertices and P (padded) tetrahedra: W (9 BLOCK,) float64 as
    block_scratch, moved (N,) bool, flags (P,) bool."""
    return (np.zeros(9 * BLOCK), np.zeros(n_vertices, dtype=np.bool_), np.zeros(n_padded, dtype=np.bool_))


@nb.njit(**_HOT)
def hybrid_force(data, scratch, u, f):
    """f = f_linear-tm(u) + sum over flagged tetrahedra of (f_stvk,e(u) - f_linear,e(u)).

    A tetrahedron is non-linear when one of its vertices moved more than ``threshold`` (m) from rest
    (Picinbono et al. 2003, section 5). Threshold 0: every tetrahedron, the stvk-tm force (to
    round-off). Threshold infinity: none, exactly the linear-tm force. Blocks with no flagged
    tetrahedron cost only the flag test.
    data: (linear-tm data tuple, tets (P, 4) int64 and geo (GEO_ROWS P,) from block_data, prm (5,)
           law_params, threshold (1,) m).   scratch: hybrid_scratch(N, P).
    """
    lin, tets, geo, prm, threshold = data
    W, moved, flags = scratch
    linear_tm_force(lin, scratch, u, f)  # which takes no scratch
    thr2 = threshold[0] * threshold[0]
    for i in range(u.shape[0]):
        moved[i] = u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2
    for b in range(tets.shape[0] // BLOCK):
        e0 = b * BLOCK
        count = 0
        for e in range(e0, e0 + BLOCK):
            flags[e] = moved[tets[e, 0]] | moved[tets[e, 1]] | moved[tets[e, 2]] | moved[tets[e, 3]]
            count += flags[e]
        if count == 0:
            continue
        _gather(tets, e0, u, W)
        _stvk_block(W, geo, np.uint64(b) * _GEO_ROWS, prm, True)
        _scatter_block(tets, e0, W, f, flags)


@nb.njit(**_JIT)
def hybrid_energy(data, u):
    """Energy of the same split, with the flags of the current u: the linear tensor-mass energy plus,
    on the flagged tetrahedra, V (W_stvk + W_penalty - W_linear)."""
    lin, tets, geo, prm = data[0], data[1], data[2], data[3]
    thr2 = data[4][0] * data[4][0]
    w = linear_tm_energy(lin, u)
    for e in range(tets.shape[0]):
        moved = False
        for k in range(4):
            i = tets[e, k]
            moved |= u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2
        if not moved:
            continue
        F, vol, a = _block_grad_u(tets, geo, e, u)
        w += vol * (
            stvk_density(F, prm[0], prm[1], a, prm[2], prm[3])
            + volume_penalty_energy(F, prm[4])
            - linear_density(F, prm[0], prm[1], a, prm[2], prm[3])
        )
    return w


# ---------------------------------------------------------------------------------------------
# mass-spring


@nb.njit(**_HOT)
def spring_force(data, scratch, u, f):
    """Edge springs: f_i += k_ij (|x_j - x_i| - L_ij) (x_j - x_i) / |x_j - x_i| (Delingette 1998).

    data: (points (N,3) m, edges (E,2) int64, stiffness (E,) N/m, rest_length (E,) m).
    scratch: model.NO_SCRATCH (unused).
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
