"""Reference solves ahead of a study, on all the machine's cores (docs/metrics.md,
"References ahead of a study").

A study asks for its references one at a time, between model runs, and solves each on one core. When
the study knows its references in advance (the report's scenes, the stability study's variants), they
are solved first, in separate processes, one per core, into the reference cache; the study then finds
them there. Nothing is timed while they run: model runs, whose step times the studies report, start
afterwards on a quiet machine. Under mpirun the ranks already share the work, and nothing is
prefetched.
"""

from __future__ import annotations

import concurrent.futures
import multiprocessing
import os

from verification.progress import log
from verification.runs.reference import P1_OWN_MESH, REFERENCE_DEFAULTS, reference_path
from verification.scene import Scene


def _solve(scene: Scene, options: dict) -> str | None:
    """One reference into the cache (in a worker process); the one-line reason if it cannot be solved."""
    from reference.errors import ReferenceSolveError
    from verification.runs.reference import reference_result

    try:
        reference_result(scene, **options)
    except ReferenceSolveError as exc:
        return str(exc)
    return None


def _workers(workers: int | None, n_jobs: int) -> int:
    """How many processes ``n_jobs`` jobs run on: ``workers`` (default the cores this process may use)
    at most, and 0 when they should run here instead (one worker, one job, or under mpirun, where the
    ranks already share each solve)."""
    from mpi4py import MPI

    workers = min(workers or len(os.sched_getaffinity(0)), n_jobs)
    return 0 if workers < 2 or MPI.COMM_WORLD.size > 1 else workers


def _end_with_parent(parent: int) -> None:
    """A worker's initializer: the worker is ended when the process that spawned it ends, however it
    ends (a killed advise left its two workers solving for minutes). Linux's PR_SET_PDEATHSIG sends
    SIGTERM then; where it is not available, nothing changes. If the parent ended before the call, the
    worker ends now."""
    import ctypes
    import signal

    try:
        ctypes.CDLL(None, use_errno=True).prctl(1, signal.SIGTERM)  # 1: PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        return
    if os.getppid() != parent:
        os._exit(1)


def _spawned(fn, jobs: list[tuple], workers: int):
    """Run ``fn(*job)`` for each of ``jobs``, in that order of submission, on ``workers`` spawned
    processes (a fresh interpreter: no MPI or PETSc state forked), which end with this one
    (``_end_with_parent``); yields (index, result) as each ends."""
    context = multiprocessing.get_context("spawn")
    pool = concurrent.futures.ProcessPoolExecutor(
        max_workers=workers, mp_context=context, initializer=_end_with_parent, initargs=(os.getpid(),)
    )
    try:
        futures = {pool.submit(fn, *job): i for i, job in enumerate(jobs)}
        for future in concurrent.futures.as_completed(futures):
            yield futures[future], future.result()
    finally:
        # after Ctrl-C (which the workers get too) or a failed job, start no job still queued: the
        # executor's own exit would have run every one of them before the interruption took effect
        pool.shutdown(wait=True, cancel_futures=True)


def _static(job: dict):
    """One static reference's displacements (in a worker process)."""
    from reference.driver import solve_static

    return solve_static(**job)["displacement"]


def static_displacements(jobs: list[dict], workers: int | None = None, done=None) -> list:
    """``reference.driver.solve_static(**job)["displacement"]`` for each of ``jobs``, in their order,
    solved ``workers`` at a time (default: the cores this process may use) in spawned processes, the
    largest first; ``done(job)`` is called as each finishes. Nothing is cached (the convergence study's
    solves at given points). Under mpirun, with one worker or one job, they are solved here in turn
    (under mpirun each solve is distributed over the ranks)."""
    done = done or (lambda job: None)
    workers = _workers(workers, len(jobs))
    if not workers:
        out = []
        for job in jobs:
            out.append(_static(job))
            done(job)
        return out
    cost = [job["mesh"].n_tets * 8 ** job.get("refine", 0) * (4 if job.get("degree", 2) == 2 else 1) for job in jobs]
    order = sorted(range(len(jobs)), key=lambda i: -cost[i])
    out = [None] * len(jobs)
    for k, result in _spawned(_static, [(jobs[i],) for i in order], workers):
        out[order[k]] = result
        done(jobs[order[k]])
    return out


def scene_jobs(scenes: list[Scene]) -> list[tuple[Scene, dict]]:
    """What a sweep, compare or advice on each scene asks for first: its P2 reference with the estimate and
    its P1 solution on its own mesh (the error budget's mesh part); for a scene with events, each of its
    states' (``verification.events``), which its reference then evaluates."""
    from verification.events import states

    solved = [s for scene in scenes for s in ([st.scene for st in states(scene)] if scene.events else [scene])]
    return [(scene, options) for scene in solved for options in (REFERENCE_DEFAULTS, P1_OWN_MESH)]


def advice_jobs(scenes: list[Scene]) -> list[tuple[Scene, dict]]:
    """What advice on each scene asks for: ``scene_jobs``, and on a static scene also the P1 solution on
    its mesh refined once, from which the advisor's mesh proposal reads the observed order of the mesh's
    error (``proposal.propose_mesh``). Solved ahead, it leaves the advice's serial part (7 s on the
    report's cantilever, whose refined mesh has 22 837 vertices)."""
    jobs = scene_jobs(scenes)
    return jobs + [(scene.refined(1), P1_OWN_MESH) for scene in scenes if scene.time.mode == "static"]


def solve_references(jobs: list[tuple[Scene, dict]], workers: int | None = None) -> dict[str, str]:
    """Solve the references of ``jobs`` ((scene, ``reference_result`` keyword arguments) pairs) that are
    not cached yet, ``workers`` at a time (default: the cores this process may use), largest first.

    Returns the references that cannot be solved, as {scene hash: reason}: they are not cached, and a
    study that would solve them again can skip them. With one worker, one job, or under mpirun, nothing
    is solved here and the study solves as it goes.
    """
    todo, seen = [], set()
    for scene, options in jobs:
        path = reference_path(scene, **options)
        if path not in seen and not path.exists():
            seen.add(path)
            todo.append((scene, options))
    workers = _workers(workers, len(todo))
    if not workers:
        return {}
    # the finest solves first, so that the last to finish is a small one
    todo.sort(key=lambda job: -job[0].mesh.n_vertices * (8 if job[1].get("estimate", True) else 1))
    log(f"references: solving {len(todo)} on {workers} processes before the runs")
    failed = {}
    for k, reason in _spawned(_solve, todo, workers):
        if reason is not None:
            failed[todo[k][0].sha256()] = reason
    return failed


#: Settlings tried ahead in this process, by cache path, whatever came of them: one that diverged or did
#: not settle is not cached, and a study that asks for it again runs it itself (and reports it).
SETTLED_AHEAD: set = set()


def _settle_model(scene: Scene, model_name: str, fractions: tuple[float, ...], runs: tuple = ()) -> int:
    """(In a worker process.) Settle ``scene`` with ``model_name`` through the engine seam
    (``Simulation.settle``), into the caches its engine and ``stable_step.largest_stable_fraction`` read, as a sweep and its advice would: with symplectic Euler at
    each of ``fractions`` of its critical step and at its largest stable fraction, and with implicit Euler
    at its default step if the advisor tries it (its spec lists implicit Euler); none of these when
    ``fractions`` is empty. Then each of ``runs`` ((integrator, max_steps) at the default step: the
    stability study's cells, ``stability.settle_cells``). Returns how many settled (a run that diverges
    or does not settle is left to the study, which reports it)."""
    from realtime import DivergenceError, NotConvergedError
    from verification.engines import engine_for, spec_of
    from verification.inputs import scene_inputs
    from verification.runs.simulate import SETTLE_MAX_STEPS, SETTLE_RTOL
    from verification.studies.stable_step import largest_stable_fraction

    inputs, engine = scene_inputs(scene), engine_for(model_name)
    todo = []
    if fractions:
        stable = largest_stable_fraction(scene, model_name)["stable"]
        todo += [("symplectic-euler", f, None) for f in (*fractions, *([stable] if stable else []))]
        todo += [("implicit-euler", None, None)] if "implicit-euler" in spec_of(model_name).integrators else []
    todo += [(integrator, None, max_steps) for integrator, max_steps in runs]
    done = 0
    for integrator, fraction, max_steps in todo:
        try:
            sim = engine.build(inputs, model_name, integrator, {})
            sim.settle(SETTLE_RTOL, max_steps or SETTLE_MAX_STEPS, None, fraction)
            done += 1
        except (DivergenceError, NotConvergedError):
            pass
    return done


def settle_ahead(
    jobs: list[tuple[Scene, tuple[float, ...]]], workers: int | None = None, models=None, cells=()
) -> None:
    """Settle the static scenes of ``jobs`` ((scene, fractions of the critical step) pairs) with every
    time-stepping model (or those of ``models``), and the stability study's ``cells`` ((scene, model,
    integrator, max_steps) at the default step, ``stability.settle_cells``) not settled or tried yet,
    ``workers`` processes at a time (default: the cores this process may use), as the sweeps, advice and
    study would one after the other (``_settle_model``). They then find each equilibrium cached and
    only time its steps, on a quiet machine: nothing is timed here. With one worker, one job or under
    mpirun nothing is settled here and each settles as it goes."""
    from realtime import SPECS
    from verification.engines.settling import settled_path
    from verification.inputs import scene_inputs

    def order(m: str) -> tuple:
        """The costliest settling first (``ModelSpec.cost``: adaptive-tm's mixed mesh), so that the last
        job to finish is a short one."""
        return (-SPECS[m].cost, m)

    models = sorted((m for m in models or SPECS if not SPECS[m].quasi_static), key=order)
    todo = [
        (scene, m, tuple(fractions))
        for m in models
        for scene, fractions in sorted(jobs, key=lambda job: -job[0].mesh.n_tets)
        if scene.time.mode == "static"
    ]
    runs: dict[tuple, list] = {}  # the cells by (scene, model), in their order
    paths = []
    for scene, m, integrator, max_steps in cells:
        path = settled_path(scene_inputs(scene), m, integrator, None, None, 1e-10, max_steps, None)
        if not SPECS[m].quasi_static and path not in SETTLED_AHEAD and not path.exists():
            paths.append(path)
            runs.setdefault((scene.sha256(), m), [scene, m, ()])[2] += ((integrator, max_steps),)
    # after the sweeps' (longer) jobs, the costliest models first: the last to finish is a short one
    todo += [(scene, m, (), r) for scene, m, r in sorted(runs.values(), key=lambda job: order(job[1]))]
    workers = _workers(workers, len(todo))
    if not workers:
        return
    SETTLED_AHEAD.update(paths)
    log(f"settling: {len(todo)} model runs of static scenes on {workers} processes before the timed runs")
    for _ in _spawned(_settle_model, todo, workers):
        pass
