"""The benchmark's machinery (never its speed: `make bench` reports that): the roofline it measures and
the table it prints."""

import re

import numpy as np
import pytest


def test_the_fma_peak_loop_is_packed_fused_multiply_adds():
    """The roofline's compute ceiling is only a ceiling if its loop runs at the SIMD peak: a scalar loop
    would measure a quarter of it or less and make every kernel look near its bound (the first version
    stored eight outputs a lane, LLVM declined to vectorise it, and the "peak" was 13 GFLOP/s against
    107)."""
    import numba
    from llvmlite import binding as llvm

    from verification import roofline

    features = llvm.get_host_cpu_features()
    if not (features.get("avx2") and features.get("fma")):
        pytest.skip("this CPU has no AVX2/FMA: nothing to vectorise to")
    kernel = numba.njit(**{**roofline._FAST, "cache": False})(roofline._polynomials.py_func)
    kernel(np.full((roofline._CHAINS, 64), 0.5), 1)
    asm = kernel.inspect_asm(kernel.signatures[0])
    packed = len(re.findall(r"vfmadd\w*pd\s+%[yz]mm", asm))
    assert packed >= roofline._CHAINS * roofline._DEGREE, f"{packed} packed FMAs in the peak loop"


def test_the_benchmark_places_every_fixed_work_row_on_the_roofline():
    """A short benchmark on the stored beam: the rows whose work is a fixed count (linear-tm, stvk-tm,
    mass-spring, scipy's product) carry their flops, bytes, bound and achieved fraction, and the table
    prints them beside the measured ceilings; the others carry none."""
    from verification.bench import format_table, run

    out = run(meshes=("beam",), repeats=1, steps=2)
    roof = out["machine"]["roofline"]
    assert roof["fma_gflops"] > 0 and all(v > 0 for v in roof["triad_gbs"].values())
    rows = {r["name"]: r for r in out["results"]}
    haptic = {f"{m}, one step a call (haptic loop)" for m in ("linear-tm", "stvk-tm")}
    placed = {"linear-tm", "stvk-tm", "mass-spring", "scipy-bsr-matvec"} | haptic
    for name in placed:
        r = rows[name]
        assert (
            r["flops"] > 0 and r["bytes"] > 0 and r["roofline_us"] > 0 and r["roofline_limit"] in ("compute", "memory")
        )
        assert r["roofline_fraction"] == pytest.approx(r["roofline_us"] / r["step_us"])
    assert "roofline_us" not in rows["corotational-tm"] and "roofline_us" not in rows["stvk-tm (transverse + penalty)"]
    table = format_table(out)
    assert "FMA peak" in table and "triad GB/s by data size" in table
    assert len(re.findall(r"roofline [\d.]+ us \((compute|memory)\): \d+% of it", table)) == len(placed)
