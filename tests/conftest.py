"""Shared fixtures. Tests use a private reference cache so that no stale entry can mask a change."""

from __future__ import annotations

import numpy as np
import pytest

from verification.cli import quiet_compilers

quiet_compilers()  # FFCx's JIT logs its compiler calls at INFO


def _has_fma() -> bool:
    from llvmlite import binding as llvm

    features = llvm.get_host_cpu_features()
    return bool(features.get("avx2") and features.get("fma"))


#: For tests that read the packed instructions of compiled loops.
needs_fma = pytest.mark.skipif(not _has_fma(), reason="this CPU has no AVX2/FMA: nothing to vectorise to")


#: Scenes whose P2 reference (with its estimate) and P1 solution the suite's studies ask for (compare,
#: sweep, advise, gate, report); with the stability study's variants of the cantilever they are solved
#: ahead, on all cores, when the session runs slow tests.
SUITE_REFERENCES = ("cantilever", "cantilever-pull", "cantilever-dynamic", "block-press", "block-twist")
_SESSION = {"slow": False}
#: A clamped 6 cm StVK beam whose free end a tool pushes 1 cm down over 10 ms (no gravity or traction):
#: the Newmark tests' scene (append a [time] table for a dynamic one).
SWING = """
name = "swing"
[mesh]
generator = "box"
size = [0.06, 0.01, 0.01]
h = 0.005
[material]
law = "stvk"
young = 5.0e5
poisson = 0.3
density = 1000.0
[[fixed]]
box = [[-1e-9, -1.0, -1.0], [1e-9, 1.0, 1.0]]
[[load]]
kind = "displacement"
box = [[0.0599999, -1.0, -1.0], [1.0, 1.0, 1.0]]
value = [0.0, 0.0, -0.01]
ramp = 0.01
"""


def pytest_collection_modifyitems(config, items):
    """Tests marked run_last go after all the others (they inspect what the whole session loaded)."""
    items.sort(key=lambda item: item.get_closest_marker("run_last") is not None)


def pytest_collection_finish(session):
    """Whether any slow test is left after -k and -m deselected theirs (modifyitems sees them all)."""
    _SESSION["slow"] = any(item.get_closest_marker("slow") is not None for item in session.items)


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("TISSUEBENCH_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield
    mp.undo()


@pytest.fixture(scope="session", autouse=True)
def references_ahead(private_cache):
    """The suite's references solved first, one process per core, into the session's private cache (as
    ``tissuebench report`` does): what the tests then find there is what they would have solved, and a
    test that checks a solve itself asks for its own (``use_cache=False`` or a scene of its own)."""
    if not _SESSION["slow"]:
        return
    from verification.prefetch import scene_jobs, solve_references
    from verification.scene import load_scene
    from verification.stability import FAILED_REFERENCES, reference_jobs

    jobs = scene_jobs([load_scene(name) for name in SUITE_REFERENCES]) + reference_jobs(load_scene("cantilever"))
    FAILED_REFERENCES.update(solve_references(jobs))


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def match_nodes(coords: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index into ``coords`` (dolfinx P1 node order) of each of ``points``; asserts exact matches."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(coords).query(points)
    assert d.max() < 1e-12 * max(1.0, float(np.abs(points).max()))
    return idx


def assert_same_model(a, b, rng, rtol: float = 1e-12) -> None:
    """Two models on one vertex set agree: internal forces for a random displacement (1 mm) to ``rtol``
    of the largest, masses and constraints on the vertices b's tetrahedra use (two sums of the same
    terms in another order: round-off)."""
    assert a.n_vertices == b.n_vertices
    u = 1e-3 * rng.standard_normal((a.n_vertices, 3))
    f = b.internal_force(u)
    assert np.abs(a.internal_force(u) - f).max() <= rtol * np.abs(f).max()
    used = np.unique(b.tets)
    np.testing.assert_allclose(a.mass[used], b.mass[used], rtol=rtol)
    assert np.array_equal(a.loading.free[used], b.loading.free[used])
