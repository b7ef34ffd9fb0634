"""The ``tissuebench`` command (docs/architecture.md section 5).

Exit status: 0 on success; 1 when a model's run blows up (divergence: the step, dt and the critical
one are named); 2 for input the tool cannot use (a scene file, a mesh, an option, a gates file, or a
problem the reference or the model cannot bring to equilibrium as stated), with one line on stderr that
names the file, the key or the element and the value. Any other exception is a bug and keeps its
traceback. With --json, stdout carries one JSON object and nothing else.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from meshes.store import stored_names
from realtime import INTEGRATORS, MODELS, DivergenceError, InputError, NotConvergedError
from reference.errors import ReferenceSolveError
from verification.engines.builtin import UnboundedAnswerError
from verification.inputs import check_held
from verification.scene import implausible
from verification.scene_file import builtin_scenes, load_scene


def _print_json(obj) -> None:
    print(json.dumps(obj, indent=1, default=_default))


def _emit(args, out: dict, text) -> None:
    """The command's result: ``out`` as JSON with --json, else ``text(out)``."""
    if args.json:
        _print_json(out)
    else:
        print(text(out))


def _default(x):
    import numpy as np

    if isinstance(x, np.generic):
        return x.item()
    if isinstance(x, np.ndarray):
        return x.tolist()
    return str(x)


def cmd_scenes(args) -> int:
    rows = []
    for name, path in builtin_scenes().items():
        s = load_scene(path)
        rows.append(
            {
                "name": name,
                "mode": s.time.mode,
                "law": s.material.law,
                "mesh": s.mesh_spec["generator"],
                "description": s.description,
                "path": str(path),
            }
        )
    if args.json:
        _print_json({"scenes": rows})
    else:
        for r in rows:
            print(f"{r['name']:<18} {r['mode']:<8} {r['law']:<7} {r['mesh']:<9} {r['description']}")
    return 0


def _scene(args, warn: bool = True):
    """The command's scene, cut ``--mesh-refine`` more times than its file says; with ``warn``, what
    no soft tissue has (scene.implausible) goes to stderr before any work."""
    scene = load_scene(args.scene, refine=getattr(args, "mesh_refine", 0))
    check_held(scene)
    if warn:
        from verification.progress import log

        for line in implausible(scene):
            log(f"tissuebench: warning: {scene.path}: {line}")
    return scene


def _write_vtk(target: str, name: str, res) -> None:
    """A result's displacements at every output time as a ParaView series (--vtk)."""
    from verification.report.vtk import write_series

    write_series(target, name, res.points, res.tets, res.times, {"displacement": res.displacement})


def _zones(scene) -> list:
    """Each [[material]] table: its region, law constants and how many tetrahedra it holds."""
    import numpy as np

    if not scene.zones:
        return []
    counts = np.bincount(scene.body_material().index, minlength=len(scene.zones))
    return [
        {
            "table": f"material[{k}]",
            "region": region.describe(),
            "tets": int(counts[k]),
            "young_pa": m.young,
            "poisson": m.poisson,
            "density_kg_m3": m.density,
            "wave_speed_m_s": m.wave_speed,
        }
        for k, (region, m) in enumerate(scene.zones)
    ]


def cmd_check(args) -> int:
    """Read a scene as every command does (mesh, regions, loading, a model) and describe it, solving
    nothing: the check to run before a long study."""
    import realtime
    from verification.inputs import build_loading

    scene = _scene(args, warn=False)  # check prints them with the rest
    mesh = scene.mesh
    loading = build_loading(mesh, scene.densities(), scene.problem)
    lo, hi = mesh.bounding_box()
    model = realtime.build_model("linear-tm", mesh.points, mesh.tets, scene.body_material(), loading)
    regions = []
    for i, fx in enumerate(scene.problem.fixed):
        regions.append(
            {"table": f"fixed[{i}]", "region": fx.region.describe(), "vertices": len(fx.region.vertices(mesh))}
        )
    for i, ld in enumerate(scene.problem.loads):
        if hasattr(ld, "region"):
            regions.append(
                {"table": f"load[{i}]", "region": ld.region.describe(), "vertices": len(ld.region.vertices(mesh))}
            )
    m = scene.material
    out = {
        "scene": scene.name,
        "path": str(scene.path),
        "mode": scene.time.mode,
        "law": m.law,
        "mesh": {**mesh.quality(), "sha256": mesh.sha256(), "parts": mesh.parts()[0], "notes": list(mesh.notes)},
        "regions": regions,
        "material": {"lambda_pa": m.lam, "mu_pa": m.mu, "wave_speed_m_s": m.wave_speed},
        "materials": _zones(scene),
        "dt_crit_element_s": realtime.element_critical_dt(model),
        "extent_m": {"min": lo.tolist(), "max": hi.tolist(), "size": (hi - lo).tolist()},
        "warnings": implausible(scene),
    }

    def text(o):
        q = o["mesh"]
        lines = [
            f"{o['scene']} ({o['mode']}, {o['law']}): {q['n_vertices']} vertices, {q['n_tets']} tetrahedra, "
            f"{q['parts']} part(s), dihedral angles {q['min_dihedral_deg']:.1f} to {q['max_dihedral_deg']:.1f} "
            f"degrees, aspect ratio up to {q['max_aspect_ratio']:.2f}"
        ]
        e = o["extent_m"]
        lines.append(
            "  extent: {:.4g} x {:.4g} x {:.4g} m, from ({:.4g}, {:.4g}, {:.4g}) to ({:.4g}, {:.4g}, {:.4g}) m".format(
                *e["size"], *e["min"], *e["max"]
            )
        )
        lines += [f"  warning: {w}" for w in o["warnings"]]
        lines += [f"  mesh repaired: {n}" for n in q["notes"]]
        lines += [
            f"  {z['table']}: {z['region']} holds {z['tets']} tetrahedra: E = {z['young_pa']:.4g} Pa, "
            f"nu = {z['poisson']:.4g}, rho = {z['density_kg_m3']:.4g} kg/m^3"
            for z in o["materials"]
        ]
        lines += [f"  {r['table']}: {r['region']} holds {r['vertices']} vertices" for r in o["regions"]]
        lines.append(f"  element estimate of the explicit critical step: {o['dt_crit_element_s']:.3g} s")
        return "\n".join(lines)

    _emit(args, out, text)
    return 0


def cmd_reference(args) -> int:
    from verification.runs.reference import reference_result

    scene = _scene(args)
    res = reference_result(
        scene,
        degree=args.degree,
        refine=args.refine,
        estimate=not args.no_estimate,
        use_cache=not args.no_cache,
        newton_steps=args.load_steps,
        petsc_options=args.petsc_option,
    )
    from mpi4py import MPI

    if args.out and MPI.COMM_WORLD.rank == 0:
        res.save(args.out)
    if args.vtk and MPI.COMM_WORLD.rank == 0:
        _write_vtk(args.vtk, f"{scene.name}-reference", res)
    summary = {
        "scene": scene.name,
        "out": args.out,
        "max_displacement": float(abs(res.displacement).max()),
        "reaction": res.reaction[-1].tolist(),
        "meta": res.meta,
    }
    if MPI.COMM_WORLD.rank == 0:
        if args.json:
            _print_json(summary)
        else:
            est = res.meta.get("ref_err_estimate")
            print(
                f"{scene.name}: P{args.degree} refine {args.refine}, max |u| = {summary['max_displacement']:.4g} m"
                + (f", ref_err_estimate = {est:.3g}" if est is not None else "")
                + (f", written to {args.out}" if args.out else "")
                + (f"; unverified: {res.meta['unchecked']}" if res.meta.get("unchecked") else "")
            )
    return 0


def cmd_run(args) -> int:
    from verification.runs.simulate import run_model

    scene = _scene(args)
    res = run_model(scene, args.model, dt=args.dt, integrator=args.integrator, max_steps=args.max_steps)
    if args.out:
        res.save(args.out)
    if args.vtk:
        _write_vtk(args.vtk, f"{scene.name}-{args.model}", res)
    m = res.meta
    summary = {
        "scene": scene.name,
        "model": args.model,
        "out": args.out,
        "dt": m["dt"],
        "dt_crit": m["dt_crit"],
        "step_us": m["step_us"],
        "settle_steps": m["static"]["steps"],
        "max_displacement": float(abs(res.displacement).max()),
        "reaction": res.reaction[-1].tolist(),
    }
    if args.json:
        _print_json({**summary, "meta": m})
    else:
        # quasi-static models have no time step, dynamic runs no settling
        step = "quasi-static update" if m["dt"] is None else f"dt = {m['dt']:.3g} s"
        crit = f" (critical {m['dt_crit']:.3g} s)" if m.get("dt_crit") is not None else ""
        settle = f"settled in {m['static']['steps']} steps, " if scene.time.mode == "static" else ""
        print(
            f"{scene.name} / {args.model}: {step}{crit}, {m['step_us']:.1f} us/step, {settle}"
            f"max |u| = {summary['max_displacement']:.4g} m" + (f", written to {args.out}" if args.out else "")
        )
    return 0


def cmd_compare(args) -> int:
    from verification.runs.compare import compare

    scene = _scene(args)
    out = compare(
        scene,
        args.model,
        dt=args.dt,
        integrator=args.integrator,
        degree=args.degree,
        refine=args.refine,
        petsc_options=args.petsc_option,
        max_steps=args.max_steps,
        vtk=args.vtk,
    )
    if args.rate and out["status"] == "ok":
        from verification.studies.advise import frame_budget

        out["frame"] = frame_budget(out, args.rate, scene.time.mode == "dynamic")
    if out.get("unbounded"):  # the scene's own answer is past the blow-up guard: its input, not a step
        return _fail(f"tissuebench: {_one_line(out['message'])}", 2)
    if args.json:
        _print_json(out)
    elif out["status"] != "ok":
        print(out["message"])
    else:
        acc = " (at reference accuracy)" if out["at_reference_accuracy"] else ""
        at = "its quasi-static update" if out["dt"] is None else f"dt = {out['dt']:.3g} s"
        print(f"{scene.name} / {args.model} at {at}:")
        for k in (
            "rel_l2",
            "surface_rel_l2",
            "max_err",
            "reaction_rel_err",
            "volume_err",
            "ref_err_estimate",
            "step_us",
            "realtime_factor",
            "rate_hz",
        ):
            v = out[k]
            print(f"  {k:<18} {'-' if v is None else f'{v:.4g}'}{acc if k == 'rel_l2' else ''}")
        b = out.get("error_budget") or {}
        if b.get("mesh") is not None:
            parts = ", ".join(f"{p} {b[p]:.3g}" for p in ("mesh", "model", "time") if b.get(p) is not None)
            print(f"  {'error_budget':<18} {parts}: the {b['dominant']}'s part dominates")
        if out.get("frame"):
            f = out["frame"]
            print(f"  {'frame':<18} {'holds' if f['holds'] else 'does not hold'} {args.rate:g} Hz: {f['why']}")
        for term in out.get("unrepresented") or []:
            print(f"  {'not represented':<18} {term}: ran without it, and the errors above include what that costs")
    return 0 if out["status"] == "ok" else 1


def cmd_report(args) -> int:
    from verification.report.page import seeds_report_dir, write_report, write_seeds_report

    if args.seeds:
        if args.scenes:
            return _fail("tissuebench: report --seeds takes no scenes (it is the page of the seeds experiments)", 2)
        from verification.studies.seeds import run_seeds

        seeds_report_dir(args.out)  # a directory that cannot be made fails before half an hour of runs
        path = write_seeds_report(run_seeds(), out=args.out)
    else:
        path = write_report(args.scenes or None, out=args.out, fractions=args.fractions)
    print(f"report written to {path}")
    return 0


def cmd_seeds(args) -> int:
    from verification.studies.seeds import EXPERIMENTS, format_seeds, run_seeds, without_pictures

    unknown = [k for k in args.only or () if k not in EXPERIMENTS]
    if unknown:
        return _fail(f"tissuebench: seeds --only {unknown[0]}: not an experiment (known: {', '.join(EXPERIMENTS)})", 2)
    out = run_seeds(args.only)
    if args.json:
        _print_json(without_pictures(out))
    else:
        print(format_seeds(out))
    return 0


def _mpi_comm():
    """The world communicator when running under mpirun with more than one rank, else None."""
    try:
        from mpi4py import MPI
    except ImportError:  # pragma: no cover - mpi4py comes with dolfinx
        return None
    return MPI.COMM_WORLD if MPI.COMM_WORLD.size > 1 else None


def _rank0(comm) -> bool:
    return comm is None or comm.rank == 0


def cmd_sweep(args) -> int:
    from verification.studies.sweep import format_sweep, sweep, sweep_csv

    scene = _scene(args)
    comm = _mpi_comm()
    out = sweep(
        scene,
        models=args.models,
        fractions=args.fractions,
        dts=args.dts,
        integrator=args.integrator,
        largest_stable=not args.no_largest_stable,
        use_cache=not args.no_cache,
        comm=comm,
        float32=args.float32,
    )
    if not _rank0(comm):
        return 0
    if args.csv:
        from verification.runs.results import atomic_write_text

        atomic_write_text(args.csv, sweep_csv(out))
    _emit(args, out, format_sweep)
    return 0


def cmd_converge(args) -> int:
    from verification.studies.converge import converge_manufactured, converge_space, converge_time, format_converge

    scene = _scene(args)
    if scene.manufactured:
        out = converge_manufactured(scene)
    elif args.in_ == "time":
        out = converge_time(scene, models=args.models or ("linear-tm",))
    else:
        out = converge_space(scene, models=args.models or ("linear-tm", "stvk-tm"), levels=args.levels)
    _emit(args, out, format_converge)
    return 0


def cmd_stability(args) -> int:
    from verification.studies.stability import format_stability, stability

    out = stability(_scene(args), models=args.models, tol=args.tol, use_cache=not args.no_cache)
    _emit(args, out, format_stability)
    return 0


def cmd_advise(args) -> int:
    from verification.studies.advise import advise, format_advice

    comm = _mpi_comm()
    scene = _scene(args)
    if not args.no_cache:  # its three independent references on all the cores first (not under mpirun)
        from verification.studies.prefetch import advice_jobs, solve_references

        solve_references(advice_jobs([scene]))
    out = advise(
        scene,
        tol=args.tol,
        rate=args.rate,
        metric=args.metric,
        use_cache=not args.no_cache,
        comm=comm,
        models=args.models,
    )
    if _rank0(comm):
        _emit(args, out, format_advice)
    return 0


def cmd_gate(args) -> int:
    from verification.studies.gates import DEFAULT_CONFIG, format_gates, run_gates, update_baselines

    path = Path(args.config) if args.config else DEFAULT_CONFIG
    # a baseline names the commit that measured it: never a run cached by older code
    rows = run_gates(
        path,
        quick=args.quick,
        use_cache=not (args.no_cache or args.update_baselines),
        baselines=not args.update_baselines,
    )
    if args.update_baselines:
        update_baselines(path, rows)
    out = {"config": str(path), "gates": rows, "passed": all(r["passed"] for r in rows)}
    _emit(args, out, lambda o: format_gates(o["gates"]))
    return 0 if out["passed"] else 1


def cmd_bench(args) -> int:
    if args.reference:
        from mpi4py import MPI

        from verification.bench.reference import format_table, run

        out = run(cases=args.cases, newton=args.newton)
        if MPI.COMM_WORLD.rank:  # under mpirun every rank solved; the first reports
            return 0
    else:
        from verification.bench.suite import format_table, run

        out = run(meshes=args.meshes, repeats=args.repeats)
        if args.markdown:
            from verification.bench.suite import write_markdown

            write_markdown(args.markdown, out)
    if args.out:
        from verification.runs.results import atomic_write_text

        atomic_write_text(args.out, json.dumps(out, indent=1, default=_default))
    _emit(args, out, format_table)
    return 0


VTK_HELP = "also write the displacements (and, for compare, the error) at every output time for ParaView: DIR or F.pvd"


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (the usage is in --help) and exit status 2."""

    def error(self, message):
        self.exit(2, f"{self.prog}: {message} (see {self.prog} --help)\n")


def _positive(text: str) -> float:
    """A finite number > 0, for options such as --dt and --tol."""
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not (value > 0.0 and value < float("inf")):
        raise argparse.ArgumentTypeError(f"{text!r} must be a finite number > 0")
    return value


def _whole(lo: int, hi: int | None = None):
    """An argparse type: a whole number in lo..hi."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not a whole number") from None
        if value < lo or (hi is not None and value > hi):
            raise argparse.ArgumentTypeError(
                f"{text!r} must be {lo} or more" if hi is None else f"{text!r} must be {lo} to {hi}"
            )
        return value

    return parse


_count = _whole(1)
_level = _whole(0, 4)  # each refinement has 8 times the cells
MESH_REFINE_HELP = "cut the scene's mesh uniformly K more times (h / 2^K; the reference stays the base mesh's)"


PETSC_HELP = (
    "a PETSc option for the reference's linear solves, over the choice by size (MUMPS LDL^T up to "
    "reference.solver.DIRECT_LIMIT dofs, GAMG above); a pc_type replaces the choice; repeatable"
)


def _petsc_option(text: str) -> dict:
    key, sep, value = text.partition("=")
    key = key.strip().lstrip("-")
    if not sep or not key or not value.strip():
        raise argparse.ArgumentTypeError(f"{text!r} is not KEY=VALUE (for example pc_type=gamg)")
    return {key: value.strip()}


class _Merge(argparse.Action):
    """Repeated KEY=VALUE options merged into one dict."""

    def __call__(self, parser, namespace, values, option_string=None):
        setattr(namespace, self.dest, {**(getattr(namespace, self.dest) or {}), **values})


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="tissuebench", description="What real-time soft-tissue models give up for their speed.")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("scenes", help="list built-in scenes")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_scenes)

    s = sub.add_parser("check", help="read a scene (mesh, regions, loading) and describe it, solving nothing")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_check)

    s = sub.add_parser("reference", help="solve a scene's ground truth with dolfinx")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--degree", type=int, choices=(1, 2), default=2)
    s.add_argument("--refine", type=_level, default=0)
    s.add_argument(
        "--load-steps",
        type=_count,
        default=1,
        help="first load increment 1/N of a non-linear static solve (more for a hard problem; default 1)",
    )
    s.add_argument("--out", help="write the result file (.npz)")
    s.add_argument("--vtk", help=VTK_HELP)
    s.add_argument("--no-estimate", action="store_true", help="skip the refined solve behind ref_err_estimate")
    s.add_argument("--petsc-option", type=_petsc_option, action=_Merge, metavar="KEY=VALUE", help=PETSC_HELP)
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_reference)

    for name, func, helptext in (
        ("run", cmd_run, "run a real-time model on a scene"),
        ("compare", cmd_compare, "metrics of a model against the reference"),
    ):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("scene")
        s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
        s.add_argument("--model", required=True, choices=sorted(MODELS))
        s.add_argument("--dt", type=_positive, help="time step, s (default 0.9 x the critical one)")
        s.add_argument("--integrator", default="symplectic-euler", choices=sorted(INTEGRATORS))
        s.add_argument("--max-steps", type=_count, default=2_000_000, help="steps a static scene may take to settle")
        s.add_argument("--vtk", help=VTK_HELP)
        s.add_argument("--json", action="store_true")
        if name == "run":
            s.add_argument("--out", help="write the result file (.npz)")
        else:
            s.add_argument("--degree", type=int, choices=(1, 2), default=2, help="reference degree")
            s.add_argument("--refine", type=_level, default=0, help="reference refinement level")
            s.add_argument("--petsc-option", type=_petsc_option, action=_Merge, metavar="KEY=VALUE", help=PETSC_HELP)
            s.add_argument(
                "--rate", type=_positive, help="frame rate, Hz: say whether the run holds it (as advise decides)"
            )
        s.set_defaults(func=func)

    s = sub.add_parser("report", help="HTML report with plots and data")
    s.add_argument(
        "scenes",
        nargs="*",
        help="scenes (default: cantilever cantilever-pull cantilever-dynamic stiff-inclusion, with the "
        "convergence and stability studies)",
    )
    s.add_argument("--out", help="report directory (default reports/NAME)")
    s.add_argument(
        "--fractions",
        type=_positive,
        nargs="+",
        help="time steps as fractions of each model's critical step (default: the sweep's, 0.25 0.5 0.9 on a "
        "dynamic scene and 0.9 on a static one, and 1.1 to show the limit)",
    )
    s.add_argument("--seeds", action="store_true", help="the page of the seeds experiments (reports/seeds)")
    s.set_defaults(func=cmd_report)

    s = sub.add_parser("seeds", help="the source documents' experiments: each claim measured, with a verdict")
    s.add_argument("--only", nargs="+", metavar="KEY", help="run only these experiments (by key)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_seeds)

    s = sub.add_parser("sweep", help="error against step time for models x time steps, with the Pareto front")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--models", nargs="+", choices=sorted(MODELS))
    s.add_argument("--fractions", type=_positive, nargs="+", help="time steps as fractions of the critical one")
    s.add_argument("--dts", type=_positive, nargs="+", help="time steps in seconds")
    s.add_argument("--integrator", default="symplectic-euler", choices=sorted(INTEGRATORS))
    s.add_argument("--no-largest-stable", action="store_true", help="skip the search for the largest stable step")
    s.add_argument(
        "--float32",
        action="store_true",
        help="run each row of linear-tm, stvk-tm and mass-spring again in float32 and report its distance from the "
        "float64 run beside the model's error (explicit integrators)",
    )
    s.add_argument("--csv", help="also write the table as CSV")
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_sweep)

    s = sub.add_parser("converge", help="observed orders in space (mesh refinement) or time (dt halving)")
    s.add_argument("scene")
    s.add_argument("--in", dest="in_", choices=("space", "time"), default="space")
    s.add_argument("--models", nargs="+", choices=sorted(MODELS))
    s.add_argument("--levels", type=_count, default=3, help="mesh levels h, h/2, ... (space)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_converge)

    s = sub.add_parser(
        "stability", help="largest stable steps and the extremes (nu, E, rotation, compression, slivers)"
    )
    s.add_argument("scene")
    s.add_argument("--models", nargs="+", choices=sorted(MODELS))
    s.add_argument("--tol", type=_positive, default=0.1, help="rel_l2 above which a model is called inaccurate")
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_stability)

    s = sub.add_parser("advise", help="the cheapest model, integrator and dt meeting a tolerance at a rate")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--tol", type=_positive, required=True, help="largest acceptable error (relative)")
    s.add_argument("--rate", type=_positive, required=True, help="update rate the model must sustain, Hz")
    s.add_argument("--metric", default="rel_l2", choices=("rel_l2", "surface_rel_l2", "reaction_rel_err"))
    s.add_argument("--models", nargs="+", choices=sorted(MODELS), help="choose among these only (default: every model)")
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_advise)

    s = sub.add_parser("gate", help="CI accuracy gates; exit 1 on a miss")
    s.add_argument("--config", help="gates file (default: the shipped verification/gates.toml)")
    s.add_argument("--quick", action="store_true", help="only the gates marked quick")
    s.add_argument(
        "--update-baselines",
        action="store_true",
        help="record the measured values and provenance (runs afresh, not from the run cache)",
    )
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_gate)

    s = sub.add_parser("bench", help="performance benchmark: microseconds per step of every model")
    s.add_argument(
        "--meshes",
        nargs="+",
        default=["liver", "liver-x10", "liver-x10-renumbered"],
        choices=stored_names(),
        help="stored meshes to run on (NAME-renumbered: the mesh numbered along the body)",
    )
    s.add_argument("--repeats", type=_count, default=15)
    s.add_argument(
        "--reference",
        action="store_true",
        help="time the dolfinx reference instead (seconds, Newton iterations, factorisations per case)",
    )
    s.add_argument("--cases", nargs="+", help="with --reference: only the cases whose label contains one of these")
    s.add_argument(
        "--newton",
        choices=("modified", "classic"),
        default="modified",
        help="with --reference: classic refactorises at every Newton iteration with MUMPS at every size (the solver before)",
    )
    s.add_argument("--out", help="also write the JSON to this file")
    s.add_argument("--markdown", help="also put this machine's section into this markdown page (docs/benchmarks.md)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_bench)
    return p


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    where = f"{args.scene}: " if isinstance(getattr(args, "scene", None), str) else ""
    try:
        return args.func(args)
    except InputError as exc:  # the project's own input errors name the file, key or element themselves
        return _fail(f"tissuebench: {_one_line(exc)}", 2)
    except FileNotFoundError as exc:
        return _fail(f"tissuebench: {exc.filename or ''}: {exc.strerror or _one_line(exc)}", 2)
    except (ReferenceSolveError, NotConvergedError) as exc:  # the problem as stated has no equilibrium we reach
        return _fail(f"tissuebench: {where}{_one_line(exc)}", 2)
    except UnboundedAnswerError as exc:  # a divergence caused by the scene's input: named, exit 2
        return _fail(f"tissuebench: {_one_line(exc)}", 2)
    except DivergenceError as exc:
        return _fail(f"tissuebench: {where}{_one_line(exc)}", 1)
    except KeyboardInterrupt:  # Ctrl-C: what had finished is in the cache, written whole (atomic_write)
        return _fail(
            "tissuebench: interrupted; what had finished is cached, and the same command resumes from there", 130
        )


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _fail(message: str, status: int) -> int:
    print(message, file=sys.stderr)
    return status


if __name__ == "__main__":
    sys.exit(main())
