"""StVK tensor-mass (Picinbono, Delingette & Ayache 2003): the element kernel of ``stvk-tm``, with fibre
terms and the volume penalty, on blocks of tetrahedra (``realtime.blocks``)."""

from __future__ import annotations

import numba as nb
import numpy as np

from .blocks import (
    BLOCK,
    GEO_ROWS_U,
    HOT,
    JIT,
    ROW,
    UBLOCK,
    block_grad_u,
    gather,
    in_type_of,
    lane_in,
    lane_out,
    scatter_block,
)
from .laws import stvk_energy as stvk_density
from .laws import volume_penalty_energy


@nb.njit(inline="always", **HOT)
def _pk2(e00, e11, e22, e01, e02, e12, lam, mu2, a0, a1, a2, dlam, dmu, fibre):
    """S = lam tr(E) I + 2 mu E + dlam (a.Ea) a (x) a + dmu (a (x) Ea + Ea (x) a), the six components
    (00, 11, 22, 01, 02, 12) of the StVK law (Picinbono et al. 2003, eq. 9) for the strain E, in the
    floating type of the arguments. Linear in (lam, mu2, dlam, dmu): given them times a volume V, it
    returns V S."""
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
        dmu2 = dmu + dmu
        s00 += c * a0 * a0 + dmu2 * a0 * q0
        s11 += c * a1 * a1 + dmu2 * a1 * q1
        s22 += c * a2 * a2 + dmu2 * a2 * q2
        s01 += c * a0 * a1 + dmu * (a0 * q1 + q0 * a1)
        s02 += c * a0 * a2 + dmu * (a0 * q2 + q0 * a2)
        s12 += c * a1 * a2 + dmu * (a1 * q2 + q1 * a2)
    return s00, s11, s22, s01, s02, s12


@nb.njit(inline="always", **HOT)
def _stvk_lanes(W, geo, gb, prm, minus_linear, general):
    """stvk_block's loop over the block's lanes. ``general`` (a literal at each call): with the fibre
    terms and the volume penalty; without, the loop holds neither. A flag of the block's material
    tested inside the loop would be if-converted by the vectoriser, and every isotropic tetrahedron
    would pay for both (on the liver, at 256 bits, the isotropic element phase took 64 us with them,
    37 without). The stress is formed already multiplied by the volume V (its constants scaled once a
    lane: 2 products, 5 in the general loop, instead of V times the 9 outputs)."""
    lam, mu2, dlam, dmu, kappa = prm[0], prm[1] + prm[1], prm[2], prm[3], prm[4]
    half, one, zero = in_type_of(lam, 0.5), in_type_of(lam, 1.0), in_type_of(lam, 0.0)
    fibre = dlam != 0.0 or dmu != 0.0
    for q in range(UBLOCK):
        H, g, v = lane_in(W, geo, gb, q)
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = H
        # Green-Lagrange E = (H + H^T + H^T H) / 2
        e00 = h00 + half * (h00 * h00 + h10 * h10 + h20 * h20)
        e11 = h11 + half * (h01 * h01 + h11 * h11 + h21 * h21)
        e22 = h22 + half * (h02 * h02 + h12 * h12 + h22 * h22)
        e01 = half * (h01 + h10 + h00 * h01 + h10 * h11 + h20 * h21)
        e02 = half * (h02 + h20 + h00 * h02 + h10 * h12 + h20 * h22)
        e12 = half * (h12 + h21 + h01 * h02 + h11 * h12 + h21 * h22)
        lv, m2v, dlv, dmv = lam * v, mu2 * v, zero, zero
        a0, a1, a2 = zero, zero, zero
        if general:
            a0, a1, a2 = geo[gb + ROW[10] + q], geo[gb + ROW[11] + q], geo[gb + ROW[12] + q]
            dlv, dmv = dlam * v, dmu * v
        # V S
        s00, s11, s22, s01, s02, s12 = _pk2(
            e00, e11, e22, e01, e02, e12, lv, m2v, a0, a1, a2, dlv, dmv, general and fibre
        )
        if minus_linear:
            l00, l11, l22, l01, l02, l12 = _pk2(
                h00, h11, h22, half * (h01 + h10), half * (h02 + h20), half * (h12 + h21),
                lv, m2v, a0, a1, a2, dlv, dmv, general and fibre,
            )  # fmt: skip
            t00, t11, t22, t01, t02, t12 = s00 - l00, s11 - l11, s22 - l22, s01 - l01, s02 - l02, s12 - l12
        else:
            t00, t11, t22, t01, t02, t12 = s00, s11, s22, s01, s02, s12
        # V P = V (I + H) S, less V sigma(eps) with ``minus_linear``
        p00 = t00 + h00 * s00 + h01 * s01 + h02 * s02
        p01 = t01 + h00 * s01 + h01 * s11 + h02 * s12
        p02 = t02 + h00 * s02 + h01 * s12 + h02 * s22
        p10 = t01 + h10 * s00 + h11 * s01 + h12 * s02
        p11 = t11 + h10 * s01 + h11 * s11 + h12 * s12
        p12 = t12 + h10 * s02 + h11 * s12 + h12 * s22
        p20 = t02 + h20 * s00 + h21 * s01 + h22 * s02
        p21 = t12 + h20 * s01 + h21 * s11 + h22 * s12
        p22 = t22 + h20 * s02 + h21 * s12 + h22 * s22
        if general and kappa != 0.0:
            f00, f01, f02 = one + h00, h01, h02
            f10, f11, f12 = h10, one + h11, h12
            f20, f21, f22 = h20, h21, one + h22
            # J - 1 = tr H + (the principal 2x2 minors of H) + det H: det F - 1 itself would lose the
            # leading digits of a small volume change (in float32, all of them below 1e-7)
            minors = h00 * h11 - h01 * h10 + h00 * h22 - h02 * h20 + h11 * h22 - h12 * h21
            det_h = h00 * (h11 * h22 - h12 * h21) + h01 * (h12 * h20 - h10 * h22) + h02 * (h10 * h21 - h11 * h20)
            k = kappa * v * (h00 + h11 + h22 + minors + det_h)
            p00 += k * (f11 * f22 - f12 * f21)
            p01 += k * (f12 * f20 - f10 * f22)
            p02 += k * (f10 * f21 - f11 * f20)
            p10 += k * (f02 * f21 - f01 * f22)
            p11 += k * (f00 * f22 - f02 * f20)
            p12 += k * (f01 * f20 - f00 * f21)
            p20 += k * (f01 * f12 - f02 * f11)
            p21 += k * (f02 * f10 - f00 * f12)
            p22 += k * (f00 * f11 - f01 * f10)
        lane_out(W, q, (p00, p01, p02, p10, p11, p12, p20, p21, p22), g)


@nb.njit(inline="always", **HOT)
def stvk_block(W, geo, gb, prm, minus_linear):
    """Element forces of one block, in place in W: the displacement differences in, and out
    W[(3 a + r) BLOCK + q] = V (P g_{a+1})_r, with P = (I + H) S(E) + kappa (J - 1) cof F the StVK
    stress; with ``minus_linear``, less the linear stress sigma(eps) of the same law (no penalty: the
    linear tensor-mass has none), which is the hybrid model's correction.
    W: (9 BLOCK,) scratch; geo: block_data's geo; gb: uint64 offset of the block in geo;
    prm: (5,) the block's row of block_data's prm. All three of one floating type, float64 or float32,
    in which the block is computed (its constants in_type_of it). A block of an isotropic material
    without the penalty takes the loop that has neither (_stvk_lanes).
    """
    if prm[2] != 0.0 or prm[3] != 0.0 or prm[4] != 0.0:
        _stvk_lanes(W, geo, gb, prm, minus_linear, True)
    else:
        _stvk_lanes(W, geo, gb, prm, minus_linear, False)


@nb.njit(inline="always", **HOT)
def stvk_blocks(tets, geo, prm, everywhere, W, b0, b1, u, f):
    """stvk_force's pass over the blocks b0 .. b1 - 1 of BlockData's arrays, adding into f (N, 3) N;
    W (9 BLOCK,) scratch."""
    t1, u1, f1 = tets.reshape(-1), u.reshape(-1), f.reshape(-1)
    for b in range(b0, b1):
        gather(t1, b * BLOCK, u1, W)
        stvk_block(W, geo, np.uint64(b) * GEO_ROWS_U, prm[b], False)
        scatter_block(t1, b * BLOCK, W, f1, everywhere)


@nb.njit(**HOT)
def stvk_force(data, scratch, u, f):
    """StVK tensor-mass force (Picinbono et al. 2003), with fibre terms and the volume penalty.

    data: blocks.BlockData.   scratch: blocks.block_scratch().
    u: (N, 3) displacement, m.   f: (N, 3) force, N (overwritten). Both, and the data's geo and prm and
    the scratch, float64, or all float32 (a float32 model: the kernel then computes in float32).
    """
    tets, geo, prm, everywhere = data
    f[:] = 0.0
    stvk_blocks(tets, geo, prm, everywhere, scratch[0], 0, tets.shape[0] // BLOCK, u, f)


@nb.njit(**JIT)
def stvk_energy(data, u):
    """sum_e V_e W(F_e), J, W the StVK energy plus the volume penalty (laws.stvk_energy and
    laws.volume_penalty_energy: the energy stvk_force differentiates)."""
    tets, geo, prm = data.tets, data.geo, data.prm
    w = 0.0
    for e in range(tets.shape[0]):
        F, vol, a = block_grad_u(tets, geo, e, u)
        c = prm[e // BLOCK]
        w += vol * (stvk_density(F, c[0], c[1], a, c[2], c[3]) + volume_penalty_energy(F, c[4]))
    return w
