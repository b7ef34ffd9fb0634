"""Mass-spring networks on the mesh edges (Delingette 1998): the kernel of ``mass-spring``."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from .blocks import HOT, JIT, U1, U2, U3


class SpringData(NamedTuple):
    """spring_force's data: edge_vectors (E, 3) m, the rest vector X_j - X_i of each edge (i, j), edges
    (E, 2) int64, stiffness (E,) N/m, rest_length (E,) m (|X_j - X_i|, computed in float64). The float
    arrays are all of the model's float type."""

    edge_vectors: np.ndarray
    edges: np.ndarray
    stiffness: np.ndarray
    rest_length: np.ndarray


@nb.njit(inline="always", **HOT)
def _stretch(e, edges, L, u, k):
    """d = x_j - x_i = e_k + (u_j - u_i) of edge k (uint64), |d| and its stretch |d| - L_k, the latter
    as (2 e.du + du.du) / (|d| + L_k): the same number as |d| - L_k, without the cancellation that costs
    |d| - L_k its leading digits when the stretch is small (in float32, all of them below a strain of
    1e-7; the difference of positions X_j + u_j - X_i - u_i loses as many again). Zero at rest exactly.
    Returns the flat offsets 3 i and 3 j too.

    e (3 E,) m, edges (2 E,) int64 and u (3 N,) m flat views of SpringData's arrays and the displacement,
    read with unsigned offsets (blocks.U1 ...: the liver-x10's force took 691 us with 2-D signed
    indexing, 641 flat, same bits)."""
    bi, bj = U3 * np.uint64(edges[U2 * k]), U3 * np.uint64(edges[U2 * k + U1])
    be = U3 * k
    du0, du1, du2 = u[bj] - u[bi], u[bj + U1] - u[bi + U1], u[bj + U2] - u[bi + U2]
    e0, e1, e2 = e[be], e[be + U1], e[be + U2]
    d0, d1, d2 = e0 + du0, e1 + du1, e2 + du2
    length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    grow = (e0 + e0 + du0) * du0 + (e1 + e1 + du1) * du1 + (e2 + e2 + du2) * du2
    return bi, bj, d0, d1, d2, length, grow / (length + L[k])


@nb.njit(**HOT)
def spring_force(data, scratch, u, f):
    """Edge springs: f_i += k_ij (|x_j - x_i| - L_ij) (x_j - x_i) / |x_j - x_i| (Delingette 1998), the
    stretch as _stretch evaluates it.

    data: SpringData.   scratch: model.NO_SCRATCH (unused).   u: (N, 3) displacement, m.
    f: (N, 3) force, N (overwritten). u, f and the data's float arrays all float64, or all float32
    (a float32 model: the kernel then computes in float32).
    """
    e, edges, k, L = data
    e1, edges1, u1, f1 = e.reshape(-1), edges.reshape(-1), u.reshape(-1), f.reshape(-1)
    f1[:] = 0.0
    for m in range(np.uint64(edges.shape[0])):
        bi, bj, d0, d1, d2, length, stretch = _stretch(e1, edges1, L, u1, m)
        s = k[m] * stretch / length
        f1[bi] += s * d0
        f1[bi + U1] += s * d1
        f1[bi + U2] += s * d2
        f1[bj] -= s * d0
        f1[bj + U1] -= s * d1
        f1[bj + U2] -= s * d2


@nb.njit(**JIT)
def spring_energy(data, u):
    """sum_e k_e (|x_j - x_i| - L_e)^2 / 2, J (the stretch as spring_force evaluates it)."""
    e, edges, k, L = data
    e1, edges1, u1 = e.reshape(-1), edges.reshape(-1), u.reshape(-1)
    w = 0.0
    for m in range(np.uint64(edges.shape[0])):
        stretch = _stretch(e1, edges1, L, u1, m)[6]
        w += 0.5 * k[m] * stretch * stretch
    return w
