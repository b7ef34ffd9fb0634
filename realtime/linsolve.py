"""The rest-state system of implicit Euler, factored once by SuperLU and solved in numba.

``factorise`` factors A0 = cm M + ck K0 on the free components (K0 the model's rest stiffness,
``Model.rest_stiffness``); ``factor_solve`` applies A0^-1 inside the compiled CG loop.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .model import Model

_JIT = dict(nogil=True, cache=True)


class Factor(NamedTuple):
    """SuperLU's factors Pr A0 Pc = L U of A0 restricted to the free dofs, laid out for factor_solve:
    free (F,) int64 the free flat dofs; perm_r, perm_c (F,) int64; the strictly lower part of L and the
    strictly upper part of U in CSC (indptr, indices int64, data float64) and their diagonals (F,);
    work (F,) float64 scratch."""

    free: np.ndarray
    perm_r: np.ndarray
    perm_c: np.ndarray
    lower_ptr: np.ndarray
    lower_idx: np.ndarray
    lower_val: np.ndarray
    lower_diag: np.ndarray
    upper_ptr: np.ndarray
    upper_idx: np.ndarray
    upper_val: np.ndarray
    upper_diag: np.ndarray
    work: np.ndarray


#: Free components up to which implicit Euler factors its rest-state system (and min_eigenvalue uses
#: shift-invert on the rest stiffness): beyond, the fill-in of a 3D mesh's factor makes it too costly.
FACTOR_LIMIT = 20_000


def factorise(model: Model, cm: float, ck: float) -> Factor:
    """Sparse LU (SuperLU, minimum degree on A + A^T) of A0 = cm M + ck K0 on the free components, K0
    the rest stiffness, as a Factor.

    A0 is symmetric positive definite (a positive lumped mass plus a stiffness that no model makes
    indefinite at rest), so SuperLU takes its pivots on the diagonal (SymmetricMode, no threshold
    pivoting): the same fill, and on the cantilever-cut refined once (9 720 free components) 0.21 s
    instead of 3.4 s, whose row interchanges undid the ordering's elimination tree."""
    fidx = np.flatnonzero(model.loading.free.reshape(-1) != 0.0)
    a = sp.diags(cm * np.repeat(model.mass, 3)) + ck * model.rest_stiffness()
    lu = spla.splu(
        a.tocsr()[fidx][:, fidx].tocsc(),
        permc_spec="MMD_AT_PLUS_A",
        diag_pivot_thresh=0.0,
        options={"SymmetricMode": True},
    )
    lower, upper = sp.tril(lu.L, -1).tocsc(), sp.triu(lu.U, 1).tocsc()
    i64 = lambda x: np.ascontiguousarray(x, dtype=np.int64)  # noqa: E731
    return Factor(
        i64(fidx), i64(lu.perm_r), i64(lu.perm_c),
        i64(lower.indptr), i64(lower.indices), np.ascontiguousarray(lower.data), np.ascontiguousarray(lu.L.diagonal()),
        i64(upper.indptr), i64(upper.indices), np.ascontiguousarray(upper.data), np.ascontiguousarray(lu.U.diagonal()),
        np.zeros(len(fidx)),
    )  # fmt: skip


@nb.njit(**_JIT)
def factor_solve(fac, r, z):
    """z = A0^-1 r on the free components, zero on the others, with A0's sparse LU factors (factorise).

    SuperLU factors Pr A0 Pc = L U; then A0 x = b is L U y = Pr b, x = Pc y.
    fac: (fidx (F,) the free flat dofs, perm_r, perm_c (F,) int64, the strictly lower part of L and
    the strictly upper part of U in CSC (indptr, indices, data), their diagonals (F,), scratch (F,)).
    r, z: (N, 3) float64.
    """
    fidx, pr, pc, lp, li, lx, ld, up, ui, ux, ud, w = fac
    r1, z1 = r.reshape(-1), z.reshape(-1)
    n = fidx.shape[0]
    for j in range(n):
        w[pr[j]] = r1[fidx[j]]
    for j in range(n):  # forward: L
        wj = w[j] / ld[j]
        w[j] = wj
        for k in range(lp[j], lp[j + 1]):
            w[li[k]] -= lx[k] * wj
    for j in range(n - 1, -1, -1):  # backward: U
        wj = w[j] / ud[j]
        w[j] = wj
        for k in range(up[j], up[j + 1]):
            w[ui[k]] -= ux[k] * wj
    z1[:] = 0.0
    for j in range(n):
        z1[fidx[j]] = w[pc[j]]


def _empty(dtype) -> np.ndarray:
    return np.zeros(0, dtype=dtype)


#: The mass preconditioner's stand-in for a Factor (the same types, nothing in it).
NO_FACTOR = Factor(*(_empty(t) for t in (np.int64,) * 5 + (np.float64,) * 2 + (np.int64,) * 2 + (np.float64,) * 3))
