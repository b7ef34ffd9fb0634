"""The roofline of one core, measured on the machine the benchmark runs on, and each kernel's place on it.

A step cannot take less than the larger of its floating-point work at the core's peak rate and its
memory traffic at the bandwidth of the cache level its data lives in (Williams, Waterman & Patterson,
"Roofline", CACM 2009). Both ceilings are measured here, in the same run as the kernels, by two small
numba loops:

- ``fma_peak``: eight independent degree-16 polynomial chains per SIMD lane on an L1-resident array,
  Horner's rule, so that the loop is nothing but fused multiply-adds with enough independence to fill
  both FMA pipes. GFLOP/s, an FMA counted as two flops.
- ``bandwidth``: STREAM's triad a = b + s c (McCalpin), counted as STREAM counts it (24 bytes per
  element: read b and c, write a), on three arrays whose total size is the data a kernel touches in a
  step, so that the ceiling is that of the cache level (L2, L3 or memory) where that data lives.

The same two loops on every core at once (``thread_loops``, timed by the benchmark in the same rounds
as the threaded kernels; ``thread_scaling``) give what the machine itself gains from a second core:
the aggregate rate of T threads over one thread's, each thread its own chains, or its own slice of
the same triad arrays. A threaded kernel's speed-up is read beside that: a core that slows while the
other works (shared caches, memory, a host's other tenants) slows any code on it.

The work of each model's step (``step_work``) is counted from its kernel's source, per element, and
the update of symplectic Euler added (the benchmark times force and update together). Flops: + - *
and FMA halves, a square root or a division as one (they cost more: the count is a floor). Bytes:
the arrays streamed once per step (element geometry, tensors, connectivity, the integrator's per-dof
arrays, u, v and f); gathers of u and scatters to f that hit the cache again are not counted, so the
roofline is optimistic, as it should be: its fraction is an upper bound on what is left to gain.
"""

from __future__ import annotations

import time

import numba as nb
import numpy as np

from realtime.models import SPECS, stvk_tm

_FAST = dict(nogil=True, cache=True, fastmath=True)
#: fma_peak's independent chains per SIMD lane (enough FMAs in flight for two pipes of latency 4) and
#: the degree of each chain's polynomial (_horner).
_CHAINS = 8
_DEGREE = 16


@nb.njit(inline="always", **_FAST)
def _horner(v):
    """A degree-16 polynomial of v by Horner's rule: 16 dependent fused multiply-adds."""
    p = v * 0.5 + 0.25
    for _ in range(_DEGREE - 1):  # a constant trip count: LLVM unrolls it into the chain
        p = p * v + 0.25
    return p


@nb.njit(**_FAST)
def _polynomials(x, reps):
    """The sum over k = 0..7 and i of p(x[k, i]): eight independent chains in each iteration over i,
    which the compiler vectorises (a sum, not stores: eight output streams would need more run-time
    overlap checks than LLVM emits, and it would not vectorise), ``reps`` times."""
    acc = 0.0
    for _ in range(reps):
        for i in range(x.shape[1]):
            acc += (
                _horner(x[0, i]) + _horner(x[1, i]) + _horner(x[2, i]) + _horner(x[3, i])
                + _horner(x[4, i]) + _horner(x[5, i]) + _horner(x[6, i]) + _horner(x[7, i])
            )  # fmt: skip
    return acc


def fma_peak(seconds: float = 0.3) -> float:
    """The core's measured double-precision peak, GFLOP/s (best of several timed calls)."""
    x = np.full((_CHAINS, 64), 0.5)  # 4 kB: L1
    flops_per_rep = 2.0 * _DEGREE * x.size
    _polynomials(x, 1)
    reps = 1000
    best = np.inf
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        _polynomials(x, reps)
        best = min(best, (time.perf_counter() - t0) / reps)
    return flops_per_rep / best / 1e9


@nb.njit(**_FAST)
def _triad(a, b, c, s, reps):
    for _ in range(reps):
        for i in range(a.shape[0]):
            a[i] = b[i] + s * c[i]


@nb.njit(parallel=True, **_FAST)
def _polynomials_threads(x, reps):
    """_polynomials of each x[t] (T, 8, 64) on its own thread, all at once; the sum of their sums."""
    acc = 0.0
    for t in nb.prange(x.shape[0]):
        acc += _polynomials(x[t], reps)
    return acc


@nb.njit(parallel=True, **_FAST)
def _triad_threads(a, b, c, s, reps, parts):
    """_triad on ``parts`` threads at once, each a contiguous slice of the arrays (the ranges of
    threaded.sum_threads)."""
    n = a.shape[0]
    for p in nb.prange(parts):
        lo, hi = p * n // parts, (p + 1) * n // parts
        _triad(a[lo:hi], b[lo:hi], c[lo:hi], s, reps)


def thread_loops(threads: int, footprint_bytes: float) -> dict:
    """The ceilings' loops on one thread and on ``threads`` threads at once, to be timed in the same rounds
    as the kernels (their ratios are what the machine itself gains from the threads): name -> (call,
    work units a call). "fma 1" runs one thread's FMA chains, "fma T" T threads' each on its own chains
    (T times the work, so the units are chains); "triad 1" and "triad T" the triad on arrays of
    ``footprint_bytes`` in all, on one thread and split between T (the same work)."""
    x = np.full((threads, _CHAINS, 64), 0.5)
    n = max(int(footprint_bytes / 24), 1024 * threads)
    a, b, c = np.zeros(n), np.ones(n), np.ones(n)
    reps, treps = 1000, max(1, int(2e7 // n))
    return {
        "fma 1": (lambda: _polynomials(x[0], reps), 1),
        f"fma {threads}": (lambda: _polynomials_threads(x, reps), threads),
        "triad 1": (lambda: _triad(a, b, c, 0.5, treps), 1),
        f"triad {threads}": (lambda: _triad_threads(a, b, c, 0.5, treps, threads), 1),
    }


def thread_scaling(times: dict, threads: int) -> dict:
    """What ``threads`` threads gain over one, from the times (any unit, per work unit) of thread_loops'
    calls: "fma", the aggregate FMA rate, and "triad", the triad's speed on the same arrays."""
    return {
        "fma": times["fma 1"] / times[f"fma {threads}"],
        "triad": times["triad 1"] / times[f"triad {threads}"],
    }


def bandwidth(footprint_bytes: float, seconds: float = 0.2) -> float:
    """STREAM triad bandwidth, GB/s (24 bytes an element), on three arrays of ``footprint_bytes`` in all."""
    n = max(int(footprint_bytes / 24), 1024)
    a, b, c = np.zeros(n), np.ones(n), np.ones(n)
    _triad(a, b, c, 0.5, 1)
    reps = max(1, int(2e7 // n))
    best = np.inf
    end = time.perf_counter() + seconds
    while time.perf_counter() < end:
        t0 = time.perf_counter()
        _triad(a, b, c, 0.5, reps)
        best = min(best, (time.perf_counter() - t0) / reps)
    return 24.0 * n / best / 1e9


def vector_bits() -> int:
    """The widest vector registers numba emits in this process, bits (512, 256 or 128): the triad loop
    compiled afresh (numba shows no assembly for cached code) and its machine code read. The peak loop
    and the engine's kernels are compiled for the same target (realtime.target), so this is the width
    both the ceiling and the kernels were measured at."""
    loop = nb.njit(**{**_FAST, "cache": False})(_triad.py_func)
    a = np.zeros(64)
    loop(a, a, a, 0.5, 1)
    asm = loop.inspect_asm(loop.signatures[0])
    return next((bits for bits, reg in ((512, "%zmm"), (256, "%ymm")) if reg in asm), 128)


#: Per-element work of a force kernel, counted from its source, is its ModelSpec's ``work``: (flops,
#: streamed bytes) per tetrahedron ("tet"), vertex ("vertex") or edge ("edge"), each counted in the
#: model's file. scipy's BSR product: 18 flops and 80 bytes (block, column index) a 3x3 block.
#: stvk-tm's force in its two phases (the bench's rows "stvk-tm, element arithmetic alone" and
#: "stvk-tm, gather and scatter alone"), per tetrahedron: the element arithmetic is its spec's work's
#: flops less the gather's 9 and the scatter's 18, on the geometry rows the isotropic loop reads; the
#: gather and the scatter are those 27 flops and the 4 int64 indices, and read u and write f once a
#: vertex (VERTEX_STATE_BYTES, added per vertex). The indexed loads and stores of u and f (12 and 24
#: a tetrahedron, from the caches) are in neither count: the second row's fraction shows what they cost.
_STVK_INDEXED = (27.0, 32.0)  # the gather's and the scatter's flops, the 4 int64 indices
STVK_PHASE_WORK = {
    "arithmetic": tuple(w - i for w, i in zip(SPECS[stvk_tm.NAME].work["tet"], _STVK_INDEXED, strict=True)),
    "gather and scatter": _STVK_INDEXED,
}


def stvk_phase_work(phase: str, n_vertices: int, n_tets: int) -> tuple[float, float]:
    """(flops, bytes) of one pass of ``phase`` (a key of STVK_PHASE_WORK) of stvk-tm's force."""
    flops, nbytes = STVK_PHASE_WORK[phase]
    state = VERTEX_STATE_BYTES * n_vertices if phase == "gather and scatter" else 0.0
    return flops * n_tets, nbytes * n_tets + state


#: Symplectic Euler's update per vertex: 3 components of (2 FMA + 3 mul/add) flops; bytes: the per-dof
#: table (3 float64), u and v read and written, f read: (3 + 2 + 2 + 1) x 8 x 3.
UPDATE_WORK = (3 * 7.0, 3 * 8 * 8.0)
#: Bytes of u and f a force evaluation reads and writes once per vertex.
VERTEX_STATE_BYTES = 48.0


def step_work(model_name: str, n_vertices: int, n_tets: int, n_edges: int) -> tuple[float, float] | None:
    """(flops, bytes) of one symplectic Euler step of ``model_name``, or None where the work is not a
    fixed count (corotational-tm's polar iterations, hybrid-tm's non-linear share)."""
    work = SPECS[model_name].work if model_name in SPECS else None
    if not work:
        return None
    counts = {"tet": n_tets, "vertex": n_vertices, "edge": n_edges}
    flops = sum(f * counts[k] for k, (f, _) in work.items()) + UPDATE_WORK[0] * n_vertices
    nbytes = sum(b * counts[k] for k, (_, b) in work.items())
    nbytes += (VERTEX_STATE_BYTES + UPDATE_WORK[1]) * n_vertices
    return flops, nbytes


def bsr_work(n_blocks: int, n_vertices: int) -> tuple[float, float]:
    """(flops, bytes) of scipy's BSR product y = K x with ``n_blocks`` 3x3 blocks."""
    return 18.0 * n_blocks, 80.0 * n_blocks + 48.0 * n_vertices


class Roofline:
    """The measured ceilings of one core: ``peak`` GFLOP/s and a bandwidth (GB/s) per footprint."""

    def __init__(self):
        self.peak = fma_peak()
        self.vector_bits = vector_bits()
        self._bandwidths: dict[int, float] = {}

    def bandwidth(self, footprint: float) -> float:
        """Triad bandwidth, GB/s, for data of ``footprint`` bytes (measured once per power of two)."""
        key = int(2 ** round(np.log2(max(footprint, 1024.0))))
        if key not in self._bandwidths:
            self._bandwidths[key] = bandwidth(key)
        return self._bandwidths[key]

    def bound_us(self, flops: float, nbytes: float) -> tuple[float, str]:
        """The least time, microseconds, of a step with this work, and which ceiling sets it."""
        compute = flops / (self.peak * 1e3)
        memory = nbytes / (self.bandwidth(nbytes) * 1e3)
        return (compute, "compute") if compute >= memory else (memory, "memory")

    def summary(self) -> dict:
        return {
            "fma_gflops": self.peak,
            "vector_bits": self.vector_bits,
            "triad_gbs": {str(k): v for k, v in sorted(self._bandwidths.items())},
        }
