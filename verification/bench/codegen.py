"""What the engine's hot loops compile to on this machine: reported by `make bench`, never asserted.

The engine's speed rests on LLVM vectorising a few loops (stvk-tm's element loop across tetrahedra, the
threads' sum of forces, the roofline's FMA peak loop) and on indexed loops that neither wrap signed
indices nor multiply by run-time strides. How many packed instructions a loop compiles to depends on
the target (AVX2 or AVX-512, which Zen or Xeon generation), on LLVM's version and its cost model: on an
AMD EPYC with AVX2 the isotropic StVK loop held more packed instructions than the general one, where a
Xeon with AVX-512 had half as many. So the counts are measurements of this machine, stated beside the
timings they explain (a loop that stopped vectorising shows as a count near zero and a slower row), not
properties a test can demand of every machine a user has.

Each function is compiled afresh (numba shows no assembly for cached code) for numba's target in this
process (``NUMBA_CPU_NAME``/``NUMBA_CPU_FEATURES`` choose another).
"""

from __future__ import annotations

import functools
import re

import numba
import numpy as np

from realtime.models import linear_tm, mass_spring, stvk_tm

#: A packed double-precision instruction on 256- or 512-bit registers (AT&T syntax: the register last).
PACKED = r"\bv\w+pd\s+[^\n]*%[yz]mm"
PACKED_FMA = r"\bvfmadd\w*pd\s+[^\n]*%[yz]mm"
PACKED_ADD = r"\bvaddpd\s+[^\n]*%[yz]mm"
#: numba's wrap-around of a negative signed index (its sign by an arithmetic shift of 63) and an array
#: indexed by its run-time strides (a multiplication).
SIGN_SHIFT = r"\bsar[ql]?\s+\$63,"
STRIDE_MUL = r"\bimul[ql]?\b"


def _count(pattern: str, asm: str) -> int:
    return len(re.findall(pattern, asm))


def _fresh(fn, hot: dict):
    return numba.njit(**{**hot, "cache": False})(fn.py_func)


def _asm(dispatcher) -> str:
    return dispatcher.inspect_asm(dispatcher.signatures[0])


def fma_peak_loop() -> dict:
    """The roofline's peak loop: packed FMAs against the chains x degree it must issue to be a peak."""
    from verification.bench import roofline

    kernel = _fresh(roofline._polynomials, roofline._FAST)
    kernel(np.full((roofline._CHAINS, 64), 0.5), 1)
    return {"packed_fma": _count(PACKED_FMA, _asm(kernel)), "expected_at_least": roofline._CHAINS * roofline._DEGREE}


@functools.cache
def _force_asm(name: str) -> str:
    """The machine code of a model's force kernel (``name``: linear-tm, stvk-tm or mass-spring), compiled
    afresh on a small beam; once per process, as two counts read the same stvk-tm force."""
    return _asm(_force_kernel(name))


def _force_kernel(name: str):
    """A model's force kernel compiled afresh and run once on a small beam (its types are then known)."""
    import importlib

    from meshes import structured_box
    from realtime import Material, blocks, build_model

    module, fn = FORCE_KERNELS[name].split(".")
    mesh = structured_box((0.04, 0.01, 0.01), (4, 1, 1))
    compiled = _fresh(getattr(importlib.import_module(f"realtime.{module}"), fn), blocks.HOT)
    model = build_model(name, mesh.points, mesh.tets, Material(1e4, 0.3, 1000.0, law="stvk"))
    compiled(model.data, model.new_scratch(), np.zeros_like(mesh.points), np.zeros_like(mesh.points))
    return compiled


def signed_indexing(dispatcher) -> list[str]:
    """Every array access of a compiled function (its inlined helpers included) whose index numba typed
    as a signed integer, as "file:line: source": numba wraps such an index around when negative, at
    every access. Read from numba's typed IR, which is the same on every target, unlike the machine
    code the wrap-around compiles to."""
    import linecache
    from pathlib import Path

    from numba.core import ir, types

    out = set()
    for sig in dispatcher.signatures:
        calltypes = dispatcher.overloads[sig].type_annotation.calltypes
        for expr, called in calltypes.items():
            access = isinstance(expr, ir.SetItem) or (isinstance(expr, ir.Expr) and expr.op == "getitem")
            if not access or called is None or len(called.args) < 2:
                continue
            array, index = called.args[0], called.args[1]
            if isinstance(array, types.Array) and isinstance(index, types.Integer) and index.signed:
                source = linecache.getline(expr.loc.filename, expr.loc.line).strip()
                out.add(f"{Path(expr.loc.filename).name}:{expr.loc.line}: {source}")
    return sorted(out)


#: Each model's force kernel, module.function in realtime.
FORCE_KERNELS = {
    linear_tm.NAME: "tensor_mass.linear_tm_force",
    stvk_tm.NAME: "stvk.stvk_force",
    mass_spring.NAME: "springs.spring_force",
}


def stvk_loops() -> dict:
    """stvk-tm's force (packed FMAs) and its element loop compiled alone for an isotropic block and a
    general one (fibres and the penalty: packed double instructions of each)."""
    from realtime import blocks, stvk

    def lanes(general: bool) -> int:
        @numba.njit(**{**blocks.HOT, "cache": False})
        def loop(W, geo, prm):
            stvk._stvk_lanes(W, geo, np.uint64(0), prm, False, general)

        loop(np.zeros(9 * blocks.BLOCK), np.zeros(blocks.GEO_ROWS * blocks.BLOCK), np.zeros(5))
        return _count(PACKED, _asm(loop))

    return {
        "force_packed_fma": _count(PACKED_FMA, _force_asm(stvk_tm.NAME)),
        "isotropic_packed": lanes(False),
        "general_packed": lanes(True),
    }


def threads_sum() -> dict:
    """The threads' sum of forces (threaded.sum_range): its packed additions."""
    from realtime import blocks, threaded

    @numba.njit(**{**blocks.HOT, "cache": False})
    def summed(spans, F, f, lo, hi):
        threaded.sum_range(spans, F, f, lo, hi)

    summed(np.array([[0, 200], [150, 300]]), np.ones((2, 900)), np.zeros(900), 0, 900)
    return {"packed_add": _count(PACKED_ADD, _asm(summed))}


def indexed_loops() -> dict:
    """linear-tm's, stvk-tm's and mass-spring's force kernels: the sign shifts and multiplications of
    numba's signed, strided indexing left in their machine code (at most 1 and 3 of each, outside the
    loops, on the Xeon where the unsigned flat views were written; 11 to 33 and 23 to 35 before)."""
    out = {}
    for name in FORCE_KERNELS:
        asm = _force_asm(name)
        out[name] = {"sign_shifts": _count(SIGN_SHIFT, asm), "stride_multiplications": _count(STRIDE_MUL, asm)}
    return out


def report() -> dict:
    """Every count above, with numba's target (CPU name and features) they were compiled for."""
    from numba.core import config

    target = config.CPU_NAME or "host"
    return {
        "target": target,
        "features": config.CPU_FEATURES or "host",
        "fma_peak_loop": fma_peak_loop(),
        "stvk": stvk_loops(),
        "threads_sum": threads_sum(),
        "indexed_loops": indexed_loops(),
    }


def format_report(r: dict) -> str:
    s, peak = r["stvk"], r["fma_peak_loop"]
    lines = [
        f"compiled code (numba target {r['target']}):",
        f"  FMA peak loop: {peak['packed_fma']} packed FMAs ({peak['expected_at_least']} make it a peak)",
        f"  stvk-tm force: {s['force_packed_fma']} packed FMAs; element loop, packed instructions: "
        f"isotropic {s['isotropic_packed']}, general {s['general_packed']}",
        f"  threads' sum of forces: {r['threads_sum']['packed_add']} packed additions",
    ]
    for name, c in r["indexed_loops"].items():
        lines.append(
            f"  {name} force: {c['sign_shifts']} signed-index shifts, {c['stride_multiplications']} stride multiplications"
        )
    return "\n".join(lines)
