"""Mass-spring networks on the mesh edges (Delingette 1998): the kernel of ``mass-spring``."""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np

from .blocks import HOT, JIT


class SpringData(NamedTuple):
    """spring_force's data: points (N, 3) float64 m, edges (E, 2) int64, stiffness (E,) float64 N/m,
    rest_length (E,) float64 m."""

    points: np.ndarray
    edges: np.ndarray
    stiffness: np.ndarray
    rest_length: np.ndarray


@nb.njit(**HOT)
def spring_force(data, scratch, u, f):
    """Edge springs: f_i += k_ij (|x_j - x_i| - L_ij) (x_j - x_i) / |x_j - x_i| (Delingette 1998).

    data: SpringData.   scratch: model.NO_SCRATCH (unused).
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


@nb.njit(**JIT)
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
