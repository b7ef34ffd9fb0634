"""A model run on a scene, through the engine seam (``verification.engines.protocol``).

The harness's side of every run: the time step (a fraction of the engine's critical one unless given),
the output instants of a dynamic scene, the timing of the steps at the state the run reached, and the
Result with its meta (docs/data-flow.md). The engine's side (its model, how it settles, how
it samples between steps) is behind ``Engine.build``.
"""

from __future__ import annotations

import contextlib
import signal
import threading
import time

import numpy as np

from realtime import DivergenceError, NotConvergedError
from realtime.errors import InputError, ModelRestriction
from reference.progress import Progress

from ..cache import git_commit, versions
from ..engines import engine_for
from ..engines.builtin import BUILTIN
from ..engines.protocol import Simulation
from ..inputs import scene_inputs
from ..progress import mpi_rank
from ..scene import Scene
from .results import Result
from .worker import PlugInError, forks, in_worker

#: A static run's default tolerance (its residual against the load) and its most steps to settle.
SETTLE_RTOL, SETTLE_MAX_STEPS = 1e-10, 2_000_000
#: The default time step of an explicit integrator, and of implicit Euler on a dynamic scene, as
#: fractions of the explicit critical step.
EXPLICIT_FRACTION, IMPLICIT_FRACTION = 0.9, 10.0


def time_steps(sim: Simulation, n: int = 100, repeats: int = 9) -> dict:
    """Median and spread of the wall time of one of ``sim``'s steps across the seam, after a warm-up
    step (compilation, caches), in microseconds. Each repeat times n steps in one call. The simulation's
    state moves on."""
    sim.step(1)
    per_step = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        sim.step(n)
        per_step.append((time.perf_counter() - t0) / n * 1e6)
    per_step = np.sort(per_step)
    return {
        "step_us": float(np.median(per_step)),
        "step_us_min": float(per_step[0]),
        "step_us_max": float(per_step[-1]),
        "timing_steps": n,
        "timing_repeats": repeats,
    }


def _timing(sim: Simulation, n: int, repeats: int) -> dict:
    """The step timing of a run: measured across the seam (``time_steps``), or, for an engine that runs
    in a process of its own (``timing`` None), the step time it reports (``step_us()``, us, or None
    where it reports none), labelled as the engine's."""
    if sim.timing is not None:
        return {**time_steps(sim, n, repeats), "timed_by": "harness"}
    us = sim.step_us()
    return {"step_us": us, "step_us_min": us, "step_us_max": us, "timing_steps": None, "timing_repeats": None,
            "timed_by": "engine"}  # fmt: skip


def output_times(scene: Scene) -> np.ndarray:
    """0, output_every, 2 output_every, ... up to end (the reference's output instants), s."""
    ts = scene.time
    n = int(round(ts.end / ts.output_every))
    return np.arange(n + 1) * ts.output_every


def run_model(
    scene: Scene,
    model_name: str,
    dt: float | None = None,
    dt_fraction: float | None = None,
    integrator: str = "symplectic-euler",
    rtol: float = SETTLE_RTOL,
    max_steps: int = SETTLE_MAX_STEPS,
    options: dict | None = None,
    engine=None,
) -> Result:
    """Run a model on a scene: on a static scene to equilibrium (``Simulation.settle``: at most
    ``max_steps``, else NotConvergedError), then timing; on a dynamic one the trajectory from rest; on
    one with events each state's equilibrium (``runs.staged``).

    dt defaults to ``dt_fraction`` (default 0.9, implicit Euler 10 on a dynamic scene) times the
    engine's critical step. A diverging run raises DivergenceError. ``options`` go to the model's
    builder (hybrid-tm's ``threshold``, m). ``engine`` defaults to the one offering ``model_name``."""
    engine = engine if engine is not None else engine_for(model_name)
    if scene.events:  # one static run per state (``runs.staged``)
        from .staged import staged_run

        return staged_run(
            scene, lambda s: run_model(s, model_name, dt, dt_fraction, integrator, rtol, max_steps, options, engine)
        )
    if engine is not BUILTIN:
        if scene.problem.contacts and model_name not in getattr(engine, "rigid", ()):
            raise ModelRestriction(
                f"{scene.path}: tool: {model_name} ({engine.name}) is not given a rigid tool: its adapter or plug-in "
                "does not meet one with a contact of its own (docs/engines.md)"
            )
        return _plug_in(scene, engine, model_name, dt, dt_fraction, integrator, rtol, max_steps, options)
    return _run(scene, engine, model_name, dt, dt_fraction, integrator, rtol, max_steps, options)


def _run(scene: Scene, engine, model_name, dt, dt_fraction, integrator, rtol, max_steps, options) -> Result:
    inputs = scene_inputs(scene)
    t0 = time.perf_counter()
    sim = engine.build(inputs, model_name, integrator, dict(options or {}))
    build_s = time.perf_counter() - t0
    if scene.time.mode == "dynamic":
        return _run_dynamic(scene, sim, dt, dt_fraction, build_s, engine.name)
    return _run_static(scene, sim, dt, dt_fraction, rtol, max_steps, build_s, engine.name)


#: Seconds a plug-in engine's run may take (the command line's --engine-timeout sets it).
PLUG_IN_TIMEOUT = 600.0


@contextlib.contextmanager
def _bounded(seconds: float, what: str):
    """Stop the code inside after ``seconds`` with a PlugInError naming ``what``: a plug-in that hangs
    in Python code (a loop, a sleep) is interrupted by SIGALRM. Only in the main thread, where signals
    are delivered; elsewhere, and inside a C call that does not return, it cannot be (a command engine
    runs in its own process, with its own timeout)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def expired(signum, frame):
        raise PlugInError(f"{what}: still running after {seconds:g} s, stopped")

    previous = signal.signal(signal.SIGALRM, expired)
    signal.setitimer(signal.ITIMER_REAL, seconds)
    try:
        yield
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0.0)
        signal.signal(signal.SIGALRM, previous)


def _plug_in(scene: Scene, engine, model_name, dt, dt_fraction, integrator, rtol, max_steps, options) -> Result:
    """A plug-in's run, as ``_run``, with whatever it raises or writes wrong said in one line: the
    harness judges other people's code and keeps going (a study records the failure). An engine that
    runs in this process runs in a forked worker (``runs.worker``), so that a hang in C code or a crash
    of the interpreter stops the worker alone; one that runs in a process of its own already (a command,
    an adapter: ``isolated``) runs here, bound by SIGALRM as well as by its own timeout."""
    what = f"engine {engine.name}, model {model_name}"

    def run():
        return _run(scene, engine, model_name, dt, dt_fraction, integrator, rtol, max_steps, options)

    try:
        if forks() and not getattr(engine, "isolated", False):
            res = in_worker(run, PLUG_IN_TIMEOUT, what)
        else:
            with _bounded(PLUG_IN_TIMEOUT, what):
                res = run()
    except (DivergenceError, NotConvergedError, InputError):
        raise
    except Exception as exc:  # the plug-in's own code: named, never a traceback of ours
        raise PlugInError(f"{what}: {type(exc).__name__}: {' '.join(str(exc).split())}") from None
    expected = (len(res.times), scene.mesh.n_vertices, 3)
    if res.displacement.shape != expected:
        raise PlugInError(
            f"{what}: its displacement is {res.displacement.shape}, not {expected} (times, vertices, xyz)"
        )
    if not np.all(np.isfinite(res.displacement)):
        bad = tuple(int(i) for i in np.argwhere(~np.isfinite(res.displacement))[0])
        raise PlugInError(f"{what}: its displacement{list(bad)} is {res.displacement[bad]} (time, vertex, component)")
    size = float(np.ptp(scene.mesh.points, axis=0).max())
    reach = float(np.abs(res.displacement).max())
    if reach > 10.0 * size:
        raise PlugInError(
            f"{what}: its displacement reaches {reach:.3g} m, over 10 times the body ({size:.3g} m): is it in metres?"
        )
    return res


def _meta(scene: Scene, sim: Simulation, solver: str, dt, dt_crit, build_s: float, timing: dict) -> dict:
    """The meta every run carries (docs/data-flow.md); ``solver``: the engine's name."""
    return {
        "solver": solver,
        "model": sim.model,
        "integrator": sim.integrator,
        "dt": dt,
        "dt_crit": dt_crit,
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": scene.mesh.sha256(),
        "build_s": build_s,
        **timing,
        "realtime_factor": None if dt is None or not timing["step_us"] else dt / (timing["step_us"] * 1e-6),
        "rate_hz": 1e6 / timing["step_us"] if timing["step_us"] else None,
        "versions": versions(),
        "commit": git_commit(),
        "engine": getattr(sim, "info", None),  # an adapter's: the engine, its version, its law, its knobs
    }


def _run_static(scene: Scene, sim: Simulation, dt, dt_fraction, rtol, max_steps, build_s: float, solver: str) -> Result:
    """Equilibrium, read, then the steps timed from it."""
    s = sim.settle(rtol, max_steps, dt, dt_fraction)
    u, reaction = sim.displacement().copy(), np.array(sim.tool_force(), dtype=float)
    # read with them, before the timed steps move the state (the seam's engines give no area yet)
    area = sim.contact_area() if scene.problem.contacts and hasattr(sim, "contact_area") else None
    timing = _timing(sim, *(sim.timing or (0, 0)))
    meta = _meta(scene, sim, solver, s.dt, s.dt_crit, build_s, timing)
    settle_ms = s.steps * timing["step_us"] * 1e-3 if timing["step_us"] else None
    meta.update(s.meta, static=s.static, settle_ms=settle_ms)
    if area is not None:
        meta["contact_area"] = np.asarray(area, dtype=float).tolist()
    mesh = scene.mesh
    return Result(mesh.points, mesh.tets, np.zeros(1), u[None], reaction[None], meta)


def trajectory(sim: Simulation, times: np.ndarray, label: str = "") -> tuple[np.ndarray, np.ndarray]:
    """The simulation, started at rest (``Simulation.start``), sampled at ``times`` (T,) s: displacement
    (T, N, 3) m of the scene's vertices and the tools' force (T, 3) N."""
    out_u, out_r = [], []
    ticker = Progress(f"run: {sim.model}{label}, output", len(times), mpi_rank())
    for k, t_out in enumerate(times):
        ticker.tick(k, f", t = {t_out:.4g} s")
        sim.advance_to(float(t_out))
        out_u.append(np.array(sim.displacement(), dtype=float))
        out_r.append(np.array(sim.tool_force(), dtype=float))
    return np.array(out_u), np.array(out_r)


def _dynamic_step(scene: Scene, sim: Simulation, dt, dt_fraction) -> tuple:
    """The step (s) a dynamic run takes and the explicit critical step (s) it comes from: ``dt``, else
    ``dt_fraction`` (default EXPLICIT_FRACTION, IMPLICIT_FRACTION for implicit Euler) of the critical
    step; an engine with none steps by the output instants or by its own choice (dt None)."""
    dt_crit = sim.critical_dt()
    if dt_crit is None:  # stepped by the output instants, or by its own choice
        dt = dt if dt is not None or getattr(sim, "own_step", False) else scene.time.output_every
    elif dt is None:
        default = IMPLICIT_FRACTION if sim.integrator == "implicit-euler" else EXPLICIT_FRACTION
        dt = (default if dt_fraction is None else dt_fraction) * dt_crit
    return dt, dt_crit


#: The steps, and their repeats, a dynamic run's step time is measured on before the run
#: (``step_time_ahead``): a few milliseconds of a small model's steps, a second of a large one's.
AHEAD_STEPS, AHEAD_REPEATS = 50, 3


def step_time_ahead(scene: Scene, model_name: str, dt=None, dt_fraction=None, integrator: str = "symplectic-euler"):
    """A built-in model's step on a dynamic scene and its time, before its run: the model built,
    started from rest at the step the run would take (``_dynamic_step``), and AHEAD_REPEATS x
    AHEAD_STEPS steps timed (``time_steps``). From rest a step costs what it costs later for every model
    whose work does not grow with the deformation, and less for those whose does (hybrid-tm's non-linear
    part, adaptive-tm's refined tetrahedra): an underestimate, never an overestimate. Returns dt,
    dt_crit (s) and the timing, or None where the step is not the harness's to time (another engine's,
    a quasi-static update) or the steps diverged (the run then says so itself)."""
    engine = engine_for(model_name)
    if engine is not BUILTIN or scene.time.mode != "dynamic" or BUILTIN.models[model_name].quasi_static:
        return None
    sim = engine.build(scene_inputs(scene), model_name, integrator, {})
    dt, dt_crit = _dynamic_step(scene, sim, dt, dt_fraction)
    if dt is None or dt_crit is None or not np.isfinite(dt):
        return None
    sim.start(dt)
    try:
        timing = time_steps(sim, AHEAD_STEPS, AHEAD_REPEATS)
    except DivergenceError:
        return None
    return {"dt": dt, "dt_crit": dt_crit, **timing}


def _run_dynamic(scene: Scene, sim: Simulation, dt, dt_fraction, build_s: float, solver: str) -> Result:
    """A dynamic scene: the trajectory from rest at the scene's output times, then steps timed."""
    ts = scene.time
    times = output_times(scene)
    dt, dt_crit = _dynamic_step(scene, sim, dt, dt_fraction)
    sim.start(dt)
    label = "" if dt_crit is None else f" ({sim.integrator}, dt = {dt:.3g} s)"
    t1 = time.perf_counter()
    u, reaction = trajectory(sim, times, label)
    run_s = time.perf_counter() - t1
    adaptation = getattr(sim, "adaptation", None)  # a re-adapting run ends on its finest step
    dt = sim.dt if dt is None or adaptation else dt  # the step it chose
    timing = _timing(sim, sim.timing[0] if sim.timing else 0, 7)
    meta = _meta(scene, sim, solver, dt, dt_crit, build_s, timing)
    if adaptation:
        meta["adaptation"] = adaptation
    meta.update(
        dt_crit_rest=dt_crit,
        mode="dynamic",
        static={
            "method": "trajectory",
            "steps": int(np.ceil(ts.end / dt)) if dt else None,
            "residual": None,
            "rtol": None,
            "wall_s": run_s,
        },
        settle_ms=None,
    )
    mesh = scene.mesh
    return Result(mesh.points, mesh.tets, times, u, reaction, meta)
