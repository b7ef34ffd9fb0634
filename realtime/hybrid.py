"""The hybrid model (Picinbono et al. 2003, section 5): linear tensor-mass everywhere, corrected to StVK
on the tetrahedra that moved; the kernel of ``hybrid-tm``."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from .blocks import BLOCK, GEO_ROWS_U, HOT, JIT, block_grad_u, gather, scatter_block
from .laws import linear_energy as linear_density
from .laws import stvk_energy as stvk_density
from .laws import volume_penalty_energy
from .stvk import stvk_block
from .tensor_mass import TensorData, linear_tm_energy, linear_tm_force


class HybridData(NamedTuple):
    """hybrid_force's data: linear (TensorData) the linear tensor-mass, tets, geo and prm as BlockData's,
    threshold (1,) float64 m."""

    linear: TensorData
    tets: np.ndarray
    geo: np.ndarray
    prm: np.ndarray
    threshold: np.ndarray


def hybrid_scratch(n_vertices: int, n_padded: int) -> tuple:
    """The scratch of hybrid_force on N vertices and P (padded) tetrahedra: W (9 BLOCK,) float64 as
    block_scratch, moved (N,) bool, flags (P,) bool."""
    return (np.zeros(9 * BLOCK), np.zeros(n_vertices, dtype=np.bool_), np.zeros(n_padded, dtype=np.bool_))


@nb.njit(**HOT)
def hybrid_force(data, scratch, u, f):
    """f = f_linear-tm(u) + sum over flagged tetrahedra of (f_stvk,e(u) - f_linear,e(u)).

    A tetrahedron is non-linear when one of its vertices moved more than ``threshold`` (m) from rest
    (Picinbono et al. 2003, section 5). Threshold 0: every tetrahedron, the stvk-tm force (to
    round-off). Threshold infinity: none, exactly the linear-tm force. Blocks with no flagged
    tetrahedron cost only the flag test.
    data: HybridData.   scratch: hybrid_scratch(N, P).
    """
    lin, tets, geo, prm, threshold = data
    W, moved, flags = scratch
    linear_tm_force(lin, scratch, u, f)  # which takes no scratch
    thr2 = threshold[0] * threshold[0]
    for i in range(u.shape[0]):
        moved[i] = u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2
    t1, u1, f1 = tets.reshape(-1), u.reshape(-1), f.reshape(-1)
    for b in range(tets.shape[0] // BLOCK):
        e0 = b * BLOCK
        count = 0
        for e in range(e0, e0 + BLOCK):
            flags[e] = moved[tets[e, 0]] | moved[tets[e, 1]] | moved[tets[e, 2]] | moved[tets[e, 3]]
            count += flags[e]
        if count == 0:
            continue
        gather(t1, e0, u1, W)
        stvk_block(W, geo, np.uint64(b) * GEO_ROWS_U, prm[b], True)
        scatter_block(t1, e0, W, f1, flags)


@nb.njit(**JIT)
def hybrid_energy(data, u):
    """Energy of the same split, with the flags of the current u: the linear tensor-mass energy plus,
    on the flagged tetrahedra, V (W_stvk + W_penalty - W_linear)."""
    lin, tets, geo, prm = data.linear, data.tets, data.geo, data.prm
    thr2 = data.threshold[0] * data.threshold[0]
    w = linear_tm_energy(lin, u)
    for e in range(tets.shape[0]):
        moved = False
        for k in range(4):
            i = tets[e, k]
            moved |= u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2] > thr2
        if not moved:
            continue
        F, vol, a = block_grad_u(tets, geo, e, u)
        c = prm[e // BLOCK]
        w += vol * (
            stvk_density(F, c[0], c[1], a, c[2], c[3])
            + volume_penalty_energy(F, c[4])
            - linear_density(F, c[0], c[1], a, c[2], c[3])
        )
    return w
