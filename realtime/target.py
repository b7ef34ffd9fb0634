"""The vector width the engine's kernels are compiled for: all the core has.

LLVM, numba's compiler, tunes code for Intel cores with AVX-512 (Skylake-SP to Sapphire Rapids; LLVM 14
takes the Xeon measured below for "icelake-client") to prefer 256-bit vectors: their early generations
lowered the clock for 512-bit code. The element kernels' lane loops and the roofline's peak loop then
ran at half the core's width. On the 2-core Xeon with AVX-512 where this was measured (median of
four fresh processes each, liver, force alone), 512-bit code made stvk-tm's force 93 -> 77 us and
corotational-tm's 174 -> 145 us; linear-tm and mass-spring, whose loops are indexed loads and
stores, did not change; and the FMA peak measured by verification.roofline went 46 -> 76 GFLOP/s, so
the roofline had put every compute-bound kernel twice as close to the machine's ceiling as it was.

``use_wide_vectors`` lifts that preference by numba's own setting (NUMBA_CPU_FEATURES: the host's
features plus "-prefer-256-bit"). numba fixes its target when it makes its first function (at
decoration), so this module calls it when imported, and ``realtime`` imports it before any of its
modules that make one; in a process that made a numba function before importing realtime, the
kernels keep 256-bit vectors (correct, slower). A user's own NUMBA_CPU_FEATURES or NUMBA_CPU_NAME is
left as it is; a core without AVX-512 has nothing to change.
The setting goes into the environment when numba is not loaded yet, so that numba reads it with the
rest and the processes the engine starts (realtime.precompile's pool, the studies' workers) inherit it;
with numba loaded, into numba's config alone (see use_wide_vectors).
"""

from __future__ import annotations

import os
import sys

FEATURES_VAR = "NUMBA_CPU_FEATURES"
#: Variables by which the user chose numba's target themselves.
USER_VARS = (FEATURES_VAR, "NUMBA_CPU_NAME")


def wide_vector_features() -> str | None:
    """numba's CPU feature string for this host with LLVM's preference for 256-bit vectors removed, or
    None where the core has no AVX-512 (or LLVM cannot tell its features)."""
    import llvmlite.binding as ll

    try:
        features = ll.get_host_cpu_features()
    except RuntimeError:
        return None
    if not features.get("avx512f"):
        return None
    return features.flatten() + ",-prefer-256-bit"


def use_wide_vectors() -> str | None:
    """Compile numba's code in this process and its children for the core's full vector width
    (wide_vector_features), unless the user chose the target (USER_VARS). Returns the features set,
    or None when nothing was changed."""
    if any(v in os.environ for v in USER_VARS):
        return None
    features = wide_vector_features()
    if features is None:
        return None
    config = sys.modules.get("numba.core.config")
    if config is None:
        os.environ[FEATURES_VAR] = features
    else:
        # numba is loaded and has read the environment: a NUMBA_ variable changed now would make its
        # next compile read them all again, undoing settings made in code since (the threading layer)
        config.CPU_FEATURES = features
    return features


use_wide_vectors()
