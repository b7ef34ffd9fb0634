"""Free-form deformation driven by the tools: the non-physics baseline.

Sederberg & Parry (1986) embed a body in a lattice of control points and move each point x of it by

    u(x) = sum_ijk B_i(s) B_j(t) B_k(r) d_ijk,   B_i(s) = C(n, i) s^i (1 - s)^(n - i)

with (s, t, r) in [0, 1]^3 the point's coordinates in the lattice's box and d_ijk the control points'
displacements (degree n, (n + 1)^3 control points). Direct manipulation (Hsu, Hughes & Kaufman 1992)
chooses the d that carry given points to given places: here the tools' vertices to where the tools
are and the fixed vertices to rest, in the least-squares sense, and among the control displacements
that fit, the smoothest (least |D d|^2, D the differences of d along the lattice's edges): control
points no vertex pins take the harmonic interpolation of those around them instead of staying at
rest, and a field the lattice holds (an affine one, by the Bernstein basis' linear precision) is
reproduced exactly. The map from the tools'
displacements to every vertex's is linear and computed once; an update is one product.

There are no mechanics: no material, no load but the tools (gravity and forces move nothing), no
force on the tool (the tools' reaction is zero). What the sweep measures is how far "looks right" is
from right: the source documents' remark that such models "may be sufficient for some simulations".
"""

from __future__ import annotations

import math

import numba as nb
import numpy as np

from .errors import InputError
from .model import Model

_JIT = dict(nogil=True, cache=True)

#: Singular values of the fit below this fraction of the largest count as zero (the lattice's control
#: points that the constrained vertices do not see, or see only together).
RANK_TOL = 1e-10


def bernstein(n: int, s: np.ndarray) -> np.ndarray:
    """The Bernstein polynomials of degree n at s (K,) in [0, 1]: (K, n + 1) float64."""
    s = np.asarray(s, dtype=float)[:, None]
    i = np.arange(n + 1)[None, :]
    binom = np.array([math.comb(n, k) for k in range(n + 1)], dtype=float)[None, :]
    return binom * s**i * (1.0 - s) ** (n - i)


def lattice_basis(points: np.ndarray, lo: np.ndarray, hi: np.ndarray, degree: int) -> np.ndarray:
    """B (K, (degree + 1)^3) float64: the tensor-product Bernstein basis of the lattice spanning the box
    [lo, hi] (m) at points (K, 3) m; control point (i, j, k) is column (i (n + 1) + j)(n + 1) + k."""
    s = (np.asarray(points, dtype=float) - lo) / (hi - lo)
    bx, by, bz = (bernstein(degree, s[:, c]) for c in range(3))
    return np.einsum("ki,kj,kl->kijl", bx, by, bz).reshape(len(s), -1)


def lattice_differences(degree: int) -> np.ndarray:
    """D (E, (degree + 1)^3) float64: d_b - d_a for each edge (a, b) of the control lattice."""
    n = degree + 1
    index = np.arange(n**3).reshape(n, n, n)
    pairs = [
        np.stack([np.take(index, range(n - 1), axis=ax).ravel(), np.take(index, range(1, n), axis=ax).ravel()], 1)
        for ax in range(3)
    ]
    pairs = np.concatenate(pairs)
    D = np.zeros((len(pairs), n**3))
    D[np.arange(len(pairs)), pairs[:, 0]] = -1.0
    D[np.arange(len(pairs)), pairs[:, 1]] = 1.0
    return D


def smoothest_fit(A: np.ndarray, DtD: np.ndarray) -> np.ndarray:
    """S (C, K) float64: d = S t is, among the least-squares solutions of A d = t (A (K, C), the basis at
    the constrained vertices), the one of least d^T DtD d (DtD (C, C), the lattice's smoothing), and of
    least |d| where that too leaves a choice. d = d_fit + N z with d_fit = A^+ t and N the null space of
    A; z minimises |D (d_fit + N z)|^2."""
    U, sv, Vt = np.linalg.svd(A, full_matrices=False)  # U (K, r0): never (K, K), K may be thousands
    rank = int(np.sum(sv > RANK_TOL * sv[0])) if len(sv) else 0
    V = Vt[:rank].T  # (C, rank), the row space
    fit = V @ (U[:, :rank].T / sv[:rank, None])  # A^+ (C, K)
    N = np.linalg.qr(V, mode="complete")[0][:, rank:]  # (C, C - rank), the null space
    if N.shape[1] == 0:
        return fit
    return fit - N @ np.linalg.pinv(N.T @ DtD @ N, rcond=RANK_TOL) @ (N.T @ DtD @ fit)


@nb.njit(**_JIT)
def no_force(data, scratch, u, f):
    """The internal force of a model without mechanics: zero. f: (N, 3) float64, N (overwritten)."""
    f[:] = 0.0


@nb.njit(**_JIT)
def no_energy(data, u):
    """The elastic energy of a model without mechanics: 0 J."""
    return 0.0


class FreeFormDeformation:
    """Direct-manipulation FFD of a model's mesh, driven by its tools (module docstring).

    Attributes:
        degree: the lattice's polynomial degree n per axis ((n + 1)^3 control points).
        lo, hi: (3,) float64, m: the lattice's box, the mesh's bounding box (so that the faces of a box-shaped
            body are the lattice's, where one layer of control points alone moves them).
        G: (3N, D) float64, dimensionless: every vertex dof's displacement per unit displacement of
            each tool dof, D the tools' prescribed dofs (``targets``).
    """

    def __init__(self, model: Model, degree: int = 3):
        from .quasistatic import _Targets

        if not (isinstance(degree, int) and 1 <= degree <= 8):
            raise InputError(f"ffd: degree = {degree!r}: a whole number from 1 to 8 (the lattice's degree per axis)")
        self.degree = degree
        x = model.points
        self.lo, self.hi = x.min(axis=0), x.max(axis=0)
        B = lattice_basis(x, self.lo, self.hi, degree)  # (N, C)
        D = lattice_differences(degree)
        DtD = D.T @ D
        self.targets = _Targets(model)
        lo = model.loading
        n = model.n_vertices
        self.G = np.zeros((3 * n, len(self.targets.dofs)))
        for c in range(3):
            tool = np.flatnonzero(self.targets.dofs % 3 == c)  # columns of G that drive component c
            tool_vertices = self.targets.dofs[tool] // 3
            held = np.setdiff1d(np.flatnonzero(lo.free[:, c] == 0.0), tool_vertices)
            rows = np.concatenate([tool_vertices, held])
            if len(tool) == 0:
                continue
            A = B[rows]  # (K, C): the constrained vertices' basis; targets: the tools', then zeros
            S = smoothest_fit(A, DtD)[:, : len(tool)]  # the targets' zeros (held vertices) drop out
            self.G[c::3, tool] = B @ S

    def advance(self, model: Model, t: float, u: np.ndarray) -> np.ndarray:
        """Write into u (N, 3) m the lattice's deformation with the tools where they are at time t (s).
        Returns the tools' force (L, 3) N: zero, there being no mechanics."""
        u.reshape(-1)[:] = self.G @ self.targets.values(model, t)
        return np.zeros((len(model.loading.tool_kind), 3))

    def equilibrium(self, model: Model, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (N, 3) m at time t and the tools' total force (3,) N (zero)."""
        return (self.G @ self.targets.values(model, t)).reshape(-1, 3), np.zeros(3)

    def tool_reactions(self, model: Model, u: np.ndarray) -> np.ndarray:
        """(L, 3) zeros: a lattice exerts no force."""
        return np.zeros((len(model.loading.tool_kind), 3))
