"""The reference's linear solvers side by side (``tissuebench bench --solvers``): which preconditioners
Debian's PETSc offers, and how each does on the tangent stiffness of P2 and P3 elasticity as the mesh
is refined and nu goes to 0.49.

The system is the first Newton step's on the liver (``liver``, StVK, its 0.5 N pull): the tangent at
rest, the load as right-hand side, the constraints lifted. Each preconditioner solves it with GMRES to
a relative residual of 1e-8 (MUMPS's factorisation: once, direct), and the row says its dofs, Krylov
iterations, set-up and solve seconds, and the process's peak memory so far (a running maximum). A preconditioner whose
iterations do not grow with the dofs is what a reference past a direct factor's memory needs; one that
fails (a diverged or stalled Krylov solve) says so, with PETSc's reason.

Speed is measured here, never in tests; the numbers are this machine's, written with its description.
"""

from __future__ import annotations

import gc
import time

from verification.bench.suite import machine
from verification.progress import log

#: The preconditioners compared: this project's GAMG (reference.solver.GAMG_OPTIONS, smoothed aggregation
#: with the rigid-body near null space), Trilinos ML's smoothed aggregation (also given the null space),
#: hypre's BoomerAMG with nodal coarsening for the three displacement components, and MUMPS's LDL^T.
PRECONDITIONERS = ("gamg", "ml", "hypre", "mumps")
#: What Debian 12's PETSc 3.18 was built with, from its petscconf.h (PETSC_HAVE_*): the preconditioners
#: and direct solvers a reference on this platform can use without building PETSc.
DEBIAN_PETSC = {
    "multigrid": ("gamg (built in)", "ml (Trilinos ML)", "hypre (BoomerAMG, ParaSails, Euclid, PILUT)"),
    "direct": ("mumps", "superlu", "superlu_dist", "cholmod/umfpack/klu (SuiteSparse)"),
}
#: (degree, refinements of the liver's mesh, nu): P2 on two meshes and P3 on the coarser, at the liver's
#: nu and at 0.49.
CASES = ((2, 0, 0.4), (2, 1, 0.4), (3, 0, 0.4), (2, 0, 0.49), (2, 1, 0.49), (3, 0, 0.49))


def _options(pc: str) -> dict:
    from reference.solver import DIRECT_OPTIONS, GAMG_OPTIONS

    krylov = {"ksp_type": "gmres", "ksp_rtol": 1e-8, "ksp_max_it": 500, "ksp_gmres_restart": 100}
    return {
        "gamg": {**GAMG_OPTIONS, **krylov},
        "ml": {**krylov, "pc_type": "ml", "mg_levels_ksp_type": "chebyshev", "mg_levels_pc_type": "jacobi"},
        # BoomerAMG took 837 iterations (282 s) at nu 0.49 on 30 525 dofs: 100 say as much
        "hypre": {**krylov, "ksp_max_it": 100, "pc_type": "hypre", "pc_hypre_type": "boomeramg", "pc_hypre_boomeramg_nodal_coarsen": 6,
                  "pc_hypre_boomeramg_vec_interp_variant": 3, "pc_hypre_boomeramg_strong_threshold": 0.5},
        "mumps": dict(DIRECT_OPTIONS),
    }[pc]  # fmt: skip


def _system(degree: int, refine: int, poisson: float):
    """The liver's first Newton system (module docstring): (the problem, its operator, right-hand side)."""
    import ufl
    from dolfinx import fem
    from dolfinx.fem import petsc
    from petsc4py import PETSc

    from reference.fem import ElasticityProblem
    from verification.scene_file import load_scene

    scene = load_scene("liver")
    material = scene.material.replace(poisson=poisson)
    ep = ElasticityProblem(scene.mesh, material, scene.problem, degree=degree, refine=refine)
    a = fem.form(ufl.derivative(ep.residual, ep.u, ufl.TrialFunction(ep.V)))
    A = petsc.assemble_matrix(a, bcs=ep.bcs)
    A.assemble()
    b = petsc.assemble_vector(fem.form(ep.residual))
    petsc.apply_lifting(b, [a], bcs=[ep.bcs])
    b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
    petsc.set_bc(b, ep.bcs)
    return ep, A, b


def _solve(ep, A, b, pc: str) -> dict:
    """One solve of A x = b with ``pc`` (``_options``): iterations, seconds, reason, peak memory."""
    from petsc4py import PETSc

    from reference.solver import configure, peak_memory_bytes

    opts = _options(pc)
    if pc in ("gamg", "ml"):
        A.setNearNullSpace(ep.rigid_body_modes())
    ksp = PETSc.KSP().create(ep.comm)
    ksp.setOptionsPrefix(f"tb_bench_{pc}_")
    ksp.setOperators(A)
    configure(ksp, opts)
    x = b.duplicate()
    t0 = time.perf_counter()
    try:
        ksp.setUp()
        t1 = time.perf_counter()
        ksp.solve(b, x)
    except PETSc.Error as exc:
        return {"pc": pc, "failed": f"PETSc error {exc.ierr}", "peak_memory_bytes": peak_memory_bytes(ep.comm)}
    t2 = time.perf_counter()
    reason = ksp.getConvergedReason()
    row = {"pc": pc, "iterations": ksp.getIterationNumber(), "setup_s": t1 - t0, "solve_s": t2 - t1}
    row.update(reason=int(reason), peak_memory_bytes=peak_memory_bytes(ep.comm))
    if reason < 0:
        row["failed"] = f"PETSc reason {reason}"
    ksp.destroy()
    return row


def run(preconditioners=None, cases=None) -> dict:
    """Each case (CASES, or those named whole in ``cases``, else those whose label contains one of them)
    with each preconditioner (default PRECONDITIONERS)."""
    from mpi4py import MPI

    rows = []
    labels = {f"liver P{d} refined {r}, nu {nu:g}": (d, r, nu) for d, r, nu in CASES}
    # a case named whole is that case alone ("nu 0.4" is in "nu 0.49" too)
    chosen = [k for k in labels if k in (cases or ())] or [k for k in labels if not cases or any(c in k for c in cases)]
    for label in chosen:
        degree, refine, poisson = labels[label]
        ep, A, b = _system(degree, refine, poisson)
        for pc in preconditioners or PRECONDITIONERS:
            if pc == "hypre" and (degree, refine) != (2, 0) and not preconditioners:
                continue  # BoomerAMG's 100 iterations took over 5 minutes on 222 003 dofs: the smallest case says enough
            log(f"bench --solvers: {label} ({ep.n_dofs} dofs): {pc} ...")
            row = {"case": label, "degree": degree, "refine": refine, "poisson": poisson, "n_dofs": ep.n_dofs}
            rows.append({**row, **_solve(ep, A, b, pc)})
        del ep, A, b
        gc.collect()
    return {"machine": machine(), "ranks": MPI.COMM_WORLD.size, "petsc": DEBIAN_PETSC, "rows": rows}


def format_table(out: dict) -> str:
    lines = [
        f"the reference's linear solvers on {out['machine']['cpu']}, {out['machine']['cores']} cores, "
        f"{out.get('ranks', 1)} MPI rank(s); Debian's PETSc offers "
        + "; ".join(f"{k}: {', '.join(v)}" for k, v in out["petsc"].items()),
        f"{'case':<32} {'dofs':>9} {'pc':<6} {'its':>5} {'setup s':>8} {'solve s':>8} {'peak GB':>8}",
    ]
    for r in out["rows"]:
        its = r.get("iterations", "")
        lines.append(
            f"{r['case']:<32} {r['n_dofs']:>9} {r['pc']:<6} {its!s:>5} {r.get('setup_s', float('nan')):>8.2f} "
            f"{r.get('solve_s', float('nan')):>8.2f} {r['peak_memory_bytes'] / 1e9:>8.2f}"
            + (f"  failed: {r['failed']}" if r.get("failed") else "")
        )
    return "\n".join(lines)
