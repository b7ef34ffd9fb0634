"""Compressible neo-Hookean tensor-mass: the element kernel of ``neohookean-tm``, on blocks of tetrahedra
(``realtime.blocks``), with the volume penalty.

Per tetrahedron, H = grad u, F = I + H, J = det F, and (laws.neo_hookean_pk1)

    P = mu (F - F^-T) + lam ln(J) F^-T = [mu (J F - cof F) + lam ln(J) cof F] / J,   cof F = J F^-T

formed from H alone, so that no leading digit is lost at small strain (where F and cof F are both near I,
and in float32 their difference would be round-off):

    cof(I + H) = (1 + tr H) I - H^T + cof H
    J F - cof F = (m2 + det H) I + H + H^T + (J - 1) H - cof H
    J - 1 = tr H + m2 + det H,   ln J = log1p(J - 1)

m2 the sum of H's principal 2x2 minors. The volume penalty adds kappa (J - 1) cof F (laws.volume_penalty_pk1).
"""

from __future__ import annotations

import numba as nb
import numpy as np

from .blocks import (
    BLOCK,
    GEO_ROWS_U,
    HOT,
    JIT,
    UBLOCK,
    block_grad_u,
    gather,
    in_type_of,
    lane_in,
    lane_out,
    scatter_block,
)
from .laws import neo_hookean_energy as neo_hookean_density
from .laws import volume_penalty_energy


@nb.njit(inline="always", **HOT)
def neohookean_block(W, geo, gb, prm):
    """Element forces of one block, in place in W: the displacement differences in, and out
    W[(3 a + r) BLOCK + q] = V (P g_{a+1})_r with P the neo-Hookean stress plus the volume penalty's.
    W: (9 BLOCK,) scratch; geo: block_data's geo; gb: uint64 offset of the block in geo; prm: (5,) the
    block's row of block_data's prm (lam, mu, -, -, kappa). All three of one floating type, float64 or
    float32, in which the block is computed. An inverted tetrahedron (J <= 0) gives NaN forces."""
    lam, mu, kappa = prm[0], prm[1], prm[4]
    one, two = in_type_of(lam, 1.0), in_type_of(lam, 2.0)
    for q in range(UBLOCK):
        H, g, v = lane_in(W, geo, gb, q)
        h00, h01, h02, h10, h11, h12, h20, h21, h22 = H
        # the cofactors of H, and its invariants
        c00, c01, c02 = h11 * h22 - h12 * h21, h12 * h20 - h10 * h22, h10 * h21 - h11 * h20
        c10, c11, c12 = h02 * h21 - h01 * h22, h00 * h22 - h02 * h20, h01 * h20 - h00 * h21
        c20, c21, c22 = h01 * h12 - h02 * h11, h02 * h10 - h00 * h12, h00 * h11 - h01 * h10
        tr = h00 + h11 + h22
        m2 = c00 + c11 + c22
        det_h = h00 * c00 + h01 * c01 + h02 * c02
        jm1 = tr + m2 + det_h
        s = v / (one + jm1)
        a = mu * s  # times J F - cof F
        b = lam * np.log1p(jm1) * s + kappa * v * jm1  # times cof F
        d = m2 + det_h
        p00 = a * (d + two * h00 + jm1 * h00 - c00) + b * (one + tr - h00 + c00)
        p11 = a * (d + two * h11 + jm1 * h11 - c11) + b * (one + tr - h11 + c11)
        p22 = a * (d + two * h22 + jm1 * h22 - c22) + b * (one + tr - h22 + c22)
        p01 = a * (h01 + h10 + jm1 * h01 - c01) + b * (c01 - h10)
        p02 = a * (h02 + h20 + jm1 * h02 - c02) + b * (c02 - h20)
        p10 = a * (h10 + h01 + jm1 * h10 - c10) + b * (c10 - h01)
        p12 = a * (h12 + h21 + jm1 * h12 - c12) + b * (c12 - h21)
        p20 = a * (h20 + h02 + jm1 * h20 - c20) + b * (c20 - h02)
        p21 = a * (h21 + h12 + jm1 * h21 - c21) + b * (c21 - h12)
        lane_out(W, q, (p00, p01, p02, p10, p11, p12, p20, p21, p22), g)


@nb.njit(inline="always", **HOT)
def neohookean_blocks(tets, geo, prm, everywhere, W, b0, b1, u, f):
    """neohookean_force's pass over the blocks b0 .. b1 - 1 of BlockData's arrays, adding into f (N, 3) N;
    W (9 BLOCK,) scratch."""
    t1, u1, f1 = tets.reshape(-1), u.reshape(-1), f.reshape(-1)
    for b in range(b0, b1):
        gather(t1, b * BLOCK, u1, W)
        neohookean_block(W, geo, np.uint64(b) * GEO_ROWS_U, prm[b])
        scatter_block(t1, b * BLOCK, W, f1, everywhere)


@nb.njit(**HOT)
def neohookean_force(data, scratch, u, f):
    """Compressible neo-Hookean tensor-mass force, with the volume penalty.

    data: blocks.BlockData.   scratch: blocks.block_scratch().
    u: (N, 3) displacement, m.   f: (N, 3) force, N (overwritten). Both, and the data's geo and prm and
    the scratch, float64, or all float32 (a float32 model: the kernel then computes in float32).
    """
    tets, geo, prm, everywhere = data
    f[:] = 0.0
    neohookean_blocks(tets, geo, prm, everywhere, scratch[0], 0, tets.shape[0] // BLOCK, u, f)


@nb.njit(**JIT)
def neohookean_energy(data, u):
    """sum_e V_e W(F_e), J, W the neo-Hookean energy plus the volume penalty (laws.neo_hookean_energy and
    laws.volume_penalty_energy: the energy neohookean_force differentiates); +inf where a tetrahedron is
    inverted."""
    tets, geo, prm = data.tets, data.geo, data.prm
    w = 0.0
    for e in range(tets.shape[0]):
        F, vol, _ = block_grad_u(tets, geo, e, u)
        if vol == 0.0:
            continue  # a block's padding: no tetrahedron
        c = prm[e // BLOCK]
        w += vol * (neo_hookean_density(F, c[0], c[1]) + volume_penalty_energy(F, c[4]))
    return w
