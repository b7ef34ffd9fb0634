"""Compile the engine's kernels into numba's on-disk cache ahead of the first run, on every core.

numba compiles a function the first time it is called and, with ``cache=True``, keeps the machine code
beside the sources. The engine's step loops are compiled once per force kernel they take, with that
kernel re-optimised inside each, so that a process that steps every model pays about three minutes of
compilation on one core before its first result (measured on a 2-core AMD EPYC: 200 s of the test
suite's 650, all in one process). This module does that work once, after an install or an upgrade,
with one process per core: each builds a few models on a two-cube mesh of its own and calls what a run
calls (every integrator's ``step``, the critical step, the energy), which compiles and caches them.
A process that imports the engine afterwards loads the machine code instead.

Run it as ``python -m realtime.precompile`` (``make`` does it during set-up). It returns at once when
the cache already holds this version of the engine (a stamp of the sources, ``jitcache``); progress goes
to stderr. numba's index of a function's cached specialisations is read and rewritten by whichever
process saves one, so two processes saving specialisations of one step loop at the same moment can lose
one of them: a last pass in this process calls everything again, which compiles whatever is missing.
"""

from __future__ import annotations

import hashlib
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from pathlib import Path

import numpy as np

from .jitcache import sources_digest, write_stamp

#: The cost class (``ModelSpec.cost``) from which a model's kernels are the slow ones to compile.
HEAVY = 2
#: The file in numba's cache folder that says which version of the engine it holds, compiled.
STAMP = "tissuebench-precompiled.sha256"


def jobs() -> list[tuple[str, str, int]]:
    """What each job builds: (model, precision, threads), for every model and every precision it has, on
    one thread; the most expensive to compile first (``ModelSpec.cost`` from HEAVY), so that the pool's
    processes end together.

    The threaded kernels (``threads`` > 1) are left to compile when a run first builds one: no study
    does (sweep, advise, report and the reference never ask for threads), only a simulator embedding the
    engine and ``make bench``. Compiled ahead with every integrator they took 151 of this step's 240
    CPU seconds on a 2-core AMD EPYC (corotational-tm's parallel force alone 28 s); a run compiles only
    the integrator it steps with."""
    from .models import SPECS

    out = [
        (s.name, precision, 1)
        for s in SPECS.values()
        for precision in (("float64", "float32") if s.float32 else ("float64",))
    ]
    return sorted(out, key=lambda j: (SPECS[j[0]].cost < HEAVY, j[1] == "float32"))


def _two_cubes() -> tuple[np.ndarray, np.ndarray]:
    """points (12, 3) float64 m and tets (12, 4) int64: two unit cubes of 1 cm side by side along x, each
    in six tetrahedra around its diagonal (Kuhn's triangulation), positively oriented."""
    points = np.array([(x, y, z) for z in (0, 1) for y in (0, 1) for x in (0, 1, 2)], dtype=np.float64) * 0.01

    def vertex(x, y, z):
        return x + 3 * y + 6 * z

    tets = []
    for x0 in (0, 1):
        for axes in ((0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)):
            corner = [x0, 0, 0]
            path = [vertex(*corner)]
            for a in axes:
                corner[a] += 1
                path.append(vertex(*corner))
            p = points[path]
            if np.linalg.det(p[1:] - p[0]) < 0.0:
                path[2], path[3] = path[3], path[2]
            tets.append(path)
    return points, np.array(tets, dtype=np.int64)


def compile_job(job: tuple[str, str, int]) -> float:
    """Build ``job``'s model on the two cubes, clamped at x = 0, one tool pulling the far face and one
    turning a vertex, and call what a run calls. Returns the seconds it took."""
    from .integrators import INTEGRATORS, ImplicitEuler
    from .material import Material
    from .model import TOOL_ROTATION, TOOL_TRANSLATION, Loading
    from .models import SPECS, build_model
    from .quasistatic import QuasiStatic
    from .spectra import element_critical_dt
    from .statics import solve_static

    t0 = time.perf_counter()
    name, precision, threads = job
    points, tets = _two_cubes()
    n = len(points)
    free = np.ones((n, 3))
    free[points[:, 0] == 0.0] = 0.0
    pulled, turned = np.flatnonzero(points[:, 0] == 0.02), np.array([4])
    tool_vertex = np.concatenate([pulled, turned])
    free[tool_vertex] = 0.0
    loading = Loading(
        free=free,
        external_force=np.full((n, 3), 1e-3),
        tool_vertex=tool_vertex,
        tool_mask=np.ones((len(tool_vertex), 3)),
        tool_id=np.array([0] * len(pulled) + [1], dtype=np.int64),
        tool_kind=np.array([TOOL_TRANSLATION, TOOL_ROTATION], dtype=np.int64),
        tool_vector=np.array([[0.001, 0.0, 0.0], [0.0, 0.0, 0.0]]),
        tool_axis=np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]),
        tool_center=np.zeros((2, 3)),
        tool_angle=np.array([0.0, 0.1]),
        tool_ramp=np.array([0.01, 0.01]),
    )
    options = {}
    if precision != "float64":
        options["precision"] = precision
    if threads != 1:
        options["threads"] = threads
    model = build_model(name, points, tets, Material(5e3, 0.45, 1000.0, volume_penalty=1e4), loading, **options)
    state = model.rest_state()
    if SPECS[name].quasi_static:
        QuasiStatic().step(model, state, 1e-3, 2)
        return time.perf_counter() - t0
    model.elastic_energy(state.u)
    dt = 0.1 * element_critical_dt(model)
    for cls in INTEGRATORS.values():
        if cls is ImplicitEuler and precision != "float64":
            continue  # its CG solves in float64 only, and says so
        integrator = cls()
        integrator.critical_dt(model)
        integrator.step(model, state, dt, 2)
    solve_static(model, steps=2)
    return time.perf_counter() - t0


def _cache_dir() -> Path | None:
    from .steppers import _run_symplectic_euler

    path = getattr(getattr(_run_symplectic_euler, "_cache", None), "cache_path", None)
    return Path(path) if path else None


def _target() -> tuple:
    """numba's target in this process, as it keys its cache entries: (triple, CPU name, features)."""
    from numba.core.registry import cpu_target

    return cpu_target.target_context.codegen().magic_tuple()


def _digest() -> str:
    """The stamp of this version of the engine compiled for this process's target: the sources' digest
    and numba's target (realtime.target chooses its features). numba keeps entries for other targets
    apart, so a cache stamped for another one is not current: the first run would compile."""
    sources = sources_digest(list(Path(__file__).parent.glob("*.py")))
    return hashlib.sha256(f"{sources} {_target()!r}".encode()).hexdigest()


def is_current() -> bool:
    """Whether numba's cache holds this version of the engine, compiled by ``precompile``."""
    folder = _cache_dir()
    try:
        return folder is not None and (folder / STAMP).read_text() == _digest()
    except OSError:
        return False


def precompile(processes: int | None = None, todo: list | None = None, log=None) -> bool:
    """Compile ``todo`` (default every job()) into numba's cache on ``processes`` (default: the cores),
    unless the cache is current. Returns whether it compiled. ``log`` (default stderr) gets one line a
    job. Only the full list stamps the cache as current."""
    import realtime  # noqa: F401  (jitcache.guard: a stale cache is cleared before anything is saved)

    def say(text):
        line = f"precompile: {text}"
        if log is None:
            print(line, file=sys.stderr, flush=True)
        else:
            log(line)

    if is_current():
        return False
    full = todo is None
    todo = jobs() if full else list(todo)
    processes = processes or max(1, len(os.sched_getaffinity(0)))
    say(f"compiling the engine's kernels into numba's cache ({len(todo)} models, {processes} processes; once)")
    t0 = time.perf_counter()
    if processes > 1:
        import multiprocessing

        with ProcessPoolExecutor(processes, mp_context=multiprocessing.get_context("spawn")) as pool:
            futures = {pool.submit(compile_job, job): job for job in todo}
            for done in as_completed(futures):
                say(f"{_label(futures[done])}: {done.result():.1f} s")
    for job in todo:  # loads what the pool cached; compiles what a lost index entry left out
        compile_job(job)
    folder = _cache_dir()
    if full and folder is not None:
        write_stamp(folder / STAMP, _digest())
    say(f"done in {time.perf_counter() - t0:.0f} s")
    return True


def _label(job: tuple[str, str, int]) -> str:
    name, precision, threads = job
    return f"{name} ({precision}, {threads} thread{'s' * (threads > 1)})"


def main() -> int:
    """``python -m realtime.precompile``: 0 when the cache is current, 1 with one line on stderr when a
    job failed (the engine then compiles on first use, as without this step), 130 on Ctrl-C."""
    try:
        precompile()
    except KeyboardInterrupt:
        print("precompile: interrupted; what had finished is cached", file=sys.stderr)
        return 130
    except Exception as exc:  # a defect of the engine: the suite's tests say which
        print(f"precompile: failed: {type(exc).__name__}: {exc}".splitlines()[0], file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
