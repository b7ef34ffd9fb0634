"""The reference of a scene, from the cache or solved now (docs/data-flow.md and docs/metrics.md).

Reference results are cached under ``$TISSUEBENCH_CACHE`` (default ``~/.cache/tissuebench``), keyed by
a hash of everything they depend on: the scene's content and mesh hash, degree, refinement, the
estimate flag, the solver options and the reference code's version. A study interrupted half-way
finds the solves it finished and goes on from there.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

import numpy as np

from meshes.io import atomic_savez

from ..cache import REFERENCE_CODE, code_digest, digest, entry, git_commit, library_versions, read_cached
from ..progress import log
from ..scene import Scene, SceneError
from .results import Result

#: Bumped whenever the reference's numbers can change for the same inputs, so old cache entries die.
REFERENCE_VERSION = "2"  # 2: spanned regions, the finer solution returned, det F checked, exact tool kinematics

REFERENCE_DEFAULTS = {"degree": 2, "refine": 0, "estimate": True}

#: The P1 solution of a scene on its own mesh (the error budget's mesh part).
P1_OWN_MESH = {"degree": 1, "refine": 0, "estimate": False, "own_mesh": True}


def solver_changed(meta: dict, petsc_options: dict | None) -> str:
    """Why a kept reference is not what solving it here now would give, or "": its key holds the rule
    that chooses a direct or an iterative solve by the free memory (``reference.solver.solver_options``),
    and each of its solves records the kind the rule chose then (``chosen``); a solve of that size on
    this machine now must choose the same. A solve that records no choice (a result of an older version)
    is unknown, and unknown is not the same."""
    from reference.solver import solver_family, solver_options

    for s in meta.get("solves") or []:
        n = s.get("n_dofs")
        if n is None:
            continue
        now = solver_family(solver_options(n, petsc_options, linear=bool(s.get("linear"))))
        if s.get("chosen") != now:
            then = s.get("chosen") or "unrecorded"
            return f"its {n}-dof solve was {then}; this machine now chooses {now} for it"
    return ""


def reference_key(
    scene: Scene,
    degree: int,
    refine: int,
    estimate: bool,
    newton=(1, 1e-4),
    own_mesh: bool = False,
    petsc_options: dict | None = None,
    adapt: dict | None = None,
) -> str:
    from reference.solver import DIRECT_MEMORY_SHARE, DIRECT_OPTIONS, GAMG_OPTIONS

    return digest(
        {
            "scene": scene.sha256(),
            "solved_on": "own mesh" if own_mesh or not scene.level else "base mesh",
            "degree": degree,
            "refine": refine,
            "estimate": estimate,
            **({"adapt": adapt} if adapt else {}),  # the adaptive estimate's target, budget and levels
            "newton": list(newton),
            "solver": {
                "direct": DIRECT_OPTIONS,
                "gamg": GAMG_OPTIONS,
                "direct_where_the_factor_fits_in": DIRECT_MEMORY_SHARE,
                "user": petsc_options,
            },
            "version": REFERENCE_VERSION,
            "code": code_digest(REFERENCE_CODE),
            "libraries": library_versions(),
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


def levels_path(reference: Path) -> Path:
    """Beside an adaptive reference, its levels: each adapted mesh (vertices m, tetrahedra), its
    indicator eta^2 (J per cell) and its P2 displacement at the vertices (m), for ``reference --vtk``."""
    return reference.with_name(reference.stem + "-levels.npz")


def _save_levels(path: Path, levels: list[dict]) -> None:
    arrays = {}
    for k, level in enumerate(levels):
        arrays.update({f"x{k}": level["x"], f"cells{k}": level["cells"], f"u{k}": level["u"]})
        if level["eta2"] is not None:
            arrays[f"eta2_{k}"] = level["eta2"]
    atomic_savez(path, **arrays)


def read_levels(path: Path) -> list[dict]:
    """``_save_levels``'s levels, in order (eta2 None where that level's P3 check found no equilibrium)."""
    with np.load(path) as data:
        n = sum(1 for key in data.files if key.startswith("cells"))
        return [
            {
                "x": data[f"x{k}"],
                "cells": data[f"cells{k}"],
                "u": data[f"u{k}"],
                "eta2": data[f"eta2_{k}"] if f"eta2_{k}" in data.files else None,
            }
            for k in range(n)
        ]


def reference_path(
    scene: Scene,
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    newton_steps: int = 1,
    min_increment: float = 1e-4,
    own_mesh: bool = False,
    petsc_options: dict | None = None,
    adapt: dict | None = None,
) -> Path:
    """Where ``reference_result`` with these arguments keeps its answer."""
    newton = (newton_steps, min_increment)
    key = reference_key(scene, degree, refine, estimate, newton, own_mesh, petsc_options, adapt)
    return entry("reference", scene.name, key, ".npz")


def _save_solved(path: Path, problems: list, meta: dict) -> None:
    from reference.driver import solved_fields

    arrays = solved_fields(problems)
    atomic_savez(path, meta=np.array(json.dumps(meta)), **arrays)


def _restore_solved(memo: tuple, path: Path, solved: Scene, material, degree: int, refine: int, estimate) -> None:
    """Into _SOLVED, the solve kept at ``path`` (_save_solved) rebuilt; nothing if it cannot be."""
    from reference.driver import restore_static

    def read(path):
        with np.load(path) as data:
            return {k: data[k] for k in data.files if k != "meta"}, json.loads(str(data["meta"]))

    kept = read_cached(path, read)
    if kept is None:  # a damaged file: solve again
        return
    arrays, meta = kept
    problems = restore_static(solved.mesh, material, solved.problem, degree, refine, arrays, estimate)
    if problems is not None:
        _SOLVED[memo] = problems, meta
        while len(_SOLVED) > SOLVED_KEPT:
            _SOLVED.pop(next(iter(_SOLVED)))


def reference_result(
    scene: Scene,
    degree: int = 2,
    refine: int = 0,
    estimate: bool | str = True,
    use_cache: bool = True,
    newton_steps: int = 1,
    min_increment: float = 1e-4,
    own_mesh: bool = False,
    petsc_options: dict | None = None,
    adapt: dict | None = None,
) -> Result:
    """The scene's reference, from the cache or solved now (and then cached). ``newton_steps`` and
    ``min_increment`` set the non-linear static solve's first load increment (1 / newton_steps) and the
    smallest increment it may halve to before it gives up.

    On a refined scene (``Scene.refined``) the reference is solved on the base scene's mesh and
    evaluated at the refined vertices: the truth does not depend on the mesh a model runs on, and the
    base's solve (with its estimate) costs 8^level times less. ``own_mesh`` solves on the scene's own
    mesh instead (the error budget's P1 solution on the model's mesh). ``petsc_options`` go over the
    solver chosen by size (``reference.solver.solver_options``). ``estimate = "adaptive"``: the mesh adapted
    where the error lives (``reference.adaptive``) with ``adapt``'s target, budget_s and max_levels; its
    levels' meshes and indicator are kept beside the result (``levels_path``)."""
    from mpi4py import MPI

    if estimate == "adaptive" and scene.time.mode == "dynamic":
        raise SceneError(f"{scene.path}: the adaptive estimate adapts a static P2 reference; this scene is dynamic")
    path = reference_path(scene, degree, refine, estimate, newton_steps, min_increment, own_mesh, petsc_options, adapt)
    cached = read_cached(path, Result.load) if use_cache else None
    if cached is not None and (changed := solver_changed(cached.meta, petsc_options)):
        log(f"reference: {path.name}: {changed}: solving it again")
        cached = None
    if cached is not None:
        return cached
    if scene.events:  # one static reference per state (``runs.staged``)
        from .staged import staged_reference

        opts = dict(degree=degree, refine=refine, estimate=estimate, use_cache=use_cache, newton_steps=newton_steps)
        opts.update(min_increment=min_increment, own_mesh=own_mesh, petsc_options=petsc_options, adapt=adapt)
        res = staged_reference(scene, lambda state, points: reference_at(state, points, **opts))
        if use_cache and MPI.COMM_WORLD.rank == 0:
            res.save(path)
        return res
    mesh = scene.mesh
    solved = scene if own_mesh or not scene.level else scene.base
    where = f" on the base mesh at the {mesh.n_vertices} vertices of level {scene.level}" if solved is not scene else ""
    check = {True: " + estimate", "p3": " + its check by P3", "adaptive": " adapted, checked by P3"}.get(estimate, "")
    log(f"reference: {scene.name} P{degree} refine {refine}{check}{where} ...")
    t0 = time.perf_counter()
    if scene.time.mode == "dynamic":
        sol = _solve_dynamic(scene, solved, degree, refine, estimate, petsc_options)
        times, disp, reac = sol["times"], sol["displacement"], sol["reaction"]
    else:
        newton = (newton_steps, min_increment)
        sol = _solve_static(scene, solved, degree, refine, estimate, newton, petsc_options, use_cache, adapt=adapt)
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
        if sol.get("levels"):
            _save_levels(levels_path(path), sol["levels"])
    log(f"reference: done in {meta['wall_s']:.1f} s")
    return res


def _solve_dynamic(
    scene: Scene, solved: Scene, degree: int, refine: int, estimate: bool, petsc_options, points=None
) -> dict:
    """The dynamic reference of ``solved`` (the scene, or its base) at ``points`` (K, 3) m (default
    ``scene``'s vertices)."""
    from reference.driver import solve_dynamic

    ts = scene.time
    return solve_dynamic(
        solved.mesh,
        solved.body_material(),
        solved.problem,
        ts.end,
        ts.output_every,
        rayleigh=(ts.damping_mass, ts.damping_stiffness),
        degree=degree,
        refine=refine,
        estimate=estimate,
        points=scene.mesh.points if points is None else points,
        petsc_options=petsc_options,
    )


def _memo(solved: Scene, degree, refine, estimate, newton_steps, min_increment, petsc_options, adapt=None) -> tuple:
    """The key of a static solve kept in this process (``_SOLVED``)."""
    options = json.dumps([petsc_options or {}, adapt or {}], sort_keys=True)
    return (solved.sha256(), degree, refine, estimate, newton_steps, min_increment, options)


def _solve_static(
    scene: Scene,
    solved: Scene,
    degree,
    refine,
    estimate,
    newton: tuple,
    petsc_options,
    use_cache,
    points=None,
    adapt: dict | None = None,
):
    """The static reference of ``solved`` (the scene, or its base) at ``points`` (default ``scene``'s
    vertices): the same problem solved before in this process (``_SOLVED``) or kept beside its cached
    result evaluated there, else solved (and kept). ``newton``: (the first load increment's inverse,
    the smallest increment); ``adapt``: the adaptive estimate's options."""
    at = scene.mesh.points if points is None else points
    from mpi4py import MPI

    from reference.driver import evaluate_static, solve_static

    newton_steps, min_increment = newton
    memo = _memo(solved, degree, refine, estimate, newton_steps, min_increment, petsc_options, adapt)
    serial = MPI.COMM_WORLD.size == 1
    fields = _fields_path(
        reference_path(solved, degree, refine, estimate, newton_steps, min_increment, False, petsc_options, adapt)
    )
    if use_cache and memo not in _SOLVED and serial and solved is not scene and fields.exists():
        _restore_solved(memo, fields, solved, solved.body_material(), degree, refine, estimate)
    if use_cache and memo in _SOLVED:  # use_cache=False asks for a solve (the benchmarks time it)
        log("reference: the same problem was solved before: evaluated at these vertices")
        return evaluate_static(*_SOLVED[memo], at)
    sol = solve_static(
        solved.mesh,
        solved.body_material(),
        solved.problem,
        degree=degree,
        refine=refine,
        estimate=estimate,
        newton_steps=newton_steps,
        min_increment=min_increment,
        points=at,
        petsc_options=petsc_options,
        adapt=adapt,
    )
    problems = sol.pop("problems")
    if use_cache:
        _SOLVED[memo] = problems, copy.deepcopy(sol["meta"])
        if serial and estimate and solved is scene:
            _save_solved(fields, problems, sol["meta"])
    while len(_SOLVED) > SOLVED_KEPT:
        _SOLVED.pop(next(iter(_SOLVED)))
    return sol


def reference_at(scene: Scene, points: np.ndarray, **options) -> Result:
    """The scene's reference (``reference_result`` with ``options``) evaluated at ``points`` (K, 3) m
    instead of the scene mesh's vertices: where another engine, on a mesh of its own, wrote its answer.
    A static reference is the same solve (kept in this process or beside its cached result) evaluated
    there; a dynamic one is solved again, evaluating those points at every output, and cached under the
    points' hash. Every point must lie in the body (ReferenceSolveError naming the first that does not)."""
    import hashlib

    from reference.driver import evaluate_static

    options = {**REFERENCE_DEFAULTS, **options}
    points = np.ascontiguousarray(points, dtype=float)
    base = reference_result(scene, **options)  # solved (and kept) at the vertices first
    if np.array_equal(points, scene.mesh.points):
        return base
    empty = np.zeros((0, 4), dtype=np.int64)
    if scene.time.mode == "dynamic":
        key = digest({"reference": base.meta["cache_key"], "points": hashlib.sha256(points.tobytes()).hexdigest()})
        path = entry("reference", f"{scene.name}-at", key, ".npz")
        cached = read_cached(path, Result.load)
        if cached is not None:
            return cached
        sol = _solve_dynamic(scene, scene, options["degree"], options["refine"], options["estimate"], None, points)
        res = Result(points, empty, sol["times"], sol["displacement"], sol["reaction"], {**base.meta, **sol["meta"]})
        res.save(path)
        return res
    degree, refine, estimate = options["degree"], options["refine"], options["estimate"]
    newton = (options.get("newton_steps", 1), options.get("min_increment", 1e-4))
    petsc, adapt = options.get("petsc_options"), options.get("adapt")
    if scene.level and not options.get("own_mesh"):  # a refined scene's truth is its base's, evaluated here
        sol = _solve_static(scene, scene.base, degree, refine, estimate, newton, petsc, True, points, adapt)
        meta = {**base.meta, **sol["meta"]}
        return Result(points, empty, np.zeros(1), sol["displacement"][None], sol["reaction"][None], meta)
    memo = _memo(scene, degree, refine, estimate, *newton, petsc, adapt)
    fields = _fields_path(reference_path(scene, degree, refine, estimate, *newton, False, petsc, adapt))
    if memo not in _SOLVED and fields.exists():
        _restore_solved(memo, fields, scene, scene.body_material(), degree, refine, estimate)
    if memo not in _SOLVED:  # nothing kept to evaluate: solve again there
        sol = _solve_static(scene, scene, degree, refine, estimate, newton, petsc, False, points, adapt)
    else:
        sol = evaluate_static(*_SOLVED[memo], points)
    return Result(
        points, empty, np.zeros(1), sol["displacement"][None], sol["reaction"][None], {**base.meta, **sol["meta"]}
    )


def contact_summary(meta: dict) -> list[dict]:
    """Each rigid tool's force and contact area as the truth states them, with bars, from a reference's
    ``meta`` (its solves' ``contact`` records, reference.static): the force (3,) N of the returned
    solve at its stiffest penalty, its bar the difference to the other level's plus the penalty's
    error; the area m^2 of the returned solve at its first penalty (the penetrated region's edge is
    lost in round-off as the penalty stiffens on a fixed mesh), its bar the difference to the other
    level's plus its change when the penalty stiffens. [] for a scene without tools; a bar is None
    when the reference solved one level (unknown, never zero)."""
    solves = [s for s in meta.get("solves", []) if s.get("contact")]
    if not solves:
        return []
    mine = [s for s in solves if s.get("level") == meta.get("returned_level") and s.get("degree") == meta.get("degree")]
    returned = mine[0] if mine else solves[0]
    other = next((s for s in solves if s is not returned), None)
    out = []
    for k in range(len(returned["contact"][0]["area"])):
        force = np.asarray(returned["contact"][-1]["force"][k])
        area = returned["contact"][0]["area"][k]
        row = {"tool": k, "force": force.tolist(), "area": area, "force_bar": None, "area_bar": None}
        row["curve"] = _curve(returned, other, k)
        if other is not None:
            penalty_area = abs(returned["contact"][1]["area"][k] - area)
            row["force_bar"] = float(np.linalg.norm(force - np.asarray(other["contact"][-1]["force"][k])))
            row["force_bar"] += returned["penalty_error"]["force"][k]
            row["area_bar"] = abs(area - other["contact"][0]["area"][k]) + penalty_area
        out.append(row)
    return out


def _curve(returned: dict, other: dict | None, k: int) -> list[dict]:
    """Tool k's force-indentation curve from the returned solve's stations (reference.static): at each
    fraction of the travel, the force (3,) N and area m^2 at the first penalty, and the force's bar: the
    other level's difference at the same fraction plus the penalty's error at the end in proportion to
    the force (the penetration is the pressure over kappa); None without another level."""
    theirs = {round(s["fraction"], 12): s for s in (other or {}).get("contact_curve", [])}
    end = np.linalg.norm(returned["contact"][-1]["force"][k]) or 1.0
    out = []
    for station in returned.get("contact_curve", []):
        force = np.asarray(station["force"][k])
        match = theirs.get(round(station["fraction"], 12))
        bar = None
        if match is not None:
            bar = float(np.linalg.norm(force - np.asarray(match["force"][k])))
            bar += returned["penalty_error"]["force"][k] * float(np.linalg.norm(force)) / end
        out.append(
            {"fraction": station["fraction"], "force": force.tolist(), "area": station["area"][k], "force_bar": bar}
        )
    return out
