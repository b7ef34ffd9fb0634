"""Corotational linear elasticity (polar rotation per tetrahedron, SOFA's "polar" method): the element
kernel of ``corotational-tm`` on blocks of tetrahedra (``realtime.blocks``)."""

from __future__ import annotations

import math

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
    lane_in,
    lane_out,
    lane_rows,
    lane_store,
    scatter_block,
)


@nb.njit(inline="always", **HOT)
def _cofactors(r):
    """cof(R) (9-tuple, row-major; R^-T = cof(R) / det R) and det R, R a row-major 9-tuple."""
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    c = (
        r11 * r22 - r12 * r21, r12 * r20 - r10 * r22, r10 * r21 - r11 * r20,
        r02 * r21 - r01 * r22, r00 * r22 - r02 * r20, r01 * r20 - r00 * r21,
        r01 * r12 - r02 * r11, r02 * r10 - r00 * r12, r00 * r11 - r01 * r10,
    )  # fmt: skip
    return c, r00 * c[0] + r01 * c[1] + r02 * c[2]


@nb.njit(inline="always", **HOT)
def _norm2(r):
    """|R|_F^2 of a row-major 9-tuple."""
    return (
        r[0] * r[0] + r[1] * r[1] + r[2] * r[2] + r[3] * r[3] + r[4] * r[4]
        + r[5] * r[5] + r[6] * r[6] + r[7] * r[7] + r[8] * r[8]
    )  # fmt: skip


@nb.njit(inline="always", **HOT)
def _mix(a, r, b, c):
    """a r + b c, r and c row-major 9-tuples."""
    return (
        a * r[0] + b * c[0], a * r[1] + b * c[1], a * r[2] + b * c[2],
        a * r[3] + b * c[3], a * r[4] + b * c[4], a * r[5] + b * c[5],
        a * r[6] + b * c[6], a * r[7] + b * c[7], a * r[8] + b * c[8],
    )  # fmt: skip


@nb.njit(inline="always", **HOT)
def _polar_step(r, scaled):
    """One scaled Newton step of the polar iteration R <- (g R + R^-T / g) / 2 (Higham 1986) on R
    (9-tuple, row-major), with g = (|R^-1|_F / |R|_F)^(1/2) if ``scaled``, else 1 (near convergence g
    -> 1, and it costs two roots). Returns the new R and |dR|_F^2."""
    c, det = _cofactors(r)
    gam = 1.0
    if scaled:
        gam = np.sqrt(np.sqrt(_norm2(c) / (det * det * _norm2(r))))
    n = _mix(0.5 * gam, r, 0.5 / (gam * det), c)
    change = (
        (n[0] - r[0]) ** 2 + (n[1] - r[1]) ** 2 + (n[2] - r[2]) ** 2
        + (n[3] - r[3]) ** 2 + (n[4] - r[4]) ** 2 + (n[5] - r[5]) ** 2
        + (n[6] - r[6]) ** 2 + (n[7] - r[7]) ** 2 + (n[8] - r[8]) ** 2
    )  # fmt: skip
    return n, change


def newton_gaps(tol: float, steps: int) -> tuple:
    """For k = 1 .. ``steps``: the largest squared gap |F^T F - I|_F^2 (< 1) at which k unscaled Newton
    steps from F (_unscaled_step) bring every singular value of the iterate within ``tol`` of 1.

    The unscaled iteration acts on each singular value alone, s <- (s + 1/s) / 2 (F = U S V^T gives
    X_k = U s_k(S) V^T): after one step every s is at least 1, and the error e = s - 1 then goes to
    e^2 / (2 (1 + e)). A gap g bounds every eigenvalue of F^T F = V S^2 V^T within sqrt(g) of 1, so
    every s lies in [sqrt(1 - sqrt(g)), sqrt(1 + sqrt(g))], and the ends of that interval, farthest
    from 1 after the first step, converge last. Found by bisection in exact arithmetic's recurrence;
    X_k - R = U (s_k(S) - I) V^T, so |X_k - R|_F <= sqrt(3) tol."""

    def worst(delta: float) -> int:
        k_max = 0
        for s in (math.sqrt(1.0 - delta), math.sqrt(1.0 + delta)):
            e, k = 0.5 * (s + 1.0 / s) - 1.0, 1
            while e > tol and k <= steps:
                e, k = e * e / (2.0 * (1.0 + e)), k + 1
            k_max = max(k_max, k)
        return k_max

    gaps = []
    for k in range(1, steps + 1):
        lo, hi = 0.0, 1.0
        for _ in range(60):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if worst(mid) <= k else (lo, mid)
        gaps.append(lo * lo)
    return tuple(gaps)


#: The error in each singular value that ends the bounded iteration: |R_k - R|_F <= sqrt(3) 5e-13
#: < 1e-12, as the adaptive iteration's stopping rule gives (below).
_POLAR_TOL = 5e-13

#: Steps the bounded iteration takes at most: a block with a gap beyond _POLAR_GAPS[-1] (0.67; a
#: singular value may be below 0.42 or above 1.35) takes the adaptive iteration, whose scaled steps
#: converge faster there. An element squashed below _POLAR_SQUASHED of its volume is always beyond it
#: (the least gap with det F < 0.1 is 0.98, one singular value at 0.1), so only the adaptive
#: iteration needs the scaled first step.
_POLAR_MAX_STEPS = 5
_POLAR_GAPS = newton_gaps(_POLAR_TOL, _POLAR_MAX_STEPS)


@nb.njit(inline="always", **HOT)
def _strain_gap(F):
    """|F^T F - I|_F^2 of a row-major 9-tuple F (4 |E|^2, E the Green strain)."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = F
    c00 = f00 * f00 + f10 * f10 + f20 * f20 - 1.0
    c11 = f01 * f01 + f11 * f11 + f21 * f21 - 1.0
    c22 = f02 * f02 + f12 * f12 + f22 * f22 - 1.0
    c01 = f00 * f01 + f10 * f11 + f20 * f21
    c02 = f00 * f02 + f10 * f12 + f20 * f22
    c12 = f01 * f02 + f11 * f12 + f21 * f22
    return c00 * c00 + c11 * c11 + c22 * c22 + 2.0 * (c01 * c01 + c02 * c02 + c12 * c12)


@nb.njit(inline="always", **HOT)
def _unscaled_step(r):
    """R <- (R + R^-T) / 2, R a row-major 9-tuple: _polar_step unscaled, without its change."""
    c, det = _cofactors(r)
    return _mix(0.5, r, 0.5 / det, c)


@nb.njit(inline="always", **HOT)
def _unscaled_pass(R):
    """_unscaled_step on every lane of the block's rotations R (10 BLOCK,) float64, in place."""
    for q in range(UBLOCK):
        lane_store(R, q, _unscaled_step(lane_rows(R, ROW[0], q)))


#: A Newton step that changes R by less than 1e-6 (Frobenius; the constants are squared changes) ends
#: the polar iteration: convergence is quadratic, so the new iterate is within about 1e-12 of the
#: rotation (a 1e-9 test took one more step, 10% of corotational-tm's force, to confirm round-off).
_POLAR_DONE = 1e-12


#: The steps are scaled only while some change exceeds 1 (a singular value beyond about 2.4 or below
#: 0.4): a scaled step costs two roots and a division, twice an unscaled one on the cube of the
#: benchmark, and near the rotation its factor is 1 anyway. The first step is unscaled, unless an
#: element is squashed below _POLAR_SQUASHED of its volume: an unscaled step adds F^-T, whose
#: round-off (eps / smallest singular value) would land on the other directions of R (1.8e-12 of the
#: force at a millionth, against 4e-15 scaled; tests/realtime/test_model_contracts.py).
_POLAR_SCALED = 1.0
_POLAR_SQUASHED = 0.1


@nb.njit(**JIT)
def _svd_rotation(F):
    """The rotation U V^T of F = U S V^T (row-major 9-tuples), the sign of U's last column flipped if
    U V^T would reflect. A compiled function of its own, cached once, rather than inlined with _polar
    into every kernel and step loop: each had compiled LAPACK's SVD and determinant bindings again
    (precompiling corotational-tm on one thread took 32.7 s of compilation, 26.7 s with this)."""
    U, _, Vt = np.linalg.svd(np.array(F).reshape(3, 3))
    if np.linalg.det(U) * np.linalg.det(Vt) < 0.0:
        U[:, 2] = -U[:, 2]
    Q = U @ Vt
    return Q[0, 0], Q[0, 1], Q[0, 2], Q[1, 0], Q[1, 1], Q[1, 2], Q[2, 0], Q[2, 1], Q[2, 2]


@nb.njit(inline="always", **HOT)
def _polar(F):
    """Rotation (9-tuple, row-major) of the polar decomposition F = R U, F a row-major 9-tuple.

    Scaled Newton iteration (_polar_step): quadratic convergence for det F > 0, in registers. An
    inverted or flat element (det F <= 1e-12) takes the SVD instead, with the sign of the smallest
    singular direction flipped so that R stays a rotation (Irving, Teran & Fedkiw 2004).
    """
    if _det(F) <= 1e-12:
        return _svd_rotation(F)
    r, scaled = F, _det(F) < _POLAR_SQUASHED
    for _ in range(30):
        r, change = _polar_step(r, scaled)
        if change < _POLAR_DONE:
            break
        scaled = change > _POLAR_SCALED
    return r


@nb.njit(inline="always", **HOT)
def _plus_identity(H):
    """F = I + H, row-major 9-tuples."""
    return (1.0 + H[0], H[1], H[2], H[3], 1.0 + H[4], H[5], H[6], H[7], 1.0 + H[8])


@nb.njit(inline="always", **HOT)
def _det(F):
    """det of a row-major 9-tuple."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = F
    return f00 * (f11 * f22 - f12 * f21) - f01 * (f10 * f22 - f12 * f20) + f02 * (f10 * f21 - f11 * f20)


@nb.njit(inline="always", **HOT)
def _corotated_pk1(F, r, lam, mu):
    """P = 2 mu (F - R) + lam tr(R^T F - I) R, R (row-major 9-tuple) the polar rotation of F: the
    stress of the corotated energy lam/2 tr(S - I)^2 + mu |S - I|^2, S = R^T F. It is R sigma(S - I),
    sigma the linear law, written with R S = F (36 flops against 81 for the rotated stress). lam and mu
    in Pa, or times the volume V for V P (lane_out's)."""
    f00, f01, f02, f10, f11, f12, f20, f21, f22 = F
    r00, r01, r02, r10, r11, r12, r20, r21, r22 = r
    c = lam * (
        (r00 * f00 + r10 * f10 + r20 * f20 - 1.0)
        + (r01 * f01 + r11 * f11 + r21 * f21 - 1.0)
        + (r02 * f02 + r12 * f12 + r22 * f22 - 1.0)
    )
    a = 2.0 * mu
    return (
        a * (f00 - r00) + c * r00, a * (f01 - r01) + c * r01, a * (f02 - r02) + c * r02,
        a * (f10 - r10) + c * r10, a * (f11 - r11) + c * r11, a * (f12 - r12) + c * r12,
        a * (f20 - r20) + c * r20, a * (f21 - r21) + c * r21, a * (f22 - r22) + c * r22,
    )  # fmt: skip


@nb.njit(inline="always", **HOT)
def _polar_pass(R, scaled):
    """One Newton step (_polar_step) on every lane of the block's rotations R (10 BLOCK,) float64, in
    place. Returns how many lanes changed by _POLAR_DONE or more, and how many by more than
    _POLAR_SCALED."""
    active = 0
    far = 0  # an integer count: a max would not vectorise
    for q in range(UBLOCK):
        n, change = _polar_step(lane_rows(R, ROW[0], q), scaled)
        lane_store(R, q, n)
        R[ROW[9] + q] = change
        active += change >= _POLAR_DONE
        far += change > _POLAR_SCALED
    return active, far


#: A block whose lanes still changing are this many or fewer finishes them one at a time
#: (_finish_lanes) instead of taking another pass over all BLOCK: in make bench's state of the liver
#: 96% of the tetrahedra converge in 3 steps, but one or two slow ones gave 84% of the blocks a 4th.
_POLAR_STRAGGLERS = 8


@nb.njit(**HOT)
def _finish_lanes(R):
    """The lanes of R (10 BLOCK,) whose last change (row 9) is _POLAR_DONE or more go on with the polar
    iteration one at a time, each until its own change falls below it (at most 30 steps), scaled while
    its change exceeds _POLAR_SCALED. A lane whose change is NaN stops, as in _polar_pass."""
    for q in range(UBLOCK):
        change = R[ROW[9] + q]
        if not change >= _POLAR_DONE:
            continue
        r = lane_rows(R, ROW[0], q)
        for _ in range(30):
            r, change = _polar_step(r, change > _POLAR_SCALED)
            if not change >= _POLAR_DONE:
                break
        lane_store(R, q, r)
        R[ROW[9] + q] = change


@nb.njit(inline="always", **HOT)
def _adaptive_polar(R, Fb):
    """The adaptive polar iteration on a block's rotations R (10 BLOCK,) float64 (rows 0..8 the
    rotation, started at F; row 9 its last change), Fb (9 BLOCK,) its F: passes over the whole block
    until no more than _POLAR_STRAGGLERS lanes are still changing, which then finish one at a time
    (_finish_lanes). Lanes that converged earlier take the block's further steps at round-off. The
    first step is unscaled unless an element of the block is squashed (det F < _POLAR_SQUASHED); later
    steps are scaled while the block's largest change is above _POLAR_SCALED (a block-wide choice, so
    that unscaled steps take no roots)."""
    far = 0
    for q in range(UBLOCK):
        far += _det(lane_rows(Fb, ROW[0], q)) < _POLAR_SQUASHED
    active = BLOCK  # every lane takes the first step, scaled if one is squashed
    for _ in range(30):
        if active <= _POLAR_STRAGGLERS:
            break
        # one decision for the whole block, taken outside the lane loop: a branch inside it would be
        # if-converted, and every step would pay the scaled one's roots
        if far > 0:
            active, far = _polar_pass(R, True)
        else:
            active, far = _polar_pass(R, False)
    if active:
        _finish_lanes(R)


@nb.njit(inline="always", **HOT)
def _corotational_block(W, R, Fb, geo, gb, lam, mu):
    """Element forces of one block, in place in W (as _stvk_block), for the corotated law.

    The polar iteration runs on all the block's tetrahedra at once, with the rotations in the scratch
    R (10 BLOCK,) float64. Its number of steps is known before it starts: the block's largest strain
    gap |F^T F - I|_F^2 gives the unscaled steps that bring every lane within _POLAR_TOL of its
    rotation (_POLAR_GAPS, newton_gaps), and the block takes them with no test of convergence (on
    make bench's liver-x10 the tests and the lanes left over had cost a quarter of the polar's time). A
    block beyond _POLAR_MAX_STEPS takes the adaptive iteration (_adaptive_polar). Inverted elements
    start from R = I (which stays put) and take the SVD afterwards, one at a time. Fb (9 BLOCK,) keeps
    each lane's F for the stress, which reads it back instead of forming it again (45 flops a
    tetrahedron).
    """
    identity = (1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0)
    inverted = 0
    g1, g2, g3, g4, g5 = _POLAR_GAPS
    over1 = over2 = over3 = over4 = over5 = 0  # lanes that need more than 1 .. 5 steps (counts vectorise)
    for q in range(UBLOCK):
        F = _plus_identity(lane_in(W, geo, gb, q)[0])
        lane_store(Fb, q, F)
        ok = _det(F) > 1e-12
        lane_store(R, q, F if ok else identity)
        inverted += not ok
        gap = _strain_gap(F) if ok else 0.0
        over1 += gap > g1
        over2 += gap > g2
        over3 += gap > g3
        over4 += gap > g4
        over5 += gap > g5
    if over5:
        _adaptive_polar(R, Fb)
    else:
        for _ in range(1 + (over1 > 0) + (over2 > 0) + (over3 > 0) + (over4 > 0)):
            _unscaled_pass(R)
    if inverted:
        for q in range(UBLOCK):
            F = lane_rows(Fb, ROW[0], q)
            if _det(F) <= 1e-12:
                lane_store(R, q, _polar(F))
    for q in range(UBLOCK):
        g = lane_rows(geo, gb, q)
        v = geo[gb + ROW[9] + q]
        lane_out(W, q, _corotated_pk1(lane_rows(Fb, ROW[0], q), lane_rows(R, ROW[0], q), lam * v, mu * v), g)


def corotational_scratch() -> tuple:
    """The scratch of corotational_force: W (9 BLOCK,) as block_scratch, R (10 BLOCK,) float64 the
    block's rotations and last polar changes, Fb (9 BLOCK,) float64 its deformation gradients."""
    return (np.zeros(9 * BLOCK), np.zeros(10 * BLOCK), np.zeros(9 * BLOCK))


@nb.njit(**HOT)
def corotational_force(data, scratch, u, f):
    """Corotational linear force: f_a -= V R sigma(R^T F - I) g_a, R the polar rotation of F.

    This is the exact gradient of W(F) = lam/2 tr(S - I)^2 + mu |S - I|^2, S = R^T F the polar stretch
    (the "corotated" energy; SOFA's TetrahedronFEMForceField, method "polar").
    data: blocks.BlockData.   scratch: corotational_scratch().
    """
    tets, geo, prm, everywhere = data
    W, R, Fb = scratch
    f[:] = 0.0
    corotational_blocks(tets, geo, prm, everywhere, W, R, Fb, 0, tets.shape[0] // BLOCK, u, f)


@nb.njit(inline="always", **HOT)
def corotational_blocks(tets, geo, prm, everywhere, W, R, Fb, b0, b1, u, f):
    """corotational_force's pass over the blocks b0 .. b1 - 1 of BlockData's arrays, adding into f
    (N, 3) N; W, R, Fb the arrays of corotational_scratch()."""
    t1, u1, f1 = tets.reshape(-1), u.reshape(-1), f.reshape(-1)
    for b in range(b0, b1):
        gather(t1, b * BLOCK, u1, W)
        _corotational_block(W, R, Fb, geo, np.uint64(b) * GEO_ROWS_U, prm[b, 0], prm[b, 1])
        scatter_block(t1, b * BLOCK, W, f1, everywhere)


@nb.njit(**JIT)
def corotational_energy(data, u):
    """sum_e V_e (lam/2 tr(S - I)^2 + mu |S - I|^2), S = R^T F."""
    tets, geo, prm = data.tets, data.geo, data.prm
    w = 0.0
    for e in range(tets.shape[0]):
        lam, mu = prm[e // BLOCK, 0], prm[e // BLOCK, 1]
        F, vol, _ = block_grad_u(tets, geo, e, u)
        R = np.array(_polar((F[0, 0], F[0, 1], F[0, 2], F[1, 0], F[1, 1], F[1, 2], F[2, 0], F[2, 1], F[2, 2])))
        S = R.reshape(3, 3).T @ F - np.eye(3)
        S = 0.5 * (S + S.T)
        tr = S[0, 0] + S[1, 1] + S[2, 2]
        w += vol * (0.5 * lam * tr * tr + mu * np.sum(S * S))
    return w
