"""An adaptive static reference: P2 refined where its error lives, checked against P3 at every level.

At each level the problem is solved with P2 and with P3 on the same mesh (P3 from the P2 solution,
interpolated: a few Newton iterations). The level's bar is the ``p3`` estimate of ``reference.driver``,

    bar = P3_SAFETY |u2 - u3| / |u3|     (Euclidean norms over the points the answer is asked at),

and the per-cell indicator is the energy of their difference in the cell (J),

    eta_K^2 = integral over K of  2 mu |eps(e)|^2 + lambda tr(eps(e))^2,   e = u3 - u2,

with the cell's own material's Lame constants: the hierarchical error estimator of Bank and Smith
(SIAM J. Numer. Anal. 30, 1993), whose higher-degree correction is solved here rather than
approximated. While the bar is over ``target``, the fewest cells holding DOERFLER of the summed eta^2
are marked (Dorfler, SIAM J. Numer. Anal. 33, 1996), their edges refined (dolfinx's Plaza refinement,
which closes the marked set into a conforming mesh), and the next level solved from the last P2
solution. It stops when the bar is within ``target``, when the next level is predicted to overrun
``budget_s`` (its time the last level's scaled by its cells to the power GROWTH), or after
``max_levels``. The answer is the last P2 solution whose P3 check converged, with that check's bar.

The adapted meshes are made on rank 0 alone and then distributed, as ``reference.forms.dolfinx_mesh``
makes a uniform refinement: Plaza's closure follows the local numbering, which a partition changes, and
the answer must not depend on the number of ranks. Each level's mesh, indicator and P2 displacement at
its vertices are kept (``levels``) for ``reference --vtk``.
"""

from __future__ import annotations

import time

import numpy as np
from mpi4py import MPI

from .errors import ReferenceSolveError
from .progress import line, within

#: Dorfler's bulk parameter: the marked cells hold at least this share of the summed indicator.
DOERFLER = 0.5
#: How a level's solve time grows with its cells, for the budget's prediction of the next level. The
#: cantilever's adapted levels grew as cells^1.3 (1.6 s at 1 787 cells to 39 s at 24 228); a direct
#: factorisation in 3D grows as dofs^2 asymptotically, so the prediction takes a little more than measured.
GROWTH = 1.5


def mesh_arrays(domain) -> tuple[np.ndarray, np.ndarray]:
    """A serial dolfinx mesh's vertices (N, 3) float64, m, and tetrahedra (M, 4) int64 (its geometry)."""
    x = domain.geometry.x[:, :3].copy()
    cells = domain.geometry.dofmap.array.reshape(-1, 4).astype(np.int64)
    return x, cells


def distributed(x: np.ndarray, cells: np.ndarray, comm):
    """The dolfinx mesh of rank 0's vertices ``x`` (N, 3) m and tetrahedra ``cells`` (M, 4), shared out over
    ``comm`` (the other ranks' arrays are ignored)."""
    import ufl
    from dolfinx import mesh as dmesh

    element = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
    if comm.rank != 0:
        x, cells = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    return dmesh.create_mesh(comm, cells, x, element)


def energy_indicator(p2, p3) -> tuple[np.ndarray, np.ndarray]:
    """Each of this rank's cells' midpoint (n, 3) m and eta^2 (n,) J: the energy of u3 - u2 in the cell
    (module docstring), ``p2`` and ``p3`` solved problems on one mesh (``ElasticityProblem``)."""
    import ufl
    from dolfinx import fem
    from dolfinx import mesh as dmesh

    diff = fem.Function(p3.V)
    diff.interpolate(p2.u)  # exact: P2 lies in P3
    diff.x.array[:] = p3.u.x.array - diff.x.array
    diff.x.scatter_forward()
    W = fem.FunctionSpace(p3.domain, ("DG", 0))
    w = ufl.TestFunction(W)
    eps = ufl.sym(ufl.grad(diff))
    form = 0
    for m, dx in p3.parts:
        density = 2.0 * p3._constant(m.mu) * ufl.inner(eps, eps) + p3._constant(m.lam) * ufl.tr(eps) ** 2
        form += density * w * dx
    vec = fem.petsc.assemble_vector(fem.form(form))
    n = p3.domain.topology.index_map(3).size_local
    eta2 = vec.array[:n].copy()
    mid = dmesh.compute_midpoints(p3.domain, 3, np.arange(n, dtype=np.int32))
    return mid, eta2


def doerfler(eta2: np.ndarray, theta: float = DOERFLER) -> np.ndarray:
    """The fewest cells whose eta2 (M,) sum to at least ``theta`` of the total: bool (M,). Ties broken by
    index, so the marking is the same on every machine."""
    order = np.argsort(-eta2, kind="stable")
    total = float(eta2.sum())
    marked = np.zeros(len(eta2), dtype=bool)
    if total <= 0.0:
        return marked
    cum = np.cumsum(eta2[order])
    k = int(np.searchsorted(cum, theta * total)) + 1
    marked[order[: min(k, len(eta2))]] = True
    return marked


def on_rank0(x: np.ndarray, cells: np.ndarray, mid: np.ndarray, eta2: np.ndarray, comm) -> np.ndarray | None:
    """Every rank's cells' eta2, gathered to rank 0 in the order of its ``cells`` (M,) J (matched by the
    cells' midpoints, which no partition moves); None on the other ranks."""
    from scipy.spatial import cKDTree

    mids, etas = comm.gather(mid, root=0), comm.gather(eta2, root=0)
    if comm.rank != 0:
        return None
    mine = x[cells].mean(axis=1)
    dist, idx = cKDTree(mine).query(np.concatenate(mids))
    size = float(np.ptp(x, axis=0).max())
    if np.any(dist > 1e-9 * size):
        raise ReferenceSolveError("the adapted mesh's cells could not be matched across ranks")
    out = np.zeros(len(cells))
    out[idx] = np.concatenate(etas)  # a cell is owned by one rank: each index comes once
    return out


def refine_marked(x: np.ndarray, cells: np.ndarray, marked: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The mesh (x (N, 3) m, cells (M, 4)) with every edge of the ``marked`` (M,) bool cells cut, closed
    into a conforming mesh by Plaza's refinement (serial); returns the refined (x, cells)."""
    from dolfinx import mesh as dmesh
    from scipy.spatial import cKDTree

    domain = distributed(x, cells, MPI.COMM_SELF)
    domain.topology.create_entities(1)
    domain.topology.create_connectivity(3, 1)
    # create_mesh renumbers the cells: find the marked ones by their midpoints
    n = domain.topology.index_map(3).size_local
    mine = dmesh.compute_midpoints(domain, 3, np.arange(n, dtype=np.int32))
    _, local = cKDTree(mine).query(x[cells[marked]].mean(axis=1))
    c2e = domain.topology.connectivity(3, 1)
    edges = np.unique(np.concatenate([c2e.links(c) for c in local]).astype(np.int32))
    return mesh_arrays(dmesh.refine(domain, edges, redistribute=False))


def _level_problems(mesh, material, problem, x, cells, previous, infos, opts) -> tuple:
    """One level's P2 solve (from ``previous``, the last level's P2) and its P3 check on the same mesh:
    (p2, p3 or None where the check found no equilibrium, its reason). Raises ReferenceSolveError when
    the P2 solve does."""
    from .fem import ElasticityProblem
    from .levels import solve_level
    from .progress import Heartbeat

    comm, newton, petsc_options = opts["comm"], opts["newton"], opts["petsc_options"]
    k, t0 = len(infos) // 2, time.perf_counter()
    n_cells = comm.bcast(None if cells is None else len(cells), root=0)
    with Heartbeat(f"reference: adaptive level {k}: building P2 on {n_cells} cells", comm.rank):
        p2 = ElasticityProblem(mesh, material, problem, degree=2, comm=comm, domain=distributed(x, cells, comm))
    info = solve_level(p2, previous, infos, newton, petsc_options)
    infos.append({**info, "level": k, "degree": 2, "n_dofs": p2.n_dofs, "wall_s": time.perf_counter() - t0})
    t0 = time.perf_counter()
    with Heartbeat(f"reference: adaptive level {k}: building P3 on {n_cells} cells", comm.rank):
        p3 = ElasticityProblem(mesh, material, problem, degree=3, comm=comm, domain=p2.domain)
    try:
        info = solve_level(p3, p2, infos, newton, petsc_options)
        infos.append({**info, "level": k, "degree": 3, "n_dofs": p3.n_dofs, "wall_s": time.perf_counter() - t0})
    except ReferenceSolveError as exc:
        return p2, None, f"its P3 check: {_first_clause(exc)}"
    return p2, p3, None


def _checked(p2, p3, at: np.ndarray, level: dict, k: int, comm) -> dict:
    """A level's record from its P2 solution ``p2`` and P3 check ``p3``: its sizes and its bars (the ``p3``
    bar at ``at`` (K, 3) m and on the tools' force; None where the check is zero), and its indicator into
    ``level`` (rank 0's, by its cells)."""
    from .levels import P3_SAFETY, relative

    pairs = ((p2.evaluate(at), p3.evaluate(at)), (p2.reaction(), p3.reaction()))
    bar, force = (None if (b := relative(*pair)) is None else P3_SAFETY * b for pair in pairs)
    mid, eta2 = energy_indicator(p2, p3)
    level["eta2"] = on_rank0(level["x"], level["cells"], mid, eta2, comm)
    n_cells = comm.bcast(len(level["cells"]) if comm.rank == 0 else None, root=0)
    return {"level": k, "n_cells": n_cells, "n_dofs": p2.n_dofs, "n_dofs_p3": p3.n_dofs, "bar": bar, "force_bar": force}


def _within(bar: float, force: float | None, target: float | None, force_target: float | None) -> bool:
    """Whether a level's bars reach what is asked: the bar within ``target`` and, where a force target is
    asked, the force's bar known and within it (no target: never, the budget or the levels stop it)."""
    if target is None or bar > target:
        return False
    return force_target is None or (force is not None and force <= force_target)


def _first_clause(exc: Exception) -> str:
    """A solve's failure in a clause ("Newton found no equilibrium without inverted elements beyond load
    fraction 0.594"): the stop reason a level's line and the advice quote (the whole message, with what to
    change, is for a user who solves the scene itself)."""
    return str(exc).removeprefix("reference: ").split(" (")[0]


def _where(k: int, records: list, target: float | None) -> str:
    """What a level's progress lines start with: the level, the bar so far and the bar asked."""
    said = [f"bar so far {_shown(records[-1]['bar'])}"] if records else []
    said += [f"asked {target:.3g}"] if target is not None else []
    return f"reference: adaptive level {k}" + (f" ({', '.join(said)})" if said else "")


def _shown(bar: float | None) -> str:
    return "unknown (no load)" if bar is None else f"{bar:.3g}"


def _sizes(record: dict) -> str:
    return f"{record['n_cells']} cells, P2 {record['n_dofs']} dofs, checked by P3 {record['n_dofs_p3']} dofs"


def _next_mesh(x, cells, eta2, record: dict, comm) -> tuple:
    """The next level's mesh (rank 0's vertices and tetrahedra; None on the others): the cells Dorfler
    marks by ``eta2`` refined, and its solve time predicted from ``record``'s (the level just solved)."""
    marked = doerfler(eta2) if comm.rank == 0 else None
    x, cells = refine_marked(x, cells, marked) if comm.rank == 0 else (None, None)
    grown, n_marked = comm.bcast((len(cells) / record["n_cells"], int(marked.sum())) if comm.rank == 0 else None)
    predicted = record["wall_s"] * grown**GROWTH
    line(
        f"reference: adaptive level {record['level'] + 1}: {n_marked} of {record['n_cells']} cells marked "
        f"(Dorfler {DOERFLER:g}), {grown:.2f} times the cells, predicted {predicted:.0f} s",
        comm.rank,
    )
    return x, cells, predicted


def solve_adaptive(
    mesh,
    material,
    problem,
    refine: int = 0,
    target: float | None = None,
    budget_s: float | None = None,
    max_levels: int = 6,
    force_target: float | None = None,
    comm=MPI.COMM_WORLD,
    newton_steps: int = 1,
    min_increment: float = 1e-4,
    points: np.ndarray | None = None,
    petsc_options: dict | None = None,
) -> dict:
    """The adaptive reference (module docstring) of ``problem`` on ``mesh`` refined ``refine`` times
    uniformly to start with, at ``points`` (K, 3) m (default the mesh's vertices): adapted until its bar
    is within ``target`` (and the tools' force's, the same P3 bar on the reaction, within ``force_target``
    where one is given), its next level would overrun ``budget_s`` seconds, or ``max_levels`` levels.

    Returns a dict for ``reference.driver.solve_static``: problems (the returned level's P2 and its P3
    check, or the P2 alone where level 0's check found no equilibrium), solves (each solve's record),
    adaptive (the options, each level's record, why it stopped and the level returned) and levels: on
    rank 0 each level's vertices (N, 3) m, tetrahedra (M, 4), indicator eta^2 (M,) J (None where P3 found
    no equilibrium) and P2 displacement (N, 3) m."""
    from .forms import dolfinx_mesh

    at = mesh.points if points is None else np.ascontiguousarray(points, dtype=float)
    x = cells = None
    if comm.rank == 0:
        x, cells = mesh_arrays(dolfinx_mesh(mesh, MPI.COMM_SELF, refine))
    opts = {"comm": comm, "newton": {"steps": newton_steps, "min_increment": min_increment}}
    opts["petsc_options"] = petsc_options
    start, infos, records, levels, kept, previous, stop = time.perf_counter(), [], [], [], None, None, None
    for k in range(max_levels + 1):
        t0 = time.perf_counter()
        try:
            with within(_where(k, records, target)):
                p2, p3, failed = _level_problems(mesh, material, problem, x, cells, previous, infos, opts)
        except ReferenceSolveError as exc:
            if kept is None:
                raise
            stop = f"level {k}'s P2 solve: {_first_clause(exc)}"
            break
        shown = comm.bcast(x, root=0)
        level = {"x": x, "cells": cells, "eta2": None, "u": p2.evaluate(shown)}
        levels.append(level)
        if p3 is None:
            stop = f"level {k}: {failed}"
            if kept is None:
                kept = (p2, None, k)
            break
        record = _checked(p2, p3, at, level, k, comm)
        record["wall_s"] = time.perf_counter() - t0
        records.append(record)
        kept, previous, bar, force = (p2, p3, k), p2, record["bar"], record["force_bar"]
        wanted = "" if target is None else f" (asked {target:.3g})"
        line(
            f"reference: adaptive level {k}: {_sizes(record)}: bar {_shown(bar)}{wanted} ({record['wall_s']:.0f} s)",
            comm.rank,
        )
        if bar is None or _within(bar, force, target, force_target):
            stop = "no load: nothing to estimate" if bar is None else f"the bar {bar:.3g} is within {target:.3g}"
            break
        if k == max_levels:
            stop = f"{max_levels} levels, the most asked"
            break
        x, cells, predicted = _next_mesh(x, cells, level["eta2"], record, comm)
        spent = time.perf_counter() - start
        if budget_s is not None and spent + predicted > budget_s:
            stop = f"level {k + 1} is predicted at {predicted:.0f} s, past the budget ({spent:.0f} of {budget_s:.0f} s spent)"
            break
    line(f"reference: adaptive: stopped: {stop}", comm.rank)
    p2, p3, returned = kept
    p2.adapted = levels[returned]["x"], levels[returned]["cells"]  # rank 0's; None elsewhere
    adapt = {"target": target, "budget_s": budget_s, "max_levels": max_levels, "doerfler": DOERFLER}
    adapt.update(stop=stop, levels=records, returned=returned)
    return {"problems": [p2] if p3 is None else [p2, p3], "solves": infos, "adaptive": adapt, "levels": levels}
