"""The reference's benchmark (``tissuebench bench --reference``): wall time, Newton iterations and
factorisations of the dolfinx ground truth on the cases that made it the bottleneck (issue 14).

Each case is solved afresh (never from the cache) with the options every study uses, and its row says
what the solve did: degrees of freedom, load steps, Newton iterations, factorisations and seconds, with
and without the error estimate. ``--newton classic`` refactorises at every iteration (the solver before
factorisations were reused, with MUMPS at every size), for a before-and-after comparison.
"""

from __future__ import annotations

import time
from pathlib import Path

from reference import solver
from verification.bench.suite import machine
from verification.progress import log
from verification.runs.reference import reference_result
from verification.scene_file import load_scene

BENCH_SCENES = Path(__file__).parents[1] / "scenes" / "bench"
#: (label, scene, with the estimate): the slender P2 beam with and without its estimate, the
#: 90-degree twisted cylinder, the liver, a dynamic case of about 40 000 dofs and 1600 steps, and a
#: stiff linear beam's dynamics with the estimate (one factorisation a level, back-substitutions).
CASES = (
    ("slender beam P2, no estimate", BENCH_SCENES / "slender-beam.toml", False),
    ("slender beam P2 + estimate", BENCH_SCENES / "slender-beam.toml", True),
    ("cylinder twisted 90 degrees P2 + estimate", BENCH_SCENES / "twisted-cylinder.toml", True),
    ("liver P2 + estimate", "liver", True),
    ("slender beam dynamic P2, 1600 steps", BENCH_SCENES / "slender-beam-dynamic.toml", False),
    ("stiff beam dynamic linear P2 + estimate", BENCH_SCENES / "stiff-beam-dynamic.toml", True),
)


def _solve_row(label: str, scene_ref, estimate: bool) -> dict:
    scene = load_scene(scene_ref)
    log(f"bench --reference: {label} ...")
    t0 = time.perf_counter()
    res = reference_result(scene, degree=2, refine=0, estimate=estimate, use_cache=False)
    wall = time.perf_counter() - t0
    solves = res.meta.get("solves", [])
    return {
        "case": label,
        "scene": scene.name,
        "estimate": estimate,
        "n_dofs": [s.get("n_dofs") for s in solves],
        "load_steps": sum(len(s.get("load_steps", [])) for s in solves),
        "newton_iterations": sum(int(s.get("iterations", 0)) for s in solves),
        "factorisations": sum(int(s.get("factorisations", 0)) for s in solves),
        "wall_s": wall,
        "ref_err_estimate": res.meta.get("ref_err_estimate"),
    }


#: The direct solver before issue 14: MUMPS's unsymmetric LU (the tangents are symmetric; LDL^T came after).
CLASSIC_DIRECT = {"ksp_type": "preonly", "pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}


def run(cases=None, newton: str = "modified") -> dict:
    """Solve each case; ``newton`` "classic" is the solver before issue 14: Newton refactorising at
    every iteration (solver.SLOW and solver.SLOW_DYNAMIC = inf) with MUMPS's LU at every size
    (solver.DIRECT_MEMORY_SHARE = inf). Under ``mpirun -n N`` every case is solved on the N ranks."""
    from mpi4py import MPI

    chosen = [c for c in CASES if cases is None or any(k in c[0] for k in cases)]
    saved = solver.SLOW, solver.SLOW_DYNAMIC, solver.DIRECT_MEMORY_SHARE, solver.DIRECT_OPTIONS
    if newton == "classic":
        solver.SLOW = solver.SLOW_DYNAMIC = solver.DIRECT_MEMORY_SHARE = float("inf")
        solver.DIRECT_OPTIONS = CLASSIC_DIRECT
    try:
        rows = [_solve_row(*c) for c in chosen]
    finally:
        solver.SLOW, solver.SLOW_DYNAMIC, solver.DIRECT_MEMORY_SHARE, solver.DIRECT_OPTIONS = saved
    return {"machine": machine(), "newton": newton, "ranks": MPI.COMM_WORLD.size, "rows": rows}


def format_table(out: dict) -> str:
    lines = [
        f"reference benchmark ({out['newton']} Newton) on {out['machine']['cpu']}, {out['machine']['cores']} cores, "
        f"{out.get('ranks', 1)} MPI rank(s)"
    ]
    lines.append(f"{'case':<44} {'dofs':>16} {'loads':>6} {'Newton':>7} {'factor.':>8} {'seconds':>9}")
    for r in out["rows"]:
        dofs = "+".join(str(d) for d in r["n_dofs"] if d)
        lines.append(
            f"{r['case']:<44} {dofs:>16} {r['load_steps']:>6} {r['newton_iterations']:>7} "
            f"{r['factorisations']:>8} {r['wall_s']:>9.1f}"
        )
    return "\n".join(lines)
