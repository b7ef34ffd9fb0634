"""The element models' shared machinery: blocks of tetrahedra in struct-of-arrays layout.

The element models (stvk-tm, corotational-tm, hybrid-tm) evaluate, on each tetrahedron e with rest shape-function gradients g_a and volume V_e,

    H = sum_a u_a (x) g_a,   F = I + H,   f_a -= V_e P(F) g_a

with P the first Piola-Kirchhoff stress of the model's law. This is the exact negative gradient of the
P1 energy sum_e V_e W(F_e): for StVK it is the same force as Picinbono's non-linear tensor-mass (2003),
whose vertex, edge, triangle and tetrahedron tensors are the expansion of this expression in powers
of u; evaluating P per element is the cheaper way to the same numbers (about 130 flops a tetrahedron
against a few hundred for the tensor sums), and the cross-solver test checks it against dolfinx's
P1 StVK residual. The kernels evaluate blocks of tetrahedra at once, vectorised across tetrahedra (the
layout below). The kernels are in ``realtime.stvk``, ``realtime.corotational`` and ``realtime.hybrid``;
the springs' in ``realtime.springs``.

Every force kernel is ``force(data, scratch, u, f)``: ``data`` the model's read-only arrays, ``scratch``
the arrays it writes besides f, which belong to the caller (an integrator's workspace: two threads
stepping one model each pass their own) and keep the kernels free of allocation. Both tuples are
documented at each kernel; all arrays are float64 unless said.
"""

from __future__ import annotations

from typing import NamedTuple

import numba as nb
import numpy as np
from numba.core import types
from numba.extending import overload

from .geometry import morton_order, shape_gradients
from .material import Material, Materials

JIT = dict(nogil=True, cache=True)


#: The force kernels of the step loop: contraction to fused multiply-adds and reassociation change
#: results at round-off level only (the cross-solver tests hold at 1e-10); no NaN/inf assumptions, so
#: the blow-up check still sees a NaN. Division by zero gives inf as in numpy instead of raising, which
#: would put a branch in the element loops and keep them from vectorising.
HOT = dict(nogil=True, cache=True, fastmath={"contract", "reassoc", "nsz", "arcp"}, error_model="numpy")


class BlockData(NamedTuple):
    """The element kernels' data (stvk_force, corotational_force): tets (P, 4) int64, geo (GEO_ROWS P,)
    float64 and prm (P / BLOCK, 5) float64 from block_data, everywhere (P,) bool all True (the scatter's
    mask)."""

    tets: np.ndarray
    geo: np.ndarray
    prm: np.ndarray
    everywhere: np.ndarray


def in_type_of(x, c):
    """The number ``c`` in the floating type of ``x`` (compiled code: a constant that keeps a float32
    kernel in float32; numba types a literal such as 0.5 as float64, and float32 times float64 is
    float64, so without it every product with a constant would widen to double)."""
    return c


@overload(in_type_of, inline="always")
def _in_type_of(x, c):
    if isinstance(x, types.Float):
        ty = x
        return lambda x, c: ty(c)
    return None


def tet_data(points: np.ndarray, tets: np.ndarray):
    """tets (M, 4) int64, grads (M, 3, 3) (rows g_1..g_3; g_0 = -(g_1 + g_2 + g_3)), vol (M,) m^3."""
    g, vol = shape_gradients(points, tets)
    return np.ascontiguousarray(tets, dtype=np.int64), np.ascontiguousarray(g[:, 1:, :]), np.ascontiguousarray(vol)


def law_params(material: Material) -> np.ndarray:
    """(5,) float64: lam, mu, dlam, dmu, kappa, Pa. The fibre direction is per tetrahedron, in
    ``block_data``'s geometry."""
    return np.array([material.lam, material.mu, material.dlam, material.dmu, material.volume_penalty])


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
ROW = tuple(np.uint64(k * BLOCK) for k in range(GEO_ROWS))
GEO_ROWS_U = np.uint64(GEO_ROWS * BLOCK)
UBLOCK = np.uint64(BLOCK)


def block_data(points: np.ndarray, tets: np.ndarray, material: Material | Materials, dtype=np.float64):
    """The element kernels' geometry and coefficients in blocks of BLOCK tetrahedra.

    points (N, 3) float64 m; tets (M, 4) int64; ``material`` a Material or Materials (one per
    tetrahedron). Returns tets (P, 4) int64, geo (GEO_ROWS P,) and prm (P / BLOCK, 5), both ``dtype``
    (float64, or float32 for a float32 model: computed in float64, then rounded once).
    The tetrahedra are grouped by material, each group in Morton order (neighbours share blocks; the
    kernels sum over all of them, so their order is internal) and padded to whole blocks with
    zero-volume tetrahedra on the first vertex of the group's last one, which contribute nothing (and
    keep a threaded chunk's forces in the range of vertices its own tetrahedra span): every block
    holds one material, whose law_params are its row of prm, so the kernels read the coefficients
    once a block. Block b holds, for its tetrahedron q (row b BLOCK + q of the returned tets), with
    G = GEO_ROWS:
    geo[(G b + 3 a + c) BLOCK + q] = g_{a+1, c} (1/m, a, c = 0..2; g_0 = -(g_1 + g_2 + g_3)),
    geo[(G b + 9) BLOCK + q] = V (m^3) and geo[(G b + 10 + c) BLOCK + q] = a_c, the material's unit
    fibre direction at the centroid (zeros for an isotropic material).
    """
    mats = Materials.of(material, len(tets))
    order = morton_order(points, tets)
    groups, prm = [], []
    for k, m in enumerate(mats.materials):
        mine = order[mats.index[order] == k]
        if len(mine) == 0:
            continue
        t, g, vol = tet_data(points, tets[mine])
        count = len(t)
        p = BLOCK * -(-count // BLOCK)
        rows = np.zeros((GEO_ROWS, p))
        rows[:9, :count] = g.reshape(count, 9).T
        rows[9, :count] = vol
        rows[10:13, :count] = m.fiber_directions(points[t].mean(axis=1)).T
        tp = np.full((p, 4), t[-1, 0], dtype=np.int64)
        tp[:count] = t
        groups.append((tp, rows.reshape(GEO_ROWS, p // BLOCK, BLOCK).transpose(1, 0, 2).ravel()))
        prm.append(np.repeat(law_params(m)[None, :], p // BLOCK, axis=0))
    if not groups:
        return np.zeros((0, 4), dtype=np.int64), np.zeros(0, dtype), np.zeros((0, 5), dtype)
    tp = np.concatenate([t for t, _ in groups])
    geo = np.concatenate([g for _, g in groups])
    return tp, np.ascontiguousarray(geo, dtype=dtype), np.ascontiguousarray(np.concatenate(prm), dtype=dtype)


def block_scratch(dtype=np.float64) -> tuple:
    """The scratch of stvk_force: W (9 BLOCK,) of the model's float type (float64 unless said), one
    block's displacement differences and forces."""
    return (np.zeros(9 * BLOCK, dtype),)


#: Unsigned index constants of the engine's indexed loops (gather and scatter, linear-tm's edges, the
#: springs, symplectic Euler's update), which read flat views of their arrays with uint64 offsets made
#: once per call: numba wraps a negative signed index around (a sign test and two more instructions per
#: access), and indexes a 2-D or 3-D array by its run-time strides (a multiplication per access); in
#: loops that only load and store, those instructions were a fifth of the time. tests/realtime/test_model_contracts.py
#: counts them in the compiled kernels.
U1, U2, U3, U4, U5, U6, U7, U8, U9 = (np.uint64(k) for k in range(1, 10))


@nb.njit(inline="always", **HOT)
def _corners(t1, e):
    """3 i_0 .. 3 i_3 (uint64): the flat offsets of tetrahedron e's vertices, t1 the (P, 4) tets flat."""
    be = U4 * np.uint64(e)
    return (
        U3 * np.uint64(t1[be]),
        U3 * np.uint64(t1[be + U1]),
        U3 * np.uint64(t1[be + U2]),
        U3 * np.uint64(t1[be + U3]),
    )


# gather and scatter_block index flat views, made once per force call, with the unsigned constants above
# (stvk-tm on liver-x10: 1446 against 1302 us, same bits; a view made per block kept 4% of it).
@nb.njit(inline="always", **HOT)
def gather(t1, e0, u1, W):
    """W[(3 r + a) BLOCK + q] = u[i_{a+1}, r] - u[i_0, r] for the tetrahedra e0 .. e0 + BLOCK - 1; t1
    (4 P,) int64 and u1 (3 N,) m the flat views of the (P, 4) tets and the (N, 3) displacement."""
    for q in range(UBLOCK):
        i0, i1, i2, i3 = _corners(t1, np.uint64(e0) + q)
        for r in range(3):
            c = np.uint64(r)
            x0 = u1[i0 + c]
            W[(U3 * c) * UBLOCK + q] = u1[i1 + c] - x0
            W[(U3 * c + U1) * UBLOCK + q] = u1[i2 + c] - x0
            W[(U3 * c + U2) * UBLOCK + q] = u1[i3 + c] - x0


@nb.njit(inline="always", **HOT)
def scatter_block(t1, e0, W, f1, mask):
    """f_{a+1} -= W[(3 a + r) BLOCK + q], f_0 += their sum, for the tetrahedra whose mask (P,) bool is
    set; t1 (4 P,) int64 and f1 (3 N,) N the flat views of the (P, 4) tets and the (N, 3) force."""
    for q in range(UBLOCK):
        e = np.uint64(e0) + q
        if not mask[e]:
            continue
        i0, i1, i2, i3 = _corners(t1, e)
        for r in range(3):
            c = np.uint64(r)
            w1, w2, w3 = W[c * UBLOCK + q], W[(U3 + c) * UBLOCK + q], W[(U6 + c) * UBLOCK + q]
            f1[i1 + c] -= w1
            f1[i2 + c] -= w2
            f1[i3 + c] -= w3
            f1[i0 + c] += w1 + w2 + w3


@nb.njit(inline="always", **HOT)
def lane_rows(A, off, q):
    """Rows 0..8 of lane q of the block at uint64 offset ``off`` in A (a row-major 3x3 as a 9-tuple)."""
    return (
        A[off + ROW[0] + q], A[off + ROW[1] + q], A[off + ROW[2] + q],
        A[off + ROW[3] + q], A[off + ROW[4] + q], A[off + ROW[5] + q],
        A[off + ROW[6] + q], A[off + ROW[7] + q], A[off + ROW[8] + q],
    )  # fmt: skip


@nb.njit(inline="always", **HOT)
def lane_store(A, q, r):
    """Rows 0..8 of lane q of the block array A (offset 0) = the row-major 9-tuple r."""
    A[ROW[0] + q], A[ROW[1] + q], A[ROW[2] + q] = r[0], r[1], r[2]
    A[ROW[3] + q], A[ROW[4] + q], A[ROW[5] + q] = r[3], r[4], r[5]
    A[ROW[6] + q], A[ROW[7] + q], A[ROW[8] + q] = r[6], r[7], r[8]


@nb.njit(inline="always", **HOT)
def lane_in(W, geo, gb, q):
    """H = grad u = sum_a (u_a - u_0) (x) g_a of lane q (row-major 9-tuple, from the displacement
    differences in W), its gradients g_1..g_3 (row-major 9-tuple, 1/m) and its volume V (m^3)."""
    ax, bx, cx, ay, by, cy, az, bz, cz = lane_rows(W, ROW[0], q)
    g = lane_rows(geo, gb, q)
    g10, g11, g12, g20, g21, g22, g30, g31, g32 = g
    H = (
        ax * g10 + bx * g20 + cx * g30, ax * g11 + bx * g21 + cx * g31, ax * g12 + bx * g22 + cx * g32,
        ay * g10 + by * g20 + cy * g30, ay * g11 + by * g21 + cy * g31, ay * g12 + by * g22 + cy * g32,
        az * g10 + bz * g20 + cz * g30, az * g11 + bz * g21 + cz * g31, az * g12 + bz * g22 + cz * g32,
    )  # fmt: skip
    return H, g, geo[gb + ROW[9] + q]


@nb.njit(inline="always", **HOT)
def lane_out(W, q, P, g):
    """W[(3 a + r) BLOCK + q] = (P g_{a+1})_r: the element's forces, P (the stress times the volume V,
    which the laws fold into their few constants rather than into the 9 outputs) and g row-major
    9-tuples."""
    p00, p01, p02, p10, p11, p12, p20, p21, p22 = P
    g10, g11, g12, g20, g21, g22, g30, g31, g32 = g
    W[ROW[0] + q] = p00 * g10 + p01 * g11 + p02 * g12
    W[ROW[1] + q] = p10 * g10 + p11 * g11 + p12 * g12
    W[ROW[2] + q] = p20 * g10 + p21 * g11 + p22 * g12
    W[ROW[3] + q] = p00 * g20 + p01 * g21 + p02 * g22
    W[ROW[4] + q] = p10 * g20 + p11 * g21 + p12 * g22
    W[ROW[5] + q] = p20 * g20 + p21 * g21 + p22 * g22
    W[ROW[6] + q] = p00 * g30 + p01 * g31 + p02 * g32
    W[ROW[7] + q] = p10 * g30 + p11 * g31 + p12 * g32
    W[ROW[8] + q] = p20 * g30 + p21 * g31 + p22 * g32


@nb.njit(inline="always", **JIT)
def block_grad_u(tets, geo, e, u):
    """F = I + grad u (3, 3) float64 on tetrahedron e of block_data's layout, its volume and fibre (3,)
    float64, whatever the float type of geo and u (the laws compute in float64: a float32 fibre made
    laws.stvk_energy's E @ a a typing error, so a float32 stvk-tm model had no energy)."""
    b, q = e // BLOCK, e % BLOCK
    F = np.eye(3)
    for a in range(1, 4):
        for r in range(3):
            d = u[tets[e, a], r] - u[tets[e, 0], r]
            for c in range(3):
                F[r, c] += d * geo[(GEO_ROWS * b + 3 * (a - 1) + c) * BLOCK + q]
    fibre = np.empty(3)
    for c in range(3):
        fibre[c] = geo[(GEO_ROWS * b + 10 + c) * BLOCK + q]
    return F, geo[(GEO_ROWS * b + 9) * BLOCK + q], fibre
