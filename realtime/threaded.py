"""Force kernels on several threads (linear-tm, stvk-tm, corotational-tm built with ``threads`` > 1).

Each kernel splits its work into T contiguous chunks fixed at build (``chunks``): blocks of tetrahedra in
``block_data``'s Morton order, so that a chunk is a compact piece of the body, or vertex rows for
linear tensor-mass, balanced by their edges. Thread t runs the serial kernel's loop over its chunk into
its own force array F[t] (no two threads write one number), and the arrays are then added in the
order t = 0, 1, ..., T - 1 by vertex ranges on all threads. A chunk writes forces in one range of the
vertices, its span (``force_spans``), zeroes only that range, and the sums read each F[t] only there:
outside it F[t] is zero and stays so. On a mesh numbered along the body (``realtime.renumber``) two
threads' spans overlap on the interface of the two pieces alone. The result therefore does not depend on
which thread ran which chunk or when: a threaded model gives the same bits in every run, and differs
from the serial kernel by round-off only (the order of the sums; the tests compare at a multiple of
machine epsilon).

The threads are numba's (``parallel=True``), in a threading layer that may be entered from several
Python threads at once (GNU OpenMP, else TBB; never numba's workqueue), so that a haptic loop and a
visual loop may each step their own state of one threaded model. ``check_threading`` says which layer
runs, or why none can.
"""

from __future__ import annotations

import warnings
from functools import partial
from typing import NamedTuple

import numba as nb
import numpy as np

from .blocks import BLOCK, HOT
from .corotational import corotational_blocks
from .errors import InputError
from .model import no_scratch
from .neohookean import neohookean_blocks
from .stvk import stvk_blocks
from .tensor_mass import linear_rows, linear_tm_energy, linear_tm_force

PAR = dict(HOT, parallel=True)

# The layer numba starts its threads in, chosen before the first parallel call of the process: GNU
# OpenMP, whose threads spin between steps (GOMP_SPINCOUNT, set in realtime/__init__.py), else TBB
# (check_threading), whose threads slept: on the liver-x10 TBB's two-thread stvk-tm step was no faster
# than one thread's (make bench), OpenMP's 1.6x. Both may be entered from two Python threads at once;
# numba's own workqueue may not (it aborts the process), so it is never used.
THREADING_LAYERS = ("omp", "tbb")
nb.config.THREADING_LAYER = THREADING_LAYERS[0]


class Threaded(NamedTuple):
    """A threaded kernel's data: ``data`` the serial kernel's (BlockData or TensorData), ``chunks`` (T + 1,)
    int64 the bounds of each thread's work units (blocks of BLOCK tetrahedra, or vertex rows)."""

    data: tuple
    chunks: np.ndarray


def balanced_chunks(cost: np.ndarray, threads: int) -> np.ndarray:
    """(T + 1,) int64 bounds splitting units of work of ``cost`` (K,) float64 (any unit) into ``threads``
    contiguous ranges of nearly equal total cost (T = min(threads, K), at least 1)."""
    t = max(1, min(int(threads), len(cost)))
    total = np.concatenate([[0.0], np.cumsum(cost, dtype=float)])
    bounds = np.searchsorted(total, total[-1] * np.arange(t + 1) / t, side="left")
    bounds[0], bounds[-1] = 0, len(cost)
    return np.maximum.accumulate(bounds).astype(np.int64)


#: Bytes between one thread's scratch and the next's. Back to back, the lines at the end of thread 0's
#: block and the start of thread 1's, written by both cores every block, were also pulled in by the
#: other core's prefetcher: on the liver-x10 the two-thread stvk-tm force took 870 to 920 us with no
#: gap or one of 128 bytes, and 817 to 834 us with a gap of 512 bytes or more (up to 8 KB; this
#: AVX2 EPYC, one process measuring each gap twice).
PAD_BYTES = 1024


def threaded_scratch(serial_scratch, threads: int, n_vertices: int, dtype, spans: np.ndarray) -> tuple:
    """Scratch of a threaded kernel: each array of ``serial_scratch()`` (1-D) once per thread ((T, K +
    pad) of its dtype, the kernel using the first K), then ``spans`` (T, 2) int64 (force_spans, a
    copy), then F (T, N + pad, 3) of the model's float type ``dtype``, each thread's forces in its first
    N rows, N, zero outside its span; each thread's row padded by PAD_BYTES."""
    one = serial_scratch()
    per = tuple(np.zeros((threads, a.size + -(-PAD_BYTES // a.itemsize)), a.dtype) for a in one)
    pad = -(-PAD_BYTES // (3 * np.dtype(dtype).itemsize))
    return per + (np.array(spans, dtype=np.int64), np.zeros((threads, n_vertices + pad, 3), dtype))


def scratch_factory(serial_scratch, threads: int, n_vertices: int, dtype, spans: np.ndarray):
    """Model.new_scratch of a threaded kernel (threaded_scratch with these arguments)."""
    return partial(threaded_scratch, serial_scratch, threads, n_vertices, dtype, spans)


def force_spans(first: np.ndarray, last: np.ndarray) -> np.ndarray:
    """(T, 2) int64: each thread's span [lo, hi), the range of vertices its chunk writes forces to,
    from ``first`` and ``last`` (T,) int64, the least and the greatest vertex it writes (last < first
    for a chunk that writes none: an empty span)."""
    first, last = np.asarray(first, dtype=np.int64), np.asarray(last, dtype=np.int64)
    return np.stack([np.minimum(first, last + 1), last + 1], axis=1)


def block_spans(tets: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """force_spans of chunks (T + 1,) of blocks of BlockData's tets (P, 4): every vertex of their
    tetrahedra, padding included (blocks.block_data pads a block with its last tetrahedron's vertex)."""
    parts = [tets[BLOCK * a : BLOCK * b] for a, b in zip(chunks[:-1], chunks[1:], strict=True)]
    return force_spans([p.min() if p.size else 0 for p in parts], [p.max() if p.size else -1 for p in parts])


def row_spans(cols: np.ndarray, row_start: np.ndarray, chunks: np.ndarray) -> np.ndarray:
    """force_spans of chunks (T + 1,) of vertex rows of TensorData: a row writes its own vertex and
    the neighbours j > i of its edges (cols (E,), row_start (N + 1,) int64)."""
    first, last = [], []
    for a, b in zip(chunks[:-1], chunks[1:], strict=True):
        j = cols[row_start[a] : row_start[b]]
        first.append(a if b > a else 0)
        last.append(max(b - 1, int(j.max()) if j.size else -1) if b > a else -1)
    return force_spans(first, last)


def check_threads(threads) -> int:
    """``threads`` as an int >= 1, or InputError; for more than one, InputError unless a thread-safe
    layer (TBB or GNU OpenMP) can run numba's threads on this machine."""
    if isinstance(threads, bool) or not isinstance(threads, (int, np.integer)) or threads < 1:
        raise InputError(f"threads = {threads!r}: must be an integer >= 1")
    if threads > 1:
        check_threading()
    return int(threads)


def check_threading() -> str:
    """The name of the threading layer the threaded kernels run in, the first of THREADING_LAYERS that
    starts, or InputError saying why none could (install Debian's libgomp1, or libtbb12). A layer other
    than GNU OpenMP works but gains nothing, and says so once (a RuntimeWarning): TBB's threads sleep
    between steps, and two of them gave stvk-tm no speed-up on liver-x10."""
    reasons = []
    for layer in THREADING_LAYERS:
        nb.config.THREADING_LAYER = layer
        try:
            _probe(np.zeros(4))
            running = nb.threading_layer()
            if running != "omp":
                warnings.warn(
                    f"threads > 1 run in numba's {running} threading layer, whose threads sleep between "
                    "steps: expect no speed-up (install Debian's libgomp1 for GNU OpenMP's)",
                    RuntimeWarning,
                    stacklevel=2,
                )
            return running
        except (ValueError, RuntimeError) as e:
            reasons.append(f"{layer}: {str(e).strip().splitlines()[0] if str(e).strip() else type(e).__name__}")
    raise InputError(
        f"threads > 1: no thread-safe threading layer for numba ({'; '.join(reasons)}); "
        "install Debian's libgomp1, or build with threads = 1"
    )


@nb.njit(parallel=True, cache=True)
def _probe(x):
    for i in nb.prange(x.shape[0]):
        x[i] = i
    return x


@nb.njit(inline="always", **HOT)
def span_part(spans, t, lo, hi):
    """The part [a, b) of the components lo .. hi - 1 (flat, 3 a vertex) inside thread t's span."""
    a = min(max(3 * spans[t, 0], lo), hi)
    return a, max(min(3 * spans[t, 1], hi), a)


@nb.njit(inline="always", **HOT)
def in_span(spans, t, k):
    """Whether component k (flat, 3 a vertex) is inside thread t's span."""
    return 3 * spans[t, 0] <= k < 3 * spans[t, 1]


@nb.njit(inline="always", **HOT)
def two_span_cuts(spans, lo, hi):
    """lo, hi and where each of two threads' spans starts and ends within them, in order (a 6-tuple of
    int64); each segment between two cuts lies wholly inside or wholly outside each span. Each span's
    part is an ordered pair inside [lo, hi], so the order is a merge of the two pairs: no sort and no
    array (np.sort cost each process that compiled it 2.5 s, and the array an allocation a call)."""
    a0, b0 = span_part(spans, 0, lo, hi)
    a1, b1 = span_part(spans, 1, lo, hi)
    inner_lo, inner_hi = max(a0, a1), min(b0, b1)
    return lo, min(a0, a1), min(inner_lo, inner_hi), max(inner_lo, inner_hi), max(b0, b1), hi


@nb.njit(inline="always", **HOT)
def _copy_sum(F, f, which, x, y):
    """f[x:y] = F[0] + F[1], F[0], F[1] or 0 (``which`` 3, 1, 2 or 0) over the components x .. y - 1,
    with unsigned indices (a signed one is tested for wrap-around at every access, which stops the
    vectoriser: the sum of two threads' liver-x10 forces took 17.8 us, this loop 5)."""
    a, b = np.uint64(x), np.uint64(y)
    if which == 3:
        for k in range(a, b):
            f[k] = F[0, k] + F[1, k]
    elif which == 1 or which == 2:
        t = which - 1
        for k in range(a, b):
            f[k] = F[t, k]
    else:
        for k in range(a, b):
            f[k] = 0.0


@nb.njit(inline="always", **HOT)
def sum_range(spans, F, f, lo, hi):
    """f[lo:hi] = F[0, lo:hi] + F[1, lo:hi] + ..., added in thread order, each F[t] read inside its span
    alone (zero outside it: the same sum); F (T, M) and f (M,) flat, spans (T, 2) int64. Each pass is a
    plain loop over contiguous numbers, which vectorises (a loop over t inside the loop over the
    numbers did not: the sum of two threads' liver-x10 forces took 108 us). Two threads' ranges are
    cut where a span starts or ends (two_span_cuts), each piece one pass."""
    if F.shape[0] == 2:
        c = two_span_cuts(spans, lo, hi)
        for i in range(5):
            _copy_sum(F, f, in_span(spans, 0, c[i]) + 2 * in_span(spans, 1, c[i]), c[i], c[i + 1])
        return
    for k in range(np.uint64(lo), np.uint64(hi)):
        f[k] = 0.0
    for t in range(F.shape[0]):
        a, b = span_part(spans, t, lo, hi)
        for k in range(np.uint64(a), np.uint64(b)):
            f[k] += F[t, k]


@nb.njit(inline="always", **HOT)
def thread_range(spans, n, p, parts):
    """The components [lo, hi) of the n that thread p of ``parts`` sums and updates. For two threads
    of two spans, the cut lies inside their overlap [a, b), where the two threads' costs are equal, a
    component costing one pass and one more read where both arrays are summed: m + (m - a) = (n - m)
    + (b - m), m = (n + a + b) / 4, rounded down to 8 components (a cache line) where the overlap
    allows. Each thread then reads the other's forces on a part of the overlap and its own elsewhere.
    Spans that do not overlap are cut at n / 2 inside the gap between them. Otherwise the p-th of
    ``parts`` equal ranges. (The middle of the overlap, the rule before, gave thread 0 63% of
    linear-tm's liver-x10 update, whose spans overlap on their right: 28.9 against 17.3 us, one core
    running each part in turn; 25.1 and 20.3 with this one.)"""
    if parts == 2 and spans.shape[0] == 2:
        a, b = 3 * spans[1, 0], 3 * spans[0, 1]
        if a < b:
            mid = min(max((n + a + b) // 4 // 8 * 8, a), b)
        else:
            mid = min(max(n // 2 // 8 * 8, b), a)
        mid = min(max(mid, 0), n)
        return (0, mid) if p == 0 else (mid, n)
    return p * n // parts, (p + 1) * n // parts


@nb.njit(inline="always", **HOT)
def sum_threads(spans, F, f):
    """f (N, 3) = the sum over t of F[:, :N] (F (T, M, 3), M >= N) inside each thread's span (spans (T,
    2) int64), in the order of t, on all threads (thread_range's range of the numbers each). Inlined,
    so that the threaded kernel that calls it holds a parallel loop of its own (a compiled function
    that only calls parallel ones need not start numba's threads when it is loaded from the cache)."""
    n = f.size
    parts = F.shape[0]
    flat = f.reshape(n)
    Fs = F.reshape(parts, F.shape[1] * 3)
    for p in nb.prange(parts):
        lo, hi = thread_range(spans, n, p, parts)
        sum_range(spans, Fs, flat, lo, hi)


# Each thread's share (its force array zeroed, then its chunk added) runs in a compiled call of its own:
# inlined into a parallel loop, the block code trips numba's array analysis (an AssertionError on the
# lanes' tuples).
@nb.njit(**HOT)
def _stvk_chunk(tets, geo, prm, everywhere, W, b0, b1, u, f, span):
    f[span[0] : span[1], :] = 0.0
    stvk_blocks(tets, geo, prm, everywhere, W, b0, b1, u, f)


@nb.njit(**HOT)
def _neohookean_chunk(tets, geo, prm, everywhere, W, b0, b1, u, f, span):
    f[span[0] : span[1], :] = 0.0
    neohookean_blocks(tets, geo, prm, everywhere, W, b0, b1, u, f)


@nb.njit(**HOT)
def _corotational_chunk(tets, geo, prm, everywhere, W, R, Fb, b0, b1, u, f, span):
    f[span[0] : span[1], :] = 0.0
    corotational_blocks(tets, geo, prm, everywhere, W, R, Fb, b0, b1, u, f)


@nb.njit(**HOT)
def _linear_chunk(cols, et, row_start, lo, hi, u, f, span):
    f[span[0] : span[1], :] = 0.0
    f1 = f.reshape(-1)
    linear_rows(cols, et.reshape(-1), row_start, lo, hi, u.reshape(-1), f1)


# The unsummed kernels: each thread's forces in its own F[t] (the scratch's last array), f untouched.
# Symplectic Euler adds them in its update (steppers.se_sum_update_threads); the threaded force
# kernels add them at once (sum_threads).
@nb.njit(**PAR)
def stvk_unsummed(data, scratch, u, f):
    (tets, geo, prm, everywhere), chunks = data
    W, spans, F = scratch
    for t in nb.prange(chunks.shape[0] - 1):
        _stvk_chunk(tets, geo, prm, everywhere, W[t], chunks[t], chunks[t + 1], u, F[t], spans[t])


@nb.njit(**PAR)
def neohookean_unsummed(data, scratch, u, f):
    (tets, geo, prm, everywhere), chunks = data
    W, spans, F = scratch
    for t in nb.prange(chunks.shape[0] - 1):
        _neohookean_chunk(tets, geo, prm, everywhere, W[t], chunks[t], chunks[t + 1], u, F[t], spans[t])


@nb.njit(**PAR)
def corotational_unsummed(data, scratch, u, f):
    (tets, geo, prm, everywhere), chunks = data
    W, R, Fb, spans, F = scratch
    for t in nb.prange(chunks.shape[0] - 1):
        _corotational_chunk(tets, geo, prm, everywhere, W[t], R[t], Fb[t], chunks[t], chunks[t + 1], u, F[t], spans[t])


@nb.njit(**PAR)
def linear_tm_unsummed(data, scratch, u, f):
    (_, cols, et, row_start), chunks = data
    spans, F = scratch[-2], scratch[-1]
    for t in nb.prange(chunks.shape[0] - 1):
        _linear_chunk(cols, et, row_start, chunks[t], chunks[t + 1], u, F[t], spans[t])


@nb.njit(**PAR)
def stvk_force_threaded(data, scratch, u, f):
    """stvk.stvk_force on the chunks' threads.

    data: Threaded(BlockData, chunks over blocks).   scratch: threaded_scratch(block_scratch, T, N, float64, spans).
    u: (N, 3) float64 displacement, m.   f: (N, 3) float64 force, N (overwritten).
    """
    stvk_unsummed(data, scratch, u, f)
    sum_threads(scratch[-2], scratch[-1], f)


@nb.njit(**PAR)
def neohookean_force_threaded(data, scratch, u, f):
    """neohookean.neohookean_force on the chunks' threads.

    data: Threaded(BlockData, chunks over blocks).   scratch: threaded_scratch(block_scratch, T, N, float64, spans).
    u: (N, 3) float64 displacement, m.   f: (N, 3) float64 force, N (overwritten).
    """
    neohookean_unsummed(data, scratch, u, f)
    sum_threads(scratch[-2], scratch[-1], f)


@nb.njit(**PAR)
def corotational_force_threaded(data, scratch, u, f):
    """corotational.corotational_force on the chunks' threads.

    data: Threaded(BlockData, chunks over blocks).
    scratch: threaded_scratch(corotational_scratch, T, N, float64, spans).
    u: (N, 3) float64 displacement, m.   f: (N, 3) float64 force, N (overwritten).
    """
    corotational_unsummed(data, scratch, u, f)
    sum_threads(scratch[-2], scratch[-1], f)


@nb.njit(**PAR)
def linear_tm_force_threaded(data, scratch, u, f):
    """tensor_mass.linear_tm_force (f = -K u) on the chunks' threads, each a range of vertex rows.

    data: Threaded(TensorData, chunks over vertices).   scratch: threaded_scratch(no_scratch, T, N, float64, spans).
    u: (N, 3) float64 displacement, m.   f: (N, 3) float64 force, N (overwritten).
    """
    linear_tm_unsummed(data, scratch, u, f)
    sum_threads(scratch[-2], scratch[-1], f)


def block_chunks(n_blocks: int, threads: int) -> np.ndarray:
    """Chunks of ``n_blocks`` blocks of tetrahedra for ``threads`` threads (equal counts)."""
    return balanced_chunks(np.ones(n_blocks), threads)


def row_chunks(row_start: np.ndarray, threads: int) -> np.ndarray:
    """Chunks of vertex rows for ``threads`` threads, balanced by each row's work: its edges (i, j > i),
    each read once (the difference form reads no vertex tensor, so a row costs its edges: with a row
    counted as one more edge, the first half of the liver-x10 took 279 us against 253 for the second,
    and 272 against 259 without); row_start (N + 1,) int64 as in TensorData."""
    return balanced_chunks(np.diff(row_start).astype(float), threads)


def linear_tm_kernel(tm, threads: int = 1, dtype=np.float64) -> tuple:
    """(force, energy, data, new_scratch) of linear tensor-mass on TensorMass ``tm`` in the float type
    ``dtype``: the serial kernel for one thread, else the threaded one with its rows split for
    ``threads``."""
    data = tm.kernel_data(dtype)
    if threads == 1:
        return linear_tm_force, linear_tm_energy, data, no_scratch
    chunks = row_chunks(data.row_start, threads)
    return (
        THREADED[linear_tm_force.__name__],
        partial(threaded_energy, linear_tm_energy),
        Threaded(data, chunks),
        scratch_factory(no_scratch, threads, tm.n_vertices, dtype, row_spans(data.cols, data.row_start, chunks)),
    )


def threaded_energy(serial, data: Threaded, u: np.ndarray) -> float:
    """The serial energy kernel ``serial`` on a threaded model's data (the energy is not on the step's
    path: one thread)."""
    return serial(data.data, u)


def block_kernel(force, energy, scratch, data, n_vertices: int, threads: int) -> tuple:
    """(force, energy, data, new_scratch) of an element model (stvk-tm, corotational-tm) whose serial
    kernels are ``force`` and ``energy`` on BlockData ``data`` with scratch ``scratch`` (a function
    returning it): those for one thread, else their threaded versions (THREADED) with the blocks split
    for ``threads``, in the float type of the data's geometry."""
    if threads == 1:
        return force, energy, data, scratch
    chunks = block_chunks(len(data.tets) // BLOCK, threads)
    return (
        THREADED[force.__name__],
        partial(threaded_energy, energy),
        Threaded(data, chunks),
        scratch_factory(scratch, threads, n_vertices, data.geo.dtype, block_spans(data.tets, chunks)),
    )


#: The threaded version of each serial force kernel, by the serial kernel's name.
THREADED = {
    "stvk_force": stvk_force_threaded,
    "neohookean_force": neohookean_force_threaded,
    "corotational_force": corotational_force_threaded,
    "linear_tm_force": linear_tm_force_threaded,
}
#: The unsummed version of each threaded force kernel, by the threaded kernel's name: what symplectic
#: Euler's loop calls, summing the threads' forces in its update (steppers.se_sum_update_threads).
UNSUMMED = {
    stvk_force_threaded.__name__: stvk_unsummed,
    neohookean_force_threaded.__name__: neohookean_unsummed,
    corotational_force_threaded.__name__: corotational_unsummed,
    linear_tm_force_threaded.__name__: linear_tm_unsummed,
}
