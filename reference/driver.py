"""Reference solutions evaluated at the scene mesh's vertices, with an error bar that means what it says.

With the estimate (the default), the problem is solved at refinement levels R and R + 1 (the mesh cut
uniformly, each tetrahedron into eight) and the finer solution u_{R+1} is returned, with

    ref_err_estimate = |u_R - u_{R+1}| / |u_{R+1}|     (Euclidean norms over the scene's vertices)

which bounds the relative error of the returned u_{R+1} whenever refining at least halves the error
(an observed order of at least one): |e_{R+1}| <= |e_R| / 2 <= (|u_R - u_{R+1}| + |e_{R+1}|) / 2. For a
method of order p in the asymptotic range the bar is 2^p - 1 times the error (3 for P1 displacements,
7 for P2). Tests check it against closed-form and manufactured solutions over a range of meshes.
Dynamic references return the spatially finer run too; their bar adds twice the temporal difference
(dt against dt / 2), which bounds the time error of the dt run in the same way.

With ``estimate = "p3"`` (static, P2) the coarse level is replaced by P3 on the returned mesh: the
returned u_{R+1} is the same, and its bar is

    ref_err_estimate = P3_SAFETY |u_{R+1} - u_{R+1}^P3| / |u_{R+1}^P3|

the error itself within P3's own on that mesh (within 1 -/+ r of it, r = e(P3) / e(P2)), doubled so that it
stays above the error while r < 1/2. Measured against truths two refinements finer on nine cases
(``tissuebench effectivity``, docs/effectivity.md): 1.1 to 2.2 times the true error, where the bar above
is 1.7 to 9.3 times it.
"""

from __future__ import annotations

import platform
import time

import numpy as np
from mpi4py import MPI

from meshes import TetMesh
from realtime.material import Material, Materials

from .errors import ReferenceSolveError
from .levels import P3_SAFETY, relative, solve_level
from .problem import Problem
from .progress import Heartbeat, line


def levels_of(degree: int, refine: int, estimate) -> list[tuple[int, int]]:
    """The (degree, refinement) of each solve of a static reference: ``estimate`` False, the one returned;
    True, refinements R and R + 1 (the finer returned, last); "p3", P2 and P3 at R + 1 (the P2 returned,
    first); "adaptive", the returned level's P2 and P3, on its adapted mesh (``restore_static`` rebuilds
    them from the mesh ``solved_fields`` keeps; the refine count only names where adapting started)."""
    if estimate in ("p3", "adaptive"):
        if degree != 2:
            raise ValueError(f"estimate {estimate} checks a P2 reference against P3; degree is {degree}")
        return [(2, refine + 1), (3, refine + 1)] if estimate == "p3" else [(2, refine), (3, refine)]
    return [(degree, refine), (degree, refine + 1)] if estimate else [(degree, refine)]


def _materials_of(material: Material | Materials) -> tuple:
    return material.materials if isinstance(material, Materials) else (material,)


def solve_static(
    mesh: TetMesh,
    material: Material | Materials,
    problem: Problem,
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    comm=MPI.COMM_WORLD,
    newton_steps: int = 1,
    points: np.ndarray | None = None,
    min_increment: float = 1e-4,
    nested: bool = True,
    petsc_options: dict | None = None,
    adapt: dict | None = None,
) -> dict:
    """Solve, evaluate at ``points`` (K, 3) m (default the scene mesh's vertices), describe the run.

    ``estimate = "adaptive"``: ``reference.adaptive.solve_adaptive`` from ``refine``, with ``adapt``'s
    target, budget_s and max_levels; its levels' meshes are then in the dict's ``levels`` (rank 0).

    ``nested``: the refined solve behind the estimate starts from the coarse solution at full load
    (nested iteration) instead of from rest with its own load path; it is the same discrete problem, so
    the answer is the same to Newton's tolerance, in a few iterations instead of a load path.
    Returns a dict: displacement (K, 3) m, reaction (3,) N, meta (dict, JSON-ready), and problems (the
    solved ElasticityProblem of each level, for ``evaluate_static`` at other points).
    """
    import dolfinx

    newton = {"steps": newton_steps, "min_increment": min_increment}
    levels, adaptive = None, None
    if estimate == "adaptive":
        from .adaptive import solve_adaptive

        run = solve_adaptive(
            mesh,
            material,
            problem,
            refine,
            comm=comm,
            newton_steps=newton_steps,
            min_increment=min_increment,
            points=points,
            petsc_options=petsc_options,
            **(adapt or {}),
        )
        problems, infos, levels, adaptive = run["problems"], run["solves"], run["levels"], run["adaptive"]
        unchecked = None if len(problems) > 1 else adaptive["stop"]
    else:
        problems, infos, unchecked = _solve_levels(
            mesh, material, problem, degree, refine, estimate, comm, newton, nested, petsc_options
        )
    meta = {
        "solver": "reference",
        "law": problems[0].law,
        "degree": degree,
        "refine": refine,
        "estimator": {"p3": "p3", "adaptive": "adaptive"}.get(estimate, "difference" if estimate else None),
        "mpi_ranks": comm.size,
        "solves": infos,
        "petsc_options": infos[-1].get("petsc_options"),  # the finest solve's: the choice goes by size
        "petsc_options_per_solve": [i.get("petsc_options") for i in infos],
        "versions": {"dolfinx": dolfinx.__version__, "python": platform.python_version()},
    }
    meta["min_det_F"] = infos[-1].get("min_det_F")
    if adaptive is not None:
        meta["adaptive"] = adaptive
    if unchecked:
        meta["unchecked"] = unchecked
    answer = evaluate_static(problems, meta, mesh.points if points is None else points)
    return {**answer, "problems": problems, "levels": levels}


def _solve_levels(mesh, material, problem, degree, refine, estimate, comm, newton, nested, petsc_options) -> tuple:
    """The uniform levels of ``solve_static`` (``levels_of``): the solved problems, each solve's record,
    and why the solution is unverified (the check level found no equilibrium) or None."""
    from .fem import ElasticityProblem

    problems, infos = [], []
    coarse = unchecked = None
    for deg, level in levels_of(degree, refine, estimate):
        t0 = time.perf_counter()
        same = coarse is not None and coarse.refine == level  # P3 beside P2: its mesh, from its solution
        domain = coarse.domain if same else None
        ep = ElasticityProblem(mesh, material, problem, degree=deg, refine=level, comm=comm, domain=domain)
        try:
            start = coarse if nested and coarse is not None and (coarse.degree == deg or same) else None
            info = solve_level(ep, start, infos, newton, petsc_options)
        except ReferenceSolveError as exc:
            if coarse is None:  # nothing converged: nothing is known
                raise
            # the level behind the estimate failed where the solution it checks converged: that solution
            # is kept, said to be unverified, and the reason is kept with it
            unchecked = f"the check at refine {level} found no equilibrium (P{deg}: {exc})"
            line(f"reference: {unchecked}; returning refine {coarse.refine}, whose error is not estimated", comm.rank)
            break
        coarse = ep
        problems.append(ep)
        info.update(
            level=level,
            degree=deg,
            n_dofs=ep.n_dofs,
            n_cells=ep.domain.topology.index_map(3).size_global,
            wall_s=time.perf_counter() - t0,
            **ep.timings,
        )
        infos.append(info)
    return problems, infos, unchecked


def solved_fields(problems: list) -> dict[str, np.ndarray]:
    """What ``restore_static`` needs to rebuild a serial static solve without solving: each level's
    displacement dofs (m) and its dof coordinates (m), by which the rebuilt space is checked."""
    out = {}
    for k, ep in enumerate(problems):
        out[f"u{k}"] = ep.u.x.array.copy()
        out[f"x{k}"] = ep.V.tabulate_dof_coordinates().copy()
    if getattr(problems[0], "adapted", None) is not None:  # an adapted mesh: no refine count rebuilds it
        out["mesh_x"], out["mesh_cells"] = problems[0].adapted
    return out


def restore_static(
    mesh: TetMesh,
    material: Material | Materials,
    problem: Problem,
    degree: int,
    refine: int,
    fields: dict,
    estimate=True,
) -> list | None:
    """The solved problems of a serial ``solve_static`` rebuilt from ``solved_fields``: each level's space
    made again and its displacement set, for ``evaluate_static`` (seconds, where the solve took tens).
    None when a rebuilt space does not number its dofs at the same points (another dolfinx, another
    partition): the caller then solves."""
    from .fem import ElasticityProblem

    problems, domain = [], None
    if "mesh_x" in fields:
        from .adaptive import distributed

        domain = distributed(fields["mesh_x"], fields["mesh_cells"], MPI.COMM_SELF)
    solved = levels_of(degree, refine, estimate)[: sum(1 for key in fields if key.startswith("u"))]
    for k, (deg, level) in enumerate(solved):
        ep = ElasticityProblem(mesh, material, problem, degree=deg, refine=level, comm=MPI.COMM_SELF, domain=domain)
        x = ep.V.tabulate_dof_coordinates()
        if x.shape != fields[f"x{k}"].shape or not np.array_equal(x, fields[f"x{k}"]):
            return None
        ep.u.x.array[:] = fields[f"u{k}"]
        ep.u.x.scatter_forward()
        problems.append(ep)
    return problems


def evaluate_static(problems: list, meta: dict, points: np.ndarray) -> dict:
    """The answer of a static solve at ``points`` (K, 3) m, from the solved problems of its levels
    (``solve_static``'s "problems": R, and R + 1 with the estimate) and its ``meta``, which is copied, not
    changed: the same solve evaluated anywhere in the body (a refined scene's vertices), with the
    estimate over those points. Collective under MPI."""
    import copy

    values = [ep.evaluate(points) for ep in problems]
    reactions = [ep.reaction() for ep in problems]
    meta = copy.deepcopy(meta)
    refine = meta["refine"]
    adapted = meta.get("adaptive")
    p3 = meta.get("estimator") in ("p3", "adaptive")
    kept = 0 if p3 else -1  # the returned solve: p3's P2 is the first, the difference's finer level the last
    on = (
        f"refine {refine + 1}"
        if adapted is None
        else f"the mesh adapted {adapted['returned']} times from refine {refine}"
    )
    if len(problems) > 1:
        factor = P3_SAFETY if p3 else 1.0
        # |u_R - u_R+1| / |u_R+1| (difference), |u_R+1 - u_R+1^P3| / |u_R+1^P3| (p3): the second solve's norm
        bars = [relative(a[0], a[1]) for a in (values, reactions)]
        # None where the checking solution is zero (no load, or no tool: 0 / 0), never a zero bar
        meta["ref_err_estimate"], meta["ref_reaction_err_estimate"] = (None if b is None else factor * b for b in bars)
        meta["returned_level"] = refine + 1 if adapted is None else refine
        meta["estimate"] = (
            f"{P3_SAFETY:g} |u2 - u3| / |u3| at the scene vertices, P2 and P3 on {on}: the returned P2 "
            "solution's error within P3's own on the same mesh, doubled"
            if p3
            else f"|u_R - u_R+1| / |u_R+1| at the scene vertices (R = {refine}); the returned solution is u_R+1, "
            "and the estimate bounds its relative error when refining at least halves the error"
        )
    else:
        meta["returned_level"] = refine + 1 if p3 and adapted is None else refine
        meta["estimate"] = "none: reference unverified" + (f"; {meta['unchecked']}" if meta.get("unchecked") else "")
    return {"displacement": values[kept], "reaction": reactions[kept], "meta": meta}


def dynamic_bars(u: tuple, r: tuple, refine: int) -> dict:
    """A dynamic reference's bars from its runs' displacements u = (u_R, u_R+1, u_R at dt / 2), each
    (T, N, 3) m, and tool forces r, the same three (T, 3) N: space + 2 time for each, relative."""
    space = float(np.linalg.norm(u[0] - u[1]) / max(np.linalg.norm(u[1]), 1e-300))
    tim = float(np.linalg.norm(u[0] - u[2]) / max(np.linalg.norm(u[2]), 1e-300))
    # the tools' force by the same rule (what a haptic verdict is judged against); none without a tool
    f_space, f_time = relative(r[0], r[1]), relative(r[0], r[2])
    return dict(
        ref_err_estimate=space + 2.0 * tim,
        ref_err_space=space,
        ref_err_time=tim,
        ref_reaction_err_estimate=None if f_space is None or f_time is None else f_space + 2.0 * f_time,
        ref_reaction_err_space=f_space,
        ref_reaction_err_time=f_time,
        returned_level=refine + 1,
        estimate=f"|u_R - u_R+1| + 2 |u_dt - u_dt/2| (relative, over vertices and output times, R = {refine}); "
        "the returned trajectory is u_R+1 at dt, and the estimate bounds its error when halving h or dt at "
        "least halves each part",
    )


#: Newmark's average-acceleration rule is second order in dt (the trapezoidal rule; Hughes, The Finite
#: Element Method, 9.1): the error of the run at dt is 2^2 / (2^2 - 1) = 4/3 of its difference to dt / 2.
NEWMARK_RICHARDSON = 4.0 / 3.0


def dynamic_p3_bars(u: tuple, r: tuple, refine: int) -> dict:
    """A dynamic reference's ``p3`` bars, from its runs' displacements u = (u2, u3, u2 at dt / 2) at
    refinement R + 1, each (T, N, 3) m (P2 returned, P3 beside it at the same dt, P2 at half the step),
    and tool forces r, the same three (T, 3) N: space P3_SAFETY |u2 - u3| / |u3| (the static p3 bar: the
    same dt, so the time error cancels) plus time NEWMARK_RICHARDSON |u_dt - u_dt/2| / |u_dt/2| (on the
    returned mesh: the time error's direction follows the modes that mesh resolves), relative."""
    space = P3_SAFETY * float(np.linalg.norm(u[0] - u[1]) / max(np.linalg.norm(u[1]), 1e-300))
    tim = NEWMARK_RICHARDSON * float(np.linalg.norm(u[0] - u[2]) / max(np.linalg.norm(u[2]), 1e-300))
    f_space, f_time = relative(r[0], r[1]), relative(r[0], r[2])
    known = f_space is not None and f_time is not None
    return dict(
        ref_err_estimate=space + tim,
        ref_err_space=space,
        ref_err_time=tim,
        ref_reaction_err_estimate=P3_SAFETY * f_space + NEWMARK_RICHARDSON * f_time if known else None,
        ref_reaction_err_space=None if f_space is None else P3_SAFETY * f_space,
        ref_reaction_err_time=None if f_time is None else NEWMARK_RICHARDSON * f_time,
        returned_level=refine + 1,
        estimator="p3",
        estimate=f"{P3_SAFETY:g} |u2 - u3| + {NEWMARK_RICHARDSON:.3g} |u_dt - u_dt/2| (relative, over vertices "
        f"and output times, P2 and P3 at refine {refine + 1}): the returned P2 trajectory's space error within "
        "P3's own, doubled, plus its time error by Richardson for Newmark's second order",
    )


def solve_dynamic(
    mesh: TetMesh,
    material: Material | Materials,
    problem: Problem,
    end: float,
    output_every: float,
    rayleigh=(0.0, 0.0),
    degree: int = 2,
    refine: int = 0,
    estimate: bool | str = True,
    substeps: int = 4,
    comm=MPI.COMM_WORLD,
    points: np.ndarray | None = None,
    petsc_options: dict | None = None,
) -> dict:
    """Newmark trajectory from rest at ``points`` (K, 3) m (default the scene mesh's vertices), every
    ``output_every`` up to ``end``.

    The time step is output_every / substeps. With the estimate, the returned trajectory is the one at
    refinement R + 1 (and dt), and ``ref_err_estimate`` = space + 2 time bounds its relative error when
    halving h or dt at least halves the error of each: space = |u_R - u_R+1| / |u_R+1| (same dt), time
    = |u_dt - u_dt/2| / |u_dt/2| (level R), norms over all vertices and output times. ``estimate =
    "p3"``: the same trajectory, its bar from P3 and dt / 2 on its own mesh (``dynamic_p3_bars``).
    Returns a dict: times (T,), displacement (T, N, 3), reaction (T, 3), meta.
    """
    import dolfinx

    from .fem import ElasticityProblem

    dt = output_every / substeps

    def run(level, step, deg=degree):
        t0 = time.perf_counter()
        # building the level and Newmark's set-up (its first solves, a mass factorisation) report nothing
        # of their own: a heartbeat until the time loop, which reports itself
        what = f"reference: P{deg} refine {level}, dt {step:.3g} s: building and setting up Newmark"
        with Heartbeat(what, comm.rank) as hb:
            ep = ElasticityProblem(mesh, material, problem, degree=deg, refine=level, comm=comm)
            run = ep.solve_dynamic(
                step,
                end,
                output_every,
                mesh.points if points is None else points,
                rayleigh=rayleigh,
                petsc_options=petsc_options,
                before_loop=hb.stop,
            )
        run.info.update(level=level, degree=deg, n_dofs=ep.n_dofs, wall_s=time.perf_counter() - t0)
        return run.times, run.values, run.reactions, run.info

    if estimate == "p3" and degree != 2:
        raise ValueError(f"estimate p3 checks a P2 reference against P3; degree is {degree}")
    # p3: P2 at R + 1 returned, P3 beside it and P2 at dt / 2 there; else u_R, u_R+1 and u_R at dt / 2
    first = refine + 1 if estimate == "p3" else refine
    times, vals, reac, info = run(first, dt)
    meta = dict(solver="reference", law="+".join(sorted({m.law for m in _materials_of(material)})), degree=degree)
    meta.update(refine=refine, mode="dynamic", dt=dt, mpi_ranks=comm.size, petsc_options=info["petsc_options"])
    meta["versions"] = {"dolfinx": dolfinx.__version__, "python": platform.python_version()}
    meta.update(returned_level=refine, estimate="none: reference unverified", solves=[info])
    if estimate == "p3":
        _, p3, p3_reac, i3 = run(first, dt, 3)
        _, half, half_reac, i2 = run(first, dt / 2)
        meta["solves"] += [i3, i2]
        meta.update(dynamic_p3_bars((vals, p3, half), (reac, p3_reac, half_reac), refine))
    elif estimate:
        _, fine_space, fine_reac, i2 = run(refine + 1, dt)
        _, fine_time, fine_time_reac, i3 = run(refine, dt / 2)
        meta["solves"] += [i2, i3]
        meta.update(dynamic_bars((vals, fine_space, fine_time), (reac, fine_reac, fine_time_reac), refine))
        vals, reac = fine_space, fine_reac
    return {"times": times, "displacement": vals, "reaction": reac, "meta": meta}
