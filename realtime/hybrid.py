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

#: A vertex that moved past the threshold stays non-linear until it is back within this share of it
#: (hysteresis). With one threshold for both ways the hybrid had no equilibrium where a vertex's
#: displacement under the linear law lay past the threshold and under StVK short of it: its tetrahedra
#: switched law at every step and damped dynamics never settled (hybrid-tm sat at a residual of 6e-3 of
#: the load on the rates beam's 57 856 tetrahedra, 5.9e-3 on a liver pressed by a 5 mm tool). With a
#: band, a vertex switches only when its displacement crosses the whole band, which a settling body's
#: vertices stop doing as its motion dies out. Half: wide against the two laws' difference in
#: displacement at a threshold of 10% of the edge (a few per cent), narrow against the threshold.
RELEASE = 0.5


class HybridData(NamedTuple):
    """hybrid_force's data: linear (TensorData) the linear tensor-mass, tets, geo and prm as BlockData's,
    threshold (2,) float64 m: the displacement past which a vertex becomes non-linear, and the one
    within which it returns to linear (RELEASE times the first)."""

    linear: TensorData
    tets: np.ndarray
    geo: np.ndarray
    prm: np.ndarray
    threshold: np.ndarray


def hybrid_scratch(n_vertices: int, n_padded: int) -> tuple:
    """The scratch of hybrid_force on N vertices and P (padded) tetrahedra: W (9 BLOCK,) float64 as
    block_scratch, moved (N,) bool, flags (P,) bool. ``moved`` is the state of the hysteresis: an
    integrator keeps its scratch from step to step, so its vertices remember their law; a fresh scratch
    (``Model.internal_force``) has none moved."""
    return (np.zeros(9 * BLOCK), np.zeros(n_vertices, dtype=np.bool_), np.zeros(n_padded, dtype=np.bool_))


@nb.njit(**HOT)
def hybrid_force(data, scratch, u, f):
    """f = f_linear-tm(u) + sum over flagged tetrahedra of (f_stvk,e(u) - f_linear,e(u)).

    A tetrahedron is non-linear when one of its vertices moved more than ``threshold[0]`` (m) from rest
    (Picinbono et al. 2003, section 5); a vertex stays moved until it is back within ``threshold[1]``
    (RELEASE, the hysteresis kept in ``scratch``). Threshold 0: every tetrahedron, the stvk-tm force (to
    round-off). Threshold infinity: none, exactly the linear-tm force. Blocks with no flagged
    tetrahedron cost only the flag test.
    data: HybridData.   scratch: hybrid_scratch(N, P), the moved vertices of the last call.
    """
    lin, tets, geo, prm, threshold = data
    W, moved, flags = scratch
    linear_tm_force(lin, scratch, u, f)  # which takes no scratch
    on2, off2 = threshold[0] * threshold[0], threshold[1] * threshold[1]
    for i in range(u.shape[0]):
        d2 = u[i, 0] * u[i, 0] + u[i, 1] * u[i, 1] + u[i, 2] * u[i, 2]
        moved[i] = d2 > on2 or (moved[i] and d2 > off2)
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
    """Energy of the same split, with the flags a fresh scratch gives at u (no vertex remembered: those
    moved past threshold[0]): the linear tensor-mass energy plus, on the flagged tetrahedra,
    V (W_stvk + W_penalty - W_linear). With a fixed set of flags the force is its gradient."""
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
