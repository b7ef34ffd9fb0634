"""Runs: the reference of a scene (cached on disk), a real-time model on a scene, and the comparison.

Reference results are cached under ``$TISSUEBENCH_CACHE`` (default ``~/.cache/tissuebench``), keyed by
a hash of everything they depend on: the scene's content and mesh hash, degree, refinement, the
estimate flag, the solver options and the reference code's version. A study interrupted half-way
finds the solves it finished and goes on from there.
"""

from __future__ import annotations

import copy
import functools
import hashlib
import json
import math
import os
import platform
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

import realtime
from meshes import TetMesh
from realtime import DivergenceError, ImplicitEuler, State, SymplecticEuler, build_model, make_integrator, solve_static
from realtime.models import FLOAT32_MODELS, QUASI_STATIC, unrepresented
from realtime.quasistatic import QuasiStatic
from realtime.spectra import max_eigenvalue, min_eigenvalue
from realtime.statics import solve_static_implicit
from reference.progress import Progress, line

from .loading import build_loading
from .metrics import compute, rel_l2
from .results import Result, atomic_savez, read_cached
from .scene import Scene

#: Bumped whenever the reference's numbers can change for the same inputs, so old cache entries die.
REFERENCE_VERSION = "2"  # 2: spanned regions, the finer solution returned, det F checked, exact tool kinematics
REFERENCE_DEFAULTS = {"degree": 2, "refine": 0, "estimate": True}
#: The P1 solution of a scene on its own mesh (the error budget's mesh part).
P1_OWN_MESH = {"degree": 1, "refine": 0, "estimate": False, "own_mesh": True}


def _rank() -> int:
    """This process's MPI rank as mpirun set it (0 outside mpirun)."""
    from . import _RANK

    return int(_RANK or 0)


def log(msg: str) -> None:
    """Progress to stderr (stdout is kept for --json), from the first MPI rank only (under mpirun every
    rank runs the same driver, and each line came once per rank), in one write (reference.progress)."""
    line(msg, _rank())


def cache_dir() -> Path:
    return Path(os.environ.get("TISSUEBENCH_CACHE", Path.home() / ".cache" / "tissuebench"))


def git_commit(root: Path | None = None) -> str:
    """The short hash of the commit the code in ``root`` (this project's, by default) ran at, with
    "-dirty" when a tracked file differs from that commit: a number from changed code is not that
    commit's, and a baseline or a report that named only the commit would say it was. "unknown"
    outside a git checkout."""

    def git(*args) -> str:
        out = subprocess.run(
            ["git", *args], capture_output=True, text=True, cwd=root or Path(__file__).parent, timeout=5
        )
        return out.stdout.strip() if out.returncode == 0 else ""

    try:
        head = git("rev-parse", "--short", "HEAD")
        if not head:
            return "unknown"
        return head + ("-dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def digest(fields: dict) -> str:
    """A cache key: 24 hex digits of the SHA-256 of ``fields`` as sorted JSON."""
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:24]


ROOT = Path(__file__).resolve().parents[1]
#: The code a reference result depends on: its solvers, the region rule both sides share, the constants.
REFERENCE_CODE = ("reference/*.py", "meshes/regions.py", "realtime/material.py")
#: The code a run's row depends on: the engine, the runner, loading, metrics and studies, and the
#: reference it is compared with.
RUN_CODE = (
    "realtime/*.py",
    "verification/runner.py",
    "verification/loading.py",
    "verification/metrics.py",
    "verification/runs.py",
    *REFERENCE_CODE,
)


@functools.cache
def code_digest(patterns: tuple[str, ...]) -> str:
    """Digest of the source files matching ``patterns`` (relative to the project root): part of every
    cache key, so that a cached result is never one that other code made."""
    files = sorted({f for pattern in patterns for f in ROOT.glob(pattern)})
    return digest({str(f.relative_to(ROOT)): hashlib.sha256(f.read_bytes()).hexdigest() for f in files})


@functools.cache
def machine_id() -> dict:
    """What a timing depends on: the architecture, the processor's name and the number of cores."""
    model = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"arch": platform.machine(), "cpu": model, "cores": os.cpu_count()}


def reference_key(
    scene: Scene,
    degree: int,
    refine: int,
    estimate: bool,
    newton=(1, 1e-4),
    own_mesh: bool = False,
    petsc_options: dict | None = None,
) -> str:
    from reference.fem import DIRECT_LIMIT, DIRECT_OPTIONS, GAMG_OPTIONS

    return digest(
        {
            "scene": scene.sha256(),
            "solved_on": "own mesh" if own_mesh or not scene.level else "base mesh",
            "degree": degree,
            "refine": refine,
            "estimate": estimate,
            "newton": list(newton),
            "solver": {
                "direct": DIRECT_OPTIONS,
                "gamg": GAMG_OPTIONS,
                "direct_limit": DIRECT_LIMIT,
                "user": petsc_options,
            },
            "version": REFERENCE_VERSION,
            "code": code_digest(REFERENCE_CODE),
        }
    )


#: The last static solves of this process (their problems and meta), by the solved scene's hash and the
#: options: a refined scene's reference is the base scene's solve evaluated at its vertices, and the
#: advisor asks for it at several levels (10 s each for the cantilever's P2 with its estimate).
_SOLVED: dict[tuple, tuple[list, dict]] = {}
SOLVED_KEPT = 2


def _fields_path(reference: Path) -> Path:
    """Beside a base reference with its estimate, its solved fields (``reference.driver.solved_fields``):
    a refined scene's truth asked for in another process (the report's references are solved in
    worker processes, the advice's refined truths in the main one) is then the base solve rebuilt and
    evaluated at its vertices, 1 s where solving again took 10 s on the report's cantilever."""
    return reference.with_name(reference.stem + "-fields.npz")


def reference_path(
    scene: Scene,
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    newton_steps: int = 1,
    min_increment: float = 1e-4,
    own_mesh: bool = False,
    petsc_options: dict | None = None,
) -> Path:
    """Where ``reference_result`` with these arguments keeps its answer."""
    key = reference_key(scene, degree, refine, estimate, (newton_steps, min_increment), own_mesh, petsc_options)
    return cache_dir() / "reference" / f"{scene.name}-{key}.npz"


def _save_solved(path: Path, problems: list, meta: dict) -> None:
    from reference.driver import solved_fields

    arrays = solved_fields(problems)
    atomic_savez(path, meta=np.array(json.dumps(meta)), **arrays)


def _restore_solved(memo: tuple, path: Path, solved: Scene, material, degree: int, refine: int) -> None:
    """Into _SOLVED, the solve kept at ``path`` (_save_solved) rebuilt; nothing if it cannot be."""
    from reference.driver import restore_static

    def read(path):
        with np.load(path) as data:
            return {k: data[k] for k in data.files if k != "meta"}, json.loads(str(data["meta"]))

    kept = read_cached(path, read)
    if kept is None:  # a damaged file: solve again
        return
    arrays, meta = kept
    problems = restore_static(solved.mesh, material, solved.problem, degree, refine, arrays)
    if problems is not None:
        _SOLVED[memo] = problems, meta
        while len(_SOLVED) > SOLVED_KEPT:
            _SOLVED.pop(next(iter(_SOLVED)))


def reference_result(
    scene: Scene,
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    use_cache: bool = True,
    newton_steps: int = 1,
    min_increment: float = 1e-4,
    own_mesh: bool = False,
    petsc_options: dict | None = None,
) -> Result:
    """The scene's reference, from the cache or solved now (and then cached). ``newton_steps`` and
    ``min_increment`` set the non-linear static solve's first load increment (1 / newton_steps) and the
    smallest increment it may halve to before it gives up.

    On a refined scene (``Scene.refined``) the reference is solved on the base scene's mesh and
    evaluated at the refined vertices: the truth does not depend on the mesh a model runs on, and the
    base's solve (with its estimate) costs 8^level times less. ``own_mesh`` solves on the scene's own
    mesh instead (the error budget's P1 solution on the model's mesh). ``petsc_options`` go over the
    solver chosen by size (``reference.fem.solver_options``)."""
    from mpi4py import MPI

    from reference.driver import evaluate_static
    from reference.driver import solve_dynamic as reference_dynamic
    from reference.driver import solve_static as reference_static

    path = reference_path(scene, degree, refine, estimate, newton_steps, min_increment, own_mesh, petsc_options)
    cached = read_cached(path, Result.load) if use_cache else None
    if cached is not None:
        return cached
    mesh = scene.mesh
    solved = scene if own_mesh or not scene.level else scene.base
    where = f" on the base mesh at the {mesh.n_vertices} vertices of level {scene.level}" if solved is not scene else ""
    log(f"reference: {scene.name} P{degree} refine {refine}{' + estimate' if estimate else ''}{where} ...")
    t0 = time.perf_counter()
    if scene.time.mode == "dynamic":
        ts = scene.time
        sol = reference_dynamic(
            solved.mesh,
            solved.body_material(),
            solved.problem,
            ts.end,
            ts.output_every,
            rayleigh=(ts.damping_mass, ts.damping_stiffness),
            degree=degree,
            refine=refine,
            estimate=estimate,
            points=mesh.points,
            petsc_options=petsc_options,
        )
        times, disp, reac = sol["times"], sol["displacement"], sol["reaction"]
    else:
        memo = (solved.sha256(), degree, refine, estimate, newton_steps, min_increment, json.dumps(petsc_options or {}))
        serial = MPI.COMM_WORLD.size == 1
        fields = _fields_path(
            reference_path(solved, degree, refine, estimate, newton_steps, min_increment, False, petsc_options)
        )
        if use_cache and memo not in _SOLVED and serial and solved is not scene and fields.exists():
            _restore_solved(memo, fields, solved, solved.body_material(), degree, refine)
        if use_cache and memo in _SOLVED:  # use_cache=False asks for a solve (the benchmarks time it)
            log("reference: the same problem was solved before: evaluated at these vertices")
            sol = evaluate_static(*_SOLVED[memo], mesh.points)
        else:
            sol = reference_static(
                solved.mesh,
                solved.body_material(),
                solved.problem,
                degree=degree,
                refine=refine,
                estimate=estimate,
                newton_steps=newton_steps,
                min_increment=min_increment,
                points=mesh.points,
                petsc_options=petsc_options,
            )
            problems = sol.pop("problems")
            if use_cache:
                _SOLVED[memo] = problems, copy.deepcopy(sol["meta"])
                if serial and estimate and solved is scene:
                    _save_solved(fields, problems, sol["meta"])
            while len(_SOLVED) > SOLVED_KEPT:
                _SOLVED.pop(next(iter(_SOLVED)))
        times, disp, reac = np.zeros(1), sol["displacement"][None], sol["reaction"][None]
    meta = sol["meta"]
    meta.update(
        scene=scene.name,
        scene_sha256=scene.sha256(),
        mesh_sha256=mesh.sha256(),
        scene_level=scene.level,
        solved_on_mesh_sha256=solved.mesh.sha256(),
        cache_key=path.stem.rsplit("-", 1)[1],
        wall_s=time.perf_counter() - t0,
        commit=git_commit(),
        date=time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    )
    res = Result(mesh.points, mesh.tets, times, disp, reac, meta)
    if use_cache and MPI.COMM_WORLD.rank == 0:
        res.save(path)
    log(f"reference: done in {meta['wall_s']:.1f} s")
    return res


#: omega_max^2 (1/s^2) of M^-1 K for each (scene hash, model, options, at) computed in this process, at
#: "rest" or at the "settled" state (with the relaxation's rtol): a sweep asks for the same model's
#: critical step at every step fraction, and the eigenvalue and, for a non-linear model, the first
#: settling behind it are what its critical step costs.
_OMEGA2: dict[tuple, float] = {}


def _omega2_key(scene: Scene, model_name: str, options: dict | None, *at) -> tuple:
    return (scene.sha256(), model_name, json.dumps(options or {}, sort_keys=True, default=str), *at)


def _omega2_rest(scene: Scene, model, options: dict | None = None) -> float:
    key = _omega2_key(scene, model.name, options, "rest")
    if key not in _OMEGA2:
        _OMEGA2[key] = max_eigenvalue(model)
    return _OMEGA2[key]


#: The most implicit Euler steps a static settling takes (it settles in tens where it settles at all).
IMPLICIT_MAX_STEPS = 20_000


@dataclass
class Settled:
    """A static scene settled by a time-stepping model (``settled``): the state at equilibrium, the
    steps it took from rest and the final relative residual, the step dt and the explicit critical step
    dt_crit (s) (the one dt was chosen from, or, for implicit Euler, the limit it steps over), omega_max^2
    (1/s^2) behind dt_crit, the settling's wall time (s) when it ran, and implicit Euler's CG iterations
    in its last step (-1 for an explicit integrator)."""

    state: State
    steps: int
    residual: float
    dt: float
    dt_crit: float
    omega2: float
    wall_s: float
    cg_iterations: int = -1


def settled_path(scene: Scene, model_name: str, integrator: str, dt, dt_fraction, rtol, max_steps, options) -> Path:
    """Where ``settled`` keeps a settling (it holds no timing, so no machine in its key)."""
    fields = {
        "code": code_digest(RUN_CODE),
        "scene": scene.sha256(),
        "model": model_name,
        "integrator": integrator,
        "dt": dt,
        "fraction": dt_fraction,
        "rtol": rtol,
        "max_steps": max_steps,
        "options": json.dumps(options or {}, sort_keys=True, default=str),
    }
    return cache_dir() / "settled" / f"{scene.name}-{digest(fields)}.npz"


#: Settled's fields after the state, as the cache file stores them.
_SETTLED_NUMBERS = ("steps", "residual", "dt", "dt_crit", "omega2", "wall_s", "cg_iterations")


def settled(
    scene: Scene,
    model,
    integrator: str = "symplectic-euler",
    dt: float | None = None,
    dt_fraction: float | None = None,
    rtol: float = 1e-10,
    max_steps: int = 2_000_000,
    options: dict | None = None,
) -> Settled:
    """A static scene settled from rest by ``model`` (a Model) with ``integrator``, through a cache of
    settlings: the report settles its static scenes ahead on every core (``prefetch.settle_ahead``) and
    times the steps afterwards on a quiet machine. Raises DivergenceError or NotConvergedError as the
    solvers do (nothing is cached then).

    - Explicit: damped dynamics (``solve_static``) at dt, default ``dt_fraction`` (default 0.9) of the
      critical step; a non-linear model's is the smaller of rest's and equilibrium's (it moves as the
      body deforms).
    - Implicit Euler: steps of dt (default 2 / omega_1, the slowest mode's time scale, which it damps by
      1/sqrt(5) a step; or ``dt_fraction`` of the explicit critical step), at most IMPLICIT_MAX_STEPS.
    """
    path = settled_path(scene, model.name, integrator, dt, dt_fraction, rtol, max_steps, options)
    kept = read_cached(path, _read_settled)
    if kept is not None:
        return kept
    integ = make_integrator(integrator, scene.time.damping_mass, scene.time.damping_stiffness)
    omega2 = _omega2_rest(scene, model, options)
    t1 = time.perf_counter()
    if isinstance(integ, ImplicitEuler):
        dt_crit = SymplecticEuler().critical_dt(model, omega2)
        if dt is None:
            dt = 2.0 / math.sqrt(min_eigenvalue(model)) if dt_fraction is None else dt_fraction * dt_crit
        static = solve_static_implicit(
            model, dt, rtol=rtol, integrator=integ, max_steps=min(max_steps, IMPLICIT_MAX_STEPS)
        )
        cg = integ.iterations
    else:
        dt_crit = integ.critical_dt(model, omega2)
        static, cg = None, -1
        if not model.linear:
            key = _omega2_key(scene, model.name, options, "settled", rtol)
            if key not in _OMEGA2:
                static = solve_static(model, dt=None, rtol=rtol, max_steps=max_steps)
                _OMEGA2[key] = max_eigenvalue(model, static.state.u)
            omega2 = max(omega2, _OMEGA2[key])
            dt_crit = min(dt_crit, integ.critical_dt(model, omega2))
        if dt is None:
            dt = (0.9 if dt_fraction is None else dt_fraction) * dt_crit
        if static is None or static.dt != dt:
            ticker = Progress(f"settling: {scene.name} / {model.name}, step", rank=_rank())
            try:
                static = solve_static(
                    model,
                    dt=dt,
                    rtol=rtol,
                    max_steps=max_steps,
                    progress=lambda taken, residual: ticker.tick(
                        taken, f": residual {residual:.2e} of the load (asked {rtol:.0e})"
                    ),
                )
            except DivergenceError as exc:
                _refuse_unbounded(scene, exc)
                raise
    out = Settled(static.state, static.steps, static.residual, dt, dt_crit, omega2, time.perf_counter() - t1, cg)
    numbers = {k: getattr(out, k) for k in _SETTLED_NUMBERS}
    atomic_savez(path, u=out.state.u, v=out.state.v, t=out.state.t, state_steps=out.state.steps, **numbers)
    return out


def _read_settled(path: Path) -> Settled:
    """A Settled as ``settled`` keeps it (an .npz of the state and _SETTLED_NUMBERS)."""
    with np.load(path) as z:
        state = State(u=z["u"], v=z["v"], t=float(z["t"]), steps=int(z["state_steps"]))
        return Settled(state, *(z[k].item() for k in _SETTLED_NUMBERS))


def model_for(scene: Scene, model: str, **options):
    """The real-time model of a scene, with its loading."""
    mesh = scene.mesh
    loading = build_loading(mesh, scene.densities(), scene.problem)
    if model == "adaptive-tm":  # its mixed mesh gets the scene's loads as exactly as the scene's mesh
        from realtime.adaptive import adaptive_plan

        plan = adaptive_plan(mesh.points, mesh.tets, scene.body_material(), loading, **options)
        mixed = TetMesh(plan.points, plan.tets, source=f"{mesh.source} adaptive")
        densities = scene.densities()[plan.parent]
        options = {**options, "plan": plan, "mixed_loading": build_loading(mixed, densities, scene.problem_on(mixed))}
    return build_model(model, mesh.points, mesh.tets, scene.body_material(), loading, **options)


def time_steps(model, integrator, dt: float, state, n: int = 100, repeats: int = 9) -> dict:
    """Median and spread of the wall time of one step, after a warm-up call, in microseconds.

    ``state`` is advanced (use a copy). Each repeat times n steps in one compiled call.
    """
    integrator.step(model, state, dt, 1)  # warm-up: compilation, caches
    per_step = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        integrator.step(model, state, dt, n)
        per_step.append((time.perf_counter() - t0) / n * 1e6)
    per_step = np.sort(per_step)
    return {
        "step_us": float(np.median(per_step)),
        "step_us_min": float(per_step[0]),
        "step_us_max": float(per_step[-1]),
        "timing_steps": n,
        "timing_repeats": repeats,
    }


def run_model(
    scene: Scene,
    model_name: str,
    dt: float | None = None,
    dt_fraction: float | None = None,
    integrator: str = "symplectic-euler",
    rtol: float = 1e-10,
    max_steps: int = 2_000_000,
    options: dict | None = None,
) -> Result:
    """Run a real-time model on a scene: on a static scene damped dynamics at dt until settled (at
    most ``max_steps``, else NotConvergedError), then timing; on a dynamic one the trajectory.

    dt defaults to ``dt_fraction`` (default 0.9) times the model's critical step. A diverging run
    raises DivergenceError. ``options`` go to the model's builder (hybrid-tm's ``threshold``, m).
    """
    t0 = time.perf_counter()
    model = model_for(scene, model_name, **(options or {}))
    build_s = time.perf_counter() - t0
    if scene.time.mode == "dynamic":
        return _run_dynamic(scene, model, integrator, dt, dt_fraction, build_s, options)
    if model_name in QUASI_STATIC:
        return _run_quasi_static(scene, model, build_s)
    integ = make_integrator(integrator, scene.time.damping_mass, scene.time.damping_stiffness)
    static = settled(scene, model, integrator, dt, dt_fraction, rtol, max_steps, options)
    if isinstance(integ, ImplicitEuler):
        return _run_implicit(scene, model, integ, static, build_s, rtol)
    dt, dt_crit, omega2, settle_s = static.dt, static.dt_crit, static.omega2, static.wall_s
    timing = time_steps(model, integ, dt, static.state.copy())
    u = static.state.u
    meta = {
        "solver": "realtime",
        "model": model_name,
        "integrator": integrator,
        "dt": dt,
        "dt_crit": dt_crit,
        "dt_crit_element": realtime.element_critical_dt(model),
        "omega_max": math.sqrt(omega2),
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": scene.mesh.sha256(),
        "static": {
            "method": "damped dynamics (adaptive dynamic relaxation)",
            "steps": static.steps,
            "residual": static.residual,
            "rtol": rtol,
            "wall_s": settle_s,
        },
        "build_s": build_s,
        **timing,
        "realtime_factor": dt / (timing["step_us"] * 1e-6),
        "rate_hz": 1e6 / timing["step_us"],
        "settle_ms": static.steps * timing["step_us"] * 1e-3,
        "versions": versions(),
        "commit": git_commit(),
    }
    return Result(
        scene.mesh.points, scene.mesh.tets, np.zeros(1), observed(model, u)[None], model.reaction(u)[None], meta
    )


def output_times(scene: Scene) -> np.ndarray:
    """0, output_every, 2 output_every, ... up to end (the reference's output instants), s."""
    ts = scene.time
    n = int(round(ts.end / ts.output_every))
    return np.arange(n + 1) * ts.output_every


def observed(model, u: np.ndarray) -> np.ndarray:
    """The displacements (..., N, 3) of the scene's N vertices in a model's u (..., V, 3): all of them,
    but for a model with vertices of its own after the scene's (adaptive-tm's midpoints)."""
    return u[..., : model.extra.get("observed", model.n_vertices), :]


class UnboundedAnswerError(DivergenceError):
    """A static settle blew up because the scene's own answer lies beyond the blow-up guard. To a study
    it is a divergence like any other (the stability study's extremes record it as one), with the
    cause named; to the command line it is the scene's input (exit 2)."""

    def __init__(self, exc: DivergenceError, message: str):
        self.step, self.dt, self.dt_crit, self.reason = exc.step, exc.dt, exc.dt_crit, exc.reason
        RuntimeError.__init__(self, message)


def _refuse_unbounded(scene: Scene, exc: DivergenceError) -> None:
    """After a static settle blew up (``exc``): UnboundedAnswerError when the scene's own answer lies
    beyond the blow-up guard, so that no time step is blamed for it. The answer's size is the P1 linear equilibrium on
    the scene's mesh (a sparse solve where it fits, as the quasi-static models do); a load far too
    large for the stiffness (a unit slip, a soft body under its own weight) puts it past 10 times the
    body, where the guard stops every run at any step. Otherwise nothing: the divergence is the run's."""
    import scipy.sparse.linalg as spla

    from realtime.integrators import blowup_bound
    from realtime.linsolve import FACTOR_LIMIT

    if scene.problem.tools:
        return
    mesh = scene.mesh
    loading = build_loading(mesh, scene.densities(), scene.problem)
    free = np.flatnonzero(loading.free.reshape(-1) != 0.0)
    if not len(free) or len(free) > FACTOR_LIMIT:
        return
    linear = build_model("linear-tm", mesh.points, mesh.tets, scene.body_material(), loading)
    K = linear.rest_stiffness()[free][:, free].tocsc()
    u = spla.spsolve(K, loading.external_force.reshape(-1)[free])
    reach, bound = float(np.abs(u).max()), blowup_bound(linear)
    if np.isfinite(reach) and reach > bound:
        raise UnboundedAnswerError(
            exc,
            f"{scene.path}: load: the scene's own static answer reaches {reach:.3g} m (P1, linear), beyond 10 times "
            f"the body ({bound:.3g} m), where every run stops at any time step: the load is far too large for "
            "this stiffness; lower the load, raise young, or check the units (scale, Pa, kg/m^3)",
        ) from None


def trajectory(model, integ, dt: float, times: np.ndarray, dt_crit: float | None = None):
    """Integrate from rest and sample the state at ``times`` (T,) s by linear interpolation between the
    two steps around each instant (quasi-static models: their equilibrium at each instant, all
    vertices). Returns displacement (T, V, 3) m of all the model's vertices (``observed`` picks the
    scene's) and reaction (T, 3) N."""
    state = model.rest_state()
    out_u = np.zeros((len(times), model.n_vertices, 3))
    out_r = np.zeros((len(times), 3))
    if isinstance(integ, QuasiStatic):  # no history: the equilibrium with the tools where they are at t
        for k, t_out in enumerate(times):
            out_u[k], out_r[k] = integ.equilibrium(model, t_out)
        return out_u, out_r
    ticker = Progress(f"run: {model.name} ({integ.name}, dt = {dt:.3g} s), output", len(times), _rank())
    for k, t_out in enumerate(times):
        ticker.tick(k, f", t = {t_out:.4g} s")
        n = int(np.ceil((t_out - state.t) / dt - 1e-9))
        if n > 1:
            integ.step(model, state, dt, n - 1, dt_crit=dt_crit)
        if n >= 1:
            before, t_before = state.u.copy(), state.t
            integ.step(model, state, dt, 1, dt_crit=dt_crit)
            w = (t_out - t_before) / (state.t - t_before)
            out_u[k] = (1.0 - w) * before + w * state.u
        else:
            out_u[k] = state.u
        out_r[k] = model.reaction(out_u[k])
    return out_u, out_r


def _run_dynamic(scene: Scene, model, integrator: str, dt, dt_fraction, build_s: float, options=None) -> Result:
    """A dynamic scene: the trajectory from rest at the scene's output times."""
    ts = scene.time
    times = output_times(scene)
    if model.name in QUASI_STATIC:
        integ, dt_crit, dt_crit_rest = QuasiStatic(), None, None
        dt = dt if dt is not None else ts.output_every
    else:
        integ = make_integrator(integrator, ts.damping_mass, ts.damping_stiffness)
        omega2 = _omega2_rest(scene, model, options)
        explicit = SymplecticEuler(ts.damping_mass, ts.damping_stiffness).critical_dt(model, omega2)
        dt_crit = dt_crit_rest = explicit
        default = 10.0 if isinstance(integ, ImplicitEuler) else 0.9
        if dt is None:
            dt = (default if dt_fraction is None else dt_fraction) * dt_crit
    t1 = time.perf_counter()
    u, reaction = trajectory(model, integ, dt, times, dt_crit=dt_crit)
    run_s = time.perf_counter() - t1
    slow = isinstance(integ, (ImplicitEuler, QuasiStatic))
    last = u[-1].astype(model.dtype)
    timing = time_steps(
        model, integ, dt, State(u=last, v=np.zeros_like(last), t=ts.end), n=5 if slow else 100, repeats=7
    )
    meta = {
        "solver": "realtime",
        "model": model.name,
        "integrator": integ.name,
        "dt": dt,
        "dt_crit": dt_crit,
        "dt_crit_rest": dt_crit_rest,
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": scene.mesh.sha256(),
        "mode": "dynamic",
        "static": {
            "method": "trajectory",
            "steps": int(np.ceil(ts.end / dt)),
            "residual": None,
            "rtol": None,
            "wall_s": run_s,
        },
        "build_s": build_s,
        **timing,
        "realtime_factor": dt / (timing["step_us"] * 1e-6),
        "rate_hz": 1e6 / timing["step_us"],
        "settle_ms": None,
        "versions": versions(),
        "commit": git_commit(),
    }
    return Result(scene.mesh.points, scene.mesh.tets, times, observed(model, u), reaction, meta)


def _run_implicit(scene: Scene, model, integ, static: Settled, build_s, rtol) -> Result:
    """Implicit Euler on a static scene, settled (``settled``): its steps timed at the equilibrium.
    dt_crit reports the explicit limit it steps over."""
    dt, explicit, omega2, settle_s = static.dt, static.dt_crit, static.omega2, static.wall_s
    timing = time_steps(model, integ, dt, static.state.copy(), n=5, repeats=7)
    u = static.state.u
    meta = {
        "solver": "realtime",
        "model": model.name,
        "integrator": integ.name,
        "dt": dt,
        "dt_crit": explicit,
        "dt_crit_rest": explicit,
        "dt_crit_element": realtime.element_critical_dt(model),
        "omega_max": math.sqrt(omega2),
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": scene.mesh.sha256(),
        "static": {
            "method": "implicit Euler steps",
            "steps": static.steps,
            "residual": static.residual,
            "rtol": rtol,
            "wall_s": settle_s,
            "cg_iterations_last_step": static.cg_iterations,
        },
        "build_s": build_s,
        **timing,
        "realtime_factor": dt / (timing["step_us"] * 1e-6),
        "rate_hz": 1e6 / timing["step_us"],
        "settle_ms": static.steps * timing["step_us"] * 1e-3,
        "versions": versions(),
        "commit": git_commit(),
    }
    return Result(
        scene.mesh.points, scene.mesh.tets, np.zeros(1), observed(model, u)[None], model.reaction(u)[None], meta
    )


def _run_quasi_static(scene: Scene, model, build_s: float) -> Result:
    """Precomputed and condensed models: one update to equilibrium; its time is the step time."""
    integ = QuasiStatic()
    t1 = time.perf_counter()
    u, reaction = integ.equilibrium(model)
    solve_s = time.perf_counter() - t1
    timing = time_steps(model, integ, 1e-3, State.at_rest(model.n_vertices), n=5, repeats=9)
    meta = {
        "solver": "realtime",
        "model": model.name,
        "integrator": integ.name,
        "dt": None,
        "dt_crit": None,
        "dt_crit_element": None,
        "omega_max": None,
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": scene.mesh.sha256(),
        "static": {
            "method": "quasi-static update (precomputed responses / condensed surface system)",
            "steps": 1,
            "residual": None,
            "rtol": None,
            "wall_s": solve_s,
        },
        "build_s": build_s,
        **timing,
        "realtime_factor": None,
        "rate_hz": 1e6 / timing["step_us"],
        "settle_ms": timing["step_us"] * 1e-3,
        "versions": versions(),
        "commit": git_commit(),
    }
    return Result(scene.mesh.points, scene.mesh.tets, np.zeros(1), observed(model, u)[None], reaction[None], meta)


def error_budget(scene: Scene, model_name: str, res: Result, ref: Result, integrator: str, max_steps: int) -> dict:
    """Which part of a model's error is whose (docs/architecture.md section 6), each an L2 distance over
    the scene's vertices and output times relative to the converged reference's norm, like ``rel_l2``:

    - ``mesh``: the P1 finite-element solution of the scene's law on the scene's mesh against the
      converged reference: what any P1 model on this mesh pays (locking, a coarse mesh), whatever it is;
    - ``model``: the model against that P1 solution: what the model's own shortcuts cost (linearity,
      lumping, springs, condensation, an unsettled run);
    - ``time`` (dynamic scenes, time-stepping models): the model at its step against the same model at
      an eighth of it; the model part is then taken at the eighth, so the parts do not overlap.

    ``dominant`` names the largest. The parts are distances between solutions over one norm, so by the
    triangle inequality |mesh - model| - time <= total <= mesh + model + time; a total far below the sum
    is errors cancelling (mass-spring's missing Poisson effect against P1's locking). A P1 reference that
    cannot solve leaves ``mesh`` None with the reason.
    """
    from reference.errors import ReferenceSolveError

    out = {"mesh": None, "model": None, "time": None}
    try:
        p1 = reference_result(scene, **P1_OWN_MESH)
    except ReferenceSolveError as exc:
        out["why"] = f"no P1 solution on this mesh: {exc}"
        return out
    scale = max(float(np.linalg.norm(ref.displacement)), 1e-300)

    def distance(a, b):
        return float(np.linalg.norm(a - b)) / scale

    out["mesh"] = distance(p1.displacement, ref.displacement)
    model_u = res.displacement
    dt = res.meta.get("dt")
    if scene.time.mode == "dynamic" and dt is not None and model_name not in QUASI_STATIC:
        fine = run_model(scene, model_name, dt=dt / 8.0, integrator=integrator, max_steps=max_steps)
        out["time"] = distance(res.displacement, fine.displacement)
        model_u = fine.displacement
    out["model"] = distance(model_u, p1.displacement)
    out["dominant"] = max((k for k in ("mesh", "model", "time") if out[k] is not None), key=lambda k: out[k])
    return out


def versions() -> dict:
    import numba
    import scipy

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
    }


def float32_twin(scene: Scene, res: Result) -> dict:
    """The run of ``res`` (a float64 explicit run of a model in FLOAT32_MODELS) again with its model
    built in float32, at the same dt: on a dynamic scene the same trajectory, on a static one the same
    number of settling steps (``solve_static``'s ``steps``: a float32 residual cannot say when to
    stop). Returns the float32 run's displacement (T, N, 3) m and its meta: dt, settle_steps and the
    step timing (``time_steps``)."""
    m = res.meta
    t0 = time.perf_counter()
    model = model_for(scene, m["model"], precision="float32")
    build_s = time.perf_counter() - t0
    if scene.time.mode == "dynamic":
        twin = _run_dynamic(scene, model, m["integrator"], m["dt"], None, build_s, {"precision": "float32"})
        return {"displacement": twin.displacement, "dt": m["dt"], "settle_steps": None, **_timing(twin.meta)}
    static = solve_static(model, dt=m["dt"], steps=m["static"]["steps"])
    integ = make_integrator(m["integrator"], scene.time.damping_mass, scene.time.damping_stiffness)
    timing = time_steps(model, integ, m["dt"], static.state.copy())
    u = observed(model, static.state.u).astype(np.float64)[None]
    return {"displacement": u, "dt": m["dt"], "settle_steps": static.steps, **_timing(timing)}


def _timing(meta: dict) -> dict:
    return {k: meta[k] for k in ("step_us", "step_us_min", "step_us_max")}


def compare(
    scene: Scene,
    model_name: str,
    dt: float | None = None,
    dt_fraction: float | None = None,
    integrator: str = "symplectic-euler",
    reference: Result | None = None,
    max_steps: int = 2_000_000,
    vtk: str | None = None,
    budget: bool = True,
    float32: bool = False,
    **ref_options,
) -> dict:
    """Metrics of one model run against the scene's reference (docs/architecture.md section 6).

    A diverging run gives {"status": "diverged", ...} with the step, dt and dt_crit instead of errors.
    ``unrepresented`` lists what the material asks that the model does not represent (fibres, the
    volume penalty: realtime.models.unrepresented): it ran without it, and its errors measure the cost.
    ``vtk`` (a directory or a .pvd path) also writes both displacements and the pointwise error at every
    output time as one ParaView series. ``budget`` adds ``error_budget`` (see ``error_budget``).
    ``float32``: for a model of FLOAT32_MODELS under an explicit integrator, the row's ``float32`` holds
    its float32 twin (``float32_twin``): rel_l2_vs_float64, its distance from this run by the row's own
    metric, beside its rel_l2 against the reference, and its step times; None for the other models.
    """
    # a quasi-static model has its own update whatever integrator was asked for
    base = {
        "scene": scene.name,
        "model": model_name,
        "integrator": "quasi-static" if model_name in QUASI_STATIC else integrator,
    }
    base["unrepresented"] = unrepresented(model_name, scene.body_material())
    ref = reference if reference is not None else reference_result(scene, **{**REFERENCE_DEFAULTS, **ref_options})
    try:
        res = run_model(scene, model_name, dt=dt, dt_fraction=dt_fraction, integrator=integrator, max_steps=max_steps)
    except DivergenceError as exc:
        return {
            **base,
            "status": "diverged",
            "dt": exc.dt,
            "dt_crit": exc.dt_crit,
            "step": exc.step,
            "message": str(exc),
            "unbounded": isinstance(exc, UnboundedAnswerError),
        }
    mesh = scene.mesh
    has_tools = bool(scene.problem.tools)
    metrics = compute(
        mesh.points,
        mesh.tets,
        mesh.surface_vertices,
        res.displacement,
        ref.displacement,
        res.reaction if has_tools else None,
        ref.reaction if has_tools else None,
        ref.meta.get("ref_err_estimate"),
    )
    if vtk is not None:
        from .vtk import write_series

        write_series(
            vtk,
            f"{scene.name}-{model_name}",
            mesh.points,
            mesh.tets,
            ref.times,
            {
                "reference_displacement": ref.displacement,
                "model_displacement": res.displacement,
                "error": res.displacement - ref.displacement,
                "error_magnitude": np.linalg.norm(res.displacement - ref.displacement, axis=2),
            },
        )
    m = res.meta
    parts = error_budget(scene, model_name, res, ref, integrator, max_steps) if budget else None
    single = None
    if float32 and model_name in FLOAT32_MODELS and integrator != "implicit-euler":
        twin = float32_twin(scene, res)
        u32 = twin.pop("displacement")
        single = {
            **twin,
            "rel_l2_vs_float64": rel_l2(u32, res.displacement),
            "rel_l2": rel_l2(u32, ref.displacement),
        }
    return {
        **base,
        "status": "ok",
        "error_budget": parts,
        "float32": single,
        "dt": m["dt"],
        "dt_crit": m["dt_crit"],
        "dt_crit_element": m.get("dt_crit_element"),
        **metrics,
        "step_us": m["step_us"],
        "step_us_min": m["step_us_min"],
        "step_us_max": m["step_us_max"],
        "realtime_factor": m["realtime_factor"],
        "rate_hz": m["rate_hz"],
        "settle_steps": m["static"]["steps"],
        "settle_ms": m["settle_ms"],
        "build_s": m.get("build_s"),
        "reference": {
            "degree": ref.meta["degree"],
            "refine": ref.meta["refine"],
            "law": ref.meta["law"],
            "cache_key": ref.meta.get("cache_key"),
            # what the reference's own error is known to be: its bar, or "unverified" without the estimate
            "ref_err_estimate": ref.meta.get("ref_err_estimate"),
            "verified": ref.meta.get("ref_err_estimate") is not None,
            "min_det_F": ref.meta.get("min_det_F"),
            "returned_level": ref.meta.get("returned_level"),
            "petsc_options": ref.meta.get("petsc_options"),
        },
        "n_vertices": mesh.n_vertices,
        "n_tets": mesh.n_tets,
    }
