"""Shared fixtures. Tests use a private reference cache so that no stale entry can mask a change."""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path

import numpy as np
import pytest

import verification  # noqa: F401  (its import keeps FFCx's compiler calls off stderr: quiet_compilers)

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


def _xdist_worker(config) -> bool:
    """Whether this process is one of pytest-xdist's workers (``make test`` runs the suite on one per core)."""
    return hasattr(config, "workeroutput")


def pytest_collection_modifyitems(config, items):
    """Tests marked run_last go after all the others (they inspect what the whole session loaded).

    On xdist's workers each process loads only the modules of its own share of the tests, so the run_last
    check of the Debian packages leaves the workers: each reports what it loaded (pytest_sessionfinish)
    and the controller checks all of it once every worker is done (_check_workers_packages)."""
    items.sort(key=lambda item: item.get_closest_marker("run_last") is not None)
    if _xdist_worker(config):
        checks = [item for item in items if item.get_closest_marker("run_last") is not None]
        if checks:
            config.hook.pytest_deselected(items=checks)
            items[:] = [item for item in items if item not in checks]
            config.workeroutput["package_check"] = True


def pytest_collection_finish(session):
    """Whether any slow test is left after -k and -m deselected theirs (modifyitems sees them all)."""
    _SESSION["slow"] = any(item.get_closest_marker("slow") is not None for item in session.items)


#: What each xdist worker loaded from outside the venv (debian_packages.loaded_files), by worker, as the
#: controller received it.
_WORKER_FILES: dict[str, dict[str, list[str]]] = {}


def pytest_sessionfinish(session, exitstatus):
    """A worker hands what it loaded to the controller; the controller, once all have ended, checks it."""
    config = session.config
    if _xdist_worker(config):
        if config.workeroutput.get("package_check"):
            from .house.debian_packages import loaded_files

            config.workeroutput["loaded_files"] = loaded_files()
    elif _WORKER_FILES:
        _check_workers_packages(session)


@pytest.hookimpl(optionalhook=True)
def pytest_testnodedown(node, error):
    """(xdist's controller) a worker ended: keep what it loaded."""
    files = getattr(node, "workeroutput", {}).get("loaded_files")
    if files is not None:
        _WORKER_FILES[node.gateway.id] = files


def _check_workers_packages(session) -> None:
    """tests/house/test_debian_packages.py's run_last check on the union of what every worker loaded: a
    package missing from the Makefile fails the session with one line naming it."""
    from .house.debian_packages import MAKEFILE, missing_packages

    union: dict[str, set[str]] = {}
    for files in _WORKER_FILES.values():
        for path, names in files.items():
            union.setdefault(path, set()).update(names)
    makefile = Path(os.environ.get("TISSUEBENCH_CHECKED_MAKEFILE", MAKEFILE))  # the check's own test
    missing = missing_packages(makefile, files={path: sorted(names) for path, names in union.items()})
    if missing:
        line = "loaded from Debian packages that the Makefile does not install: " + "; ".join(
            f"{pkg} ({', '.join(mods[:4])})" for pkg, mods in missing.items()
        )
        reporter = session.config.pluginmanager.get_plugin("terminalreporter")
        reporter.write_line(f"\nFAILED the workers' Debian package check: {line}", red=True, bold=True)
        session.exitstatus = pytest.ExitCode.TESTS_FAILED


@pytest.fixture(scope="session")
def run_dir(request, tmp_path_factory) -> Path:
    """A folder of this test run's: the session's own, or, on xdist's workers, the one they all share."""
    base = tmp_path_factory.getbasetemp()
    return base.parent if _xdist_worker(request.config) else base


@pytest.fixture(scope="session", autouse=True)
def private_cache(run_dir):
    """The run's own reference and run cache, which xdist's workers share (each write is a rename)."""
    mp = pytest.MonkeyPatch()
    cache = run_dir / "cache"
    cache.mkdir(exist_ok=True)
    mp.setenv("TISSUEBENCH_CACHE", str(cache))
    yield
    mp.undo()


@pytest.fixture(scope="session", autouse=True)
def references_ahead(private_cache, run_dir):
    """The suite's references solved first, one process per core, into the run's private cache (as
    ``tissuebench report`` does): what the tests then find there is what they would have solved, and a
    test that checks a solve itself asks for its own (``use_cache=False`` or a scene of its own).

    Under xdist the first worker to get here solves them while the others wait on the lock (the solve
    takes every core), then each reads which ones failed from the file the solver left."""
    if not _SESSION["slow"]:
        return
    from verification.scene_file import load_scene
    from verification.studies.prefetch import scene_jobs, solve_references
    from verification.studies.stability import FAILED_REFERENCES, reference_jobs

    done = run_dir / "references-ahead.json"
    with open(run_dir / "references-ahead.lock", "w") as lock:
        fcntl.flock(lock, fcntl.LOCK_EX)
        if not done.exists():
            scenes = [load_scene(name) for name in SUITE_REFERENCES]
            jobs = scene_jobs(scenes) + reference_jobs(load_scene("cantilever"))
            failed = solve_references(jobs)
            tmp = done.with_suffix(".tmp")
            tmp.write_text(json.dumps(failed))
            tmp.rename(done)
        FAILED_REFERENCES.update(json.loads(done.read_text()))


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
