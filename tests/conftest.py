"""Shared fixtures. Tests use a private reference cache so that no stale entry can mask a change."""

from __future__ import annotations

import numpy as np
import pytest

from verification.cli import quiet_compilers

quiet_compilers()  # FFCx's JIT logs its compiler calls at INFO


def pytest_collection_modifyitems(config, items):
    """Tests marked run_last go after all the others (they inspect what the whole session loaded)."""
    items.sort(key=lambda item: item.get_closest_marker("run_last") is not None)


@pytest.fixture(scope="session", autouse=True)
def private_cache(tmp_path_factory):
    mp = pytest.MonkeyPatch()
    mp.setenv("TISSUEBENCH_CACHE", str(tmp_path_factory.mktemp("cache")))
    yield
    mp.undo()


@pytest.fixture
def rng():
    return np.random.default_rng(20261122)


def match_nodes(coords: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Index into ``coords`` (dolfinx P1 node order) of each of ``points``; asserts exact matches."""
    from scipy.spatial import cKDTree

    d, idx = cKDTree(coords).query(points)
    assert d.max() < 1e-12 * max(1.0, float(np.abs(points).max()))
    return idx
