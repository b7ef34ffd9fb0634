"""Side by side with the engines users pick: NVIDIA newton and pbatoolkit, timed with ours in one run.

    make bench-peers          # its own venv (.venv-peers): installs newton and pbatoolkit from PyPI

Never part of ``make test``: it needs the two peers, which the suite does not. Every row runs on one
core (the process is pinned to CPU 0, so that no library spreads over both and a ratio compares like
with like) on the same meshes and the same material (E = 28 kPa, nu = 0.4, rho = 1000 kg/m^3), in
rounds that interleave the rows (``bench._time_round_robin``), so the ratios are measured together.
Each timed call follows an untimed one of the same row, so that every row runs with its data in the
caches whatever ran before it.

pbatoolkit 0.0.11's wheel links the Tracy profiler, whose import starts a sampling thread that
interrupts the whole process: with it, every row of the run (ours included) was about 20% slower
(stvk-tm on the liver 93.8 against 77.7 us). This module turns Tracy's sampling off
(``TRACY_NO_SAMPLING``) before pbatoolkit is imported.

- ours: microseconds per step of symplectic Euler (force and update) for each model, and scipy's BSR
  product with linear-tm's stiffness;
- newton (warp on the CPU, float32): ``SolverSemiImplicit.step`` on a soft mesh (its stable
  Neo-Hookean tetrahedra; particle contacts and triangle contacts off, as no contact acts), and its
  tetrahedral force alone (``eval_tetrahedra_forces``);
- pbatoolkit (float64): the StVK energy's gradient (``fem.hyper_elastic_potential``), the work of one
  explicit force evaluation.

The meshes: the structured unit cube of 11^3 cells (7986 tetrahedra, the one the peers' numbers are
usually quoted on) and the stored liver.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time
from pathlib import Path

import numpy as np

from realtime.models import corotational_tm, linear_tm, mass_spring, stvk_tm

# before pbatoolkit is imported (see the module docstring): its Tracy profiler samples the process
os.environ.setdefault("TRACY_NO_SAMPLING", "1")
os.environ.setdefault("TRACY_NO_CONTEXT_SWITCH", "1")
os.environ.setdefault("TRACY_NO_SYS_TRACE", "1")

from meshes import stored_mesh  # noqa: E402
from meshes.generators import structured_cube  # noqa: E402
from meshes.io import atomic_write_text  # noqa: E402
from realtime import Loading, Material, State, SymplecticEuler, build_model  # noqa: E402
from verification.bench.suite import _step_case, _time_round_robin, machine  # noqa: E402
from verification.progress import log  # noqa: E402

MATERIAL = Material(2.8e4, 0.4, 1000.0, law="stvk")
PEERS = {"newton": "1.8.0", "pbatoolkit": "0.0.11"}
MODELS = (linear_tm.NAME, mass_spring.NAME, stvk_tm.NAME, corotational_tm.NAME)


def _meshes() -> dict:
    return {"cube-11": structured_cube(11), "liver": stored_mesh("liver")}


def _held_bottom(mesh) -> Loading:
    free = np.ones((mesh.n_vertices, 3))
    free[mesh.points[:, 2] < mesh.points[:, 2].min() + 1e-9] = 0.0
    return Loading(free=free, external_force=np.zeros((mesh.n_vertices, 3)))


def _ours(mesh, u0: np.ndarray, steps: int) -> list[dict]:
    cases = []
    loading = _held_bottom(mesh)
    for name in MODELS:
        model = build_model(name, mesh.points, mesh.tets, MATERIAL, loading)
        integ = SymplecticEuler()
        dt = 0.5 * integ.critical_dt(model)
        state = State(u=u0.copy(), v=np.zeros_like(u0))
        cases.append(
            {
                "name": f"tissuebench {name}",
                "engine": "tissuebench",
                "n": steps,
                "fn": _step_case(integ, model, state, dt, steps),
            }
        )
        if name == linear_tm.NAME:
            K = model.extra["tensors"].matrix().tobsr(blocksize=(3, 3))
            x = u0.ravel().copy()

            def bsr(K=K, x=x, reps=steps):
                for _ in range(reps):
                    K @ x

            cases.append({"name": "scipy BSR K u", "engine": "scipy", "n": steps, "fn": bsr})
    return cases


def _newton(mesh, u0: np.ndarray, steps: int) -> list[dict]:
    import warp as wp

    wp.config.quiet = True
    import newton
    from newton._src.solvers.semi_implicit.solver_semi_implicit import eval_tetrahedra_forces

    builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
    builder.add_soft_mesh(
        pos=(0.0, 0.0, 0.0),
        rot=wp.quat_identity(),
        scale=1.0,
        vel=(0.0, 0.0, 0.0),
        vertices=[tuple(p) for p in mesh.points + u0],
        indices=mesh.tets.ravel().tolist(),
        density=MATERIAL.density,
        k_mu=MATERIAL.mu,
        k_lambda=MATERIAL.lam,
        k_damp=0.0,
        add_surface_mesh_edges=False,
    )
    model = builder.finalize(device="cpu")
    model.particle_grid = None  # no particle-particle contact search: nothing touches
    solver = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
    states = [model.state(), model.state()]
    control = model.control()
    dt = 1e-5

    def step(reps=steps):
        for _ in range(reps):
            solver.step(states[0], states[1], control, None, dt)
            states.reverse()
        wp.synchronize()

    def force(reps=steps):
        for _ in range(reps):
            states[0].particle_f.zero_()
            eval_tetrahedra_forces(model, states[0], control, states[0].particle_f)
        wp.synchronize()

    return [
        {"name": "newton SolverSemiImplicit.step (float32)", "engine": "newton", "n": steps, "fn": step},
        {"name": "newton tetrahedral force alone (float32)", "engine": "newton", "n": steps, "fn": force},
    ]


def _pbat(mesh, u0: np.ndarray, steps: int) -> list[dict]:
    import pbatoolkit as pbat

    fem = pbat.pbat.fem
    el = fem.Element.Tetrahedron
    V, C = fem.mesh(mesh.points.T.copy(order="F"), mesh.tets.T.copy(order="F"), element=el, order=1)
    wg = fem.mesh_quadrature_weights(C, V, el, order=1, quadrature_order=1)
    eg = fem.mesh_quadrature_elements(C, wg)
    GNeg = fem.shape_function_gradients(C, V, el, order=1, dims=3, quadrature_order=1)
    nq = wg.size
    x = (V + u0.T).ravel(order="F")
    args = (
        C,
        V.shape[1],
        eg.ravel(order="F"),
        wg.ravel(order="F"),
        GNeg,
        np.full(nq, MATERIAL.mu),
        np.full(nq, MATERIAL.lam),
        x,
    )
    kw = dict(
        energy=fem.HyperElasticEnergy.SaintVenantKirchhoff,
        flags=int(fem.ElementElasticityComputationFlags.Gradient),
        element=el,
        order=1,
        dims=3,
    )
    reps = max(1, steps // 10)

    def gradient(reps=reps):
        for _ in range(reps):
            fem.hyper_elastic_potential(*args, **kw)

    return [{"name": "pbatoolkit StVK gradient (float64)", "engine": "pbatoolkit", "n": reps, "fn": gradient}]


def run(repeats: int = 9, steps: int = 50) -> dict:
    os.sched_setaffinity(0, {0})
    rows = []
    rng = np.random.default_rng(0)
    for label, mesh in _meshes().items():
        log(f"bench-peers: {label} ({mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra): building")
        u0 = 1e-4 * rng.standard_normal(mesh.points.shape) * float(np.ptp(mesh.points, axis=0).max())
        cases = _ours(mesh, u0, steps) + _newton(mesh, u0, steps) + _pbat(mesh, u0, steps)
        log(f"bench-peers: {label}: timing {len(cases)} cases x {repeats} rounds")
        _time_round_robin(cases, repeats, warm=True)
        for c in cases:
            c.pop("fn")
            rows.append({**c, "mesh": label, "n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets})
    return {"machine": {**machine(), "pinned_to_cpu": 0}, "peers": PEERS, "results": rows}


def format_table(out: dict) -> str:
    m = out["machine"]
    lines = [f"machine: {m['cpu']}, one core (pinned), commit {m['commit']}, {m['date']}"]
    for mesh in dict.fromkeys(r["mesh"] for r in out["results"]):
        rows = [r for r in out["results"] if r["mesh"] == mesh]
        ref = next(r["step_us"] for r in rows if r["name"] == "tissuebench stvk-tm")
        lines.append(f"\n{mesh}: {rows[0]['n_vertices']} vertices, {rows[0]['n_tets']} tetrahedra; us per step")
        for r in sorted(rows, key=lambda r: r["step_us"]):
            lines.append(f"  {r['name']:<44} {r['step_us']:>10.1f} us   x{r['step_us'] / ref:7.2f} tissuebench stvk-tm")
    return "\n".join(lines)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(prog="bench_peers", description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=9)
    ap.add_argument("--out", type=Path, help="also write the JSON here")
    args = ap.parse_args(argv)
    for peer, version in PEERS.items():
        try:
            __import__({"newton": "newton", "pbatoolkit": "pbatoolkit"}[peer])
        except ImportError:
            print(f"bench-peers: {peer} {version} is not installed: run `make bench-peers`", file=sys.stderr)
            return 2
    out = run(repeats=args.repeats)
    print(format_table(out))
    if args.out:
        atomic_write_text(args.out, json.dumps(out, indent=1))
    return 0


if __name__ == "__main__":
    t0 = time.perf_counter()
    code = main()
    log(f"bench-peers: done in {time.perf_counter() - t0:.0f} s")
    sys.exit(code)
