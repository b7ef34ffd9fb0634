"""Static reference solutions evaluated at the scene mesh's vertices, with their own error estimate.

``ref_err_estimate`` is |u_R - u_{R+1}| / |u_{R+1}| over the scene's vertices, u_R the returned
solution at refinement level R and u_{R+1} the same problem on the uniformly refined mesh: the
difference between two refinement levels, which for a converging discretisation bounds the error of
the coarser one from above up to a factor 2^p / (2^p - 1) (p the observed order). It is
a serious estimate only in the asymptotic range; the harness shows it beside every error.
"""

from __future__ import annotations

import platform
import time

import numpy as np
from mpi4py import MPI

from meshes import TetMesh
from realtime.material import Material

from .problem import Problem


def solve_static(
    mesh: TetMesh,
    material: Material,
    problem: Problem,
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    comm=MPI.COMM_WORLD,
    newton_steps: int = 1,
    points: np.ndarray | None = None,
    min_increment: float = 1e-4,
) -> dict:
    """Solve, evaluate at ``points`` (K, 3) m (default the scene mesh's vertices), describe the run.

    Returns a dict: displacement (K, 3) m, reaction (3,) N, meta (dict, JSON-ready).
    """
    import dolfinx

    from .fem import ElasticityProblem

    levels = [refine, refine + 1] if estimate else [refine]
    values, reactions, infos = [], [], []
    for level in levels:
        t0 = time.perf_counter()
        ep = ElasticityProblem(mesh, material, problem, degree=degree, refine=level, comm=comm)
        nonlinear = material.law != "linear" or material.volume_penalty
        info = ep.solve(steps=newton_steps, min_increment=min_increment) if nonlinear else ep.solve()
        values.append(ep.evaluate(mesh.points if points is None else points))
        reactions.append(ep.reaction())
        info.update(
            level=level,
            n_dofs=ep.n_dofs,
            n_cells=ep.domain.topology.index_map(3).size_global,
            wall_s=time.perf_counter() - t0,
            **ep.timings,
        )
        infos.append(info)
    meta = {
        "solver": "reference",
        "law": material.law,
        "degree": degree,
        "refine": refine,
        "mpi_ranks": comm.size,
        "solves": infos,
        "petsc_options": infos[0].get("petsc_options"),
        "versions": {"dolfinx": dolfinx.__version__, "python": platform.python_version()},
    }
    if estimate:
        den = np.linalg.norm(values[1])
        meta["ref_err_estimate"] = float(np.linalg.norm(values[0] - values[1]) / den) if den > 0 else 0.0
        rden = np.linalg.norm(reactions[1])
        meta["ref_reaction_err_estimate"] = (
            float(np.linalg.norm(reactions[0] - reactions[1]) / rden) if rden > 0 else 0.0
        )
        meta["estimate"] = f"|u_R - u_R+1| / |u_R+1| at the scene vertices, R = {refine}"
    return {"displacement": values[0], "reaction": reactions[0], "meta": meta}


def solve_dynamic(
    mesh: TetMesh,
    material: Material,
    problem: Problem,
    end: float,
    output_every: float,
    rayleigh=(0.0, 0.0),
    degree: int = 2,
    refine: int = 0,
    estimate: bool = True,
    substeps: int = 4,
    comm=MPI.COMM_WORLD,
) -> dict:
    """Newmark trajectory from rest at the scene mesh's vertices, every ``output_every`` up to ``end``.

    The time step is output_every / substeps. ``ref_err_estimate`` is the larger of the spatial
    estimate (refinement R against R + 1, same dt) and the temporal one (dt against dt / 2, level R),
    each |u - u_finer| / |u_finer| over all vertices and output times.
    Returns a dict: times (T,), displacement (T, N, 3), reaction (T, 3), meta.
    """
    import dolfinx

    from .fem import ElasticityProblem

    dt = output_every / substeps

    def run(level, step):
        t0 = time.perf_counter()
        ep = ElasticityProblem(mesh, material, problem, degree=degree, refine=level, comm=comm)
        times, vals, reac, info = ep.solve_dynamic(step, end, output_every, mesh.points, rayleigh=rayleigh)
        info.update(level=level, n_dofs=ep.n_dofs, wall_s=time.perf_counter() - t0)
        return times, vals, reac, info

    times, vals, reac, info = run(refine, dt)
    solves = [info]
    meta = {
        "solver": "reference",
        "law": material.law,
        "degree": degree,
        "refine": refine,
        "mode": "dynamic",
        "dt": dt,
        "mpi_ranks": comm.size,
        "petsc_options": info["petsc_options"],
        "versions": {"dolfinx": dolfinx.__version__, "python": platform.python_version()},
    }
    if estimate:
        _, fine_space, _, i2 = run(refine + 1, dt)
        _, fine_time, _, i3 = run(refine, dt / 2)
        solves += [i2, i3]
        space = float(np.linalg.norm(vals - fine_space) / max(np.linalg.norm(fine_space), 1e-300))
        tim = float(np.linalg.norm(vals - fine_time) / max(np.linalg.norm(fine_time), 1e-300))
        meta.update(
            ref_err_estimate=max(space, tim),
            ref_err_space=space,
            ref_err_time=tim,
            estimate=f"max of |u_R - u_R+1| and |u_dt - u_dt/2| over vertices and output times, R = {refine}",
        )
    meta["solves"] = solves
    return {"times": times, "displacement": vals, "reaction": reac, "meta": meta}
