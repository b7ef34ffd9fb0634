"""realtime.target: the engine's kernels and the roofline's peak compiled for the core's full vector
width; what a new process compiles for is checked in one (numba fixes its target once per process)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
from llvmlite import binding as llvm

ROOT = Path(__file__).resolve().parents[2]

#: Prints the features numba was given and what realtime.target computes for this host.
CHILD = r"""
import json
import realtime
import numba
from realtime import target

print(json.dumps({"features": numba.core.config.CPU_FEATURES, "wide": target.wide_vector_features()}))
"""


def run_child(*args, **env_vars) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("NUMBA_CPU_FEATURES", "NUMBA_CPU_NAME")}
    env.update(env_vars)
    out = subprocess.run(
        [sys.executable, "-c", CHILD, *args], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600
    )
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("avx512", [True, False])
def test_the_256_bit_preference_is_lifted_on_cores_with_avx512_and_only_there(monkeypatch, avx512):
    """LLVM tunes Intel's AVX-512 cores to prefer 256-bit vectors; the engine lifts that
    (realtime.target), so that its kernels and the roofline's peak run at the core's width (the peak read
    46 GFLOP/s at 256 bits on the Xeon where this was written, 76 at 512). A core without AVX-512 keeps
    LLVM's choice. Both cores are posed here (LLVM's feature map of a host with and without avx512f),
    so the rule is checked on every machine; which width a kernel then compiles to is reported by
    make bench (verification.bench.codegen)."""
    import llvmlite.binding as ll
    from numba.core import config

    from realtime import target

    host = ll.targets.FeatureMap({"avx2": True, "fma": True, "avx512f": avx512})
    monkeypatch.setattr(ll, "get_host_cpu_features", lambda: host)
    for var in target.USER_VARS:
        monkeypatch.delenv(var, raising=False)
    monkeypatch.setattr(config, "CPU_FEATURES", config.CPU_FEATURES)  # restored after the test
    chosen = target.use_wide_vectors()
    if avx512:
        assert chosen == host.flatten() + ",-prefer-256-bit" and config.CPU_FEATURES == chosen
    else:
        assert chosen is None and target.wide_vector_features() is None


def test_a_fresh_process_compiles_for_the_features_the_engine_chose():
    """realtime sets its target when imported, before numba makes its first function, so a new process
    (precompile's pool, the studies' workers) compiles for it: the host's features with the 256-bit
    preference lifted on a core with AVX-512, numba's own choice elsewhere."""
    r = run_child()
    if r["wide"] is None:
        assert not r["features"]
    else:
        assert r["features"] == r["wide"]


def test_a_users_own_numba_target_is_left_alone():
    """NUMBA_CPU_FEATURES set by the user (here: the host's features, with LLVM's own tuning) is what numba
    compiles for after the engine is imported; on a core with AVX-512 the engine would have changed it."""
    features = llvm.get_host_cpu_features().flatten()
    assert run_child(NUMBA_CPU_FEATURES=features)["features"] == features
