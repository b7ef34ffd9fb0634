"""numba's on-disk cache of the engine, shared by processes that compile at once (realtime/jitcache.py)."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: Builds the models named in argv on a small beam, steps each 50 times under a pull with symplectic
#: Euler (one step loop, specialised per force kernel: several keys in one cache index), and prints
#: each final displacement's bytes as hex, and how many specialisations numba loaded from its cache.
#: Saving the step loop's index pauses WIDEN seconds after numba has read the index and chosen a data
#: file, as a slow disk or a loaded host would: the window in which another process's save collides.
CHILD = r"""
import json, sys, time
import numpy as np
from numba.core import caching

_save_index = caching.IndexDataCacheFile._save_index


def slow_save_index(self, overloads):
    if "_run_symplectic_euler" in self._index_name:
        time.sleep(WIDEN)
    _save_index(self, overloads)


caching.IndexDataCacheFile._save_index = slow_save_index
from meshes import structured_box
from realtime import Loading, Material, State, SymplecticEuler, build_model
from realtime import steppers

mesh = structured_box((0.04, 0.01, 0.01), (4, 1, 1))
n = mesh.n_vertices
free = np.ones((n, 3))
free[mesh.points[:, 0] < 1e-9] = 0.0
out = {}
for name in sys.argv[1:]:
    model = build_model(name, mesh.points, mesh.tets, Material(1e5, 0.3, 1000.0),
                        Loading(free=free, external_force=np.zeros((n, 3))))
    integ = SymplecticEuler(alpha=10.0)
    integ.set_forces(model, model.mass[:, None] * np.array([0.0, 0.0, -9.81]))
    state = State.at_rest(n)
    integ.step(model, state, 0.2 * integ.critical_dt(model), 50)
    out[name] = state.u.tobytes().hex()
out["hits"] = sum(steppers._run_symplectic_euler.stats.cache_hits.values())
out["misses"] = sum(steppers._run_symplectic_euler.stats.cache_misses.values())
print(json.dumps(out))
"""

#: Three force kernels, so three keys in the step loop's index; neohookean-tm's compiles in a third of
#: stvk-tm's time (a cold process: 7 s against 11 s here), and the collision is the index's, not a kernel's.
MODELS = ("linear-tm", "mass-spring", "neohookean-tm")
#: The pause (s) in the step loop's index saves: longer than the spread of the four processes' saves.
WIDEN = 2.0


def _start(cache: Path, models) -> subprocess.Popen:
    env = {**os.environ, "NUMBA_CACHE_DIR": str(cache)}
    return subprocess.Popen(
        [sys.executable, "-c", CHILD.replace("WIDEN", repr(WIDEN)), *models],
        cwd=ROOT,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )


def _result(proc: subprocess.Popen) -> dict:
    out, err = proc.communicate(timeout=900)
    assert proc.returncode == 0, err[-3000:]
    return json.loads(out.strip().splitlines()[-1])


@pytest.mark.slow
def test_four_cold_processes_compiling_at_once_leave_a_cache_a_fifth_reads_right(tmp_path):
    """Four processes start on an empty cache at once, each compiling the step loop for other force
    kernels, in another order. numba saves a new specialisation by reading the index, taking the first
    free data file number and writing both: two processes doing so at once gave their two keys the same
    data file, each writing an index of its own key alone: specialisations were lost, or their key
    named another's machine code, and every later process compiled them again. realtime.jitcache
    serialises the saves across processes. The window is widened (WIDEN) so that the saves of the four
    processes overlap. A fifth process, started after them, must find every step loop specialisation in
    the cache (none compiled again) and reproduce every run's displacement bit for bit."""
    cache = tmp_path / "numba-cache"
    orders = [MODELS, MODELS[::-1], MODELS[1:] + MODELS[:1], MODELS[2:] + MODELS[:2]]
    first = [_result(p) for p in [_start(cache, order) for order in orders]]
    for name in MODELS:
        assert len({r[name] for r in first}) == 1, f"{name}: the four processes disagree"
    fifth = _result(_start(cache, MODELS))
    assert (fifth["hits"], fifth["misses"]) == (len(MODELS), 0), f"step loops lost from the cache: {fifth}"
    for name in MODELS:
        assert fifth[name] == first[0][name], f"{name}: the cached step loop ran another computation"


def test_two_saves_into_one_index_at_once_keep_both_entries_each_with_its_own_data(tmp_path, monkeypatch):
    """numba's save of a cache entry, made by two savers at once (separate open files, as two processes
    have): the second starts while the first has read the index and not yet written it. Unserialised,
    both took data file 1 and each wrote an index of its own key alone, so one entry was lost and the
    data file held the other's code; under realtime.jitcache's lock the second reads the index after the
    first wrote it, and both entries survive, each naming its own data."""
    import threading
    import time

    from numba.core import caching

    from realtime import jitcache

    jitcache.serialise_saves()  # as realtime's import did
    save_index = caching.IndexDataCacheFile._save_index

    def slow(self, overloads):  # between reading the index and writing it
        time.sleep(0.3)
        save_index(self, overloads)

    monkeypatch.setattr(caching.IndexDataCacheFile, "_save_index", slow)

    def saver(key):
        caching.IndexDataCacheFile(str(tmp_path), "f", "stamp").save(key, f"code of {key}")

    threads = [threading.Thread(target=saver, args=(k,)) for k in ("a", "b")]
    threads[0].start()
    time.sleep(0.1)
    threads[1].start()
    for t in threads:
        t.join()
    index = caching.IndexDataCacheFile(str(tmp_path), "f", "stamp")
    assert index.load("a") == "code of a" and index.load("b") == "code of b"
