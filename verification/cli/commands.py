"""The commands of ``tissuebench``, one function each (``cmd_NAME``): each reads its scene, runs what it
asks through the studies and prints text, or with --json one JSON object."""

from __future__ import annotations

import json
import sys
from pathlib import Path

from realtime.models import linear_tm, stvk_tm
from verification.engines import engine_for
from verification.inputs import check_held
from verification.metrics import METRICS
from verification.scene import SceneError, check_tools, implausible
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
    from verification.runs.row import jsonable

    return jsonable(x)


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


def _scene(args, warn: bool = True, solves: bool = True):
    """The command's scene, cut ``--mesh-refine`` more times than its file says; with ``warn``, what
    no soft tissue has (scene.implausible) goes to stderr before any work. A command that ``solves``
    the scene's own problem refuses a manufactured-solution scene: it has no constraints or loads (its
    problem is the manufactured one on the unit cube, which only ``converge`` poses)."""
    scene = load_scene(args.scene, refine=getattr(args, "mesh_refine", 0))
    if solves and scene.manufactured:
        raise SceneError(
            f"{scene.path}: [manufactured]: this scene poses the manufactured solution on the unit cube, which "
            f"only converge solves; it has no constraints or loads of its own for {args.command} (run "
            f"tissuebench converge {args.scene})"
        )
    check_held(scene)
    check_tools(scene)
    model, options = getattr(args, "model", None), getattr(args, "engine_option", None)
    if isinstance(model, str) and options:  # an adapter's knobs, refused before any truth is solved for them
        check = getattr(engine_for(model), "check_options", None)
        if check is not None:
            check(model, options)
    from verification.engines.adapters import ADAPTERS

    plug_ins = [e for e in getattr(args, "engine", None) or () if e not in ADAPTERS]
    if scene.problem.contacts and plug_ins:  # refused in one line before any truth is solved for them
        raise SceneError(
            f"{scene.path}: tool: the plug-in engine {plug_ins[0]} is not given a rigid tool (the export carries "
            f"one to the adapters, {', '.join(ADAPTERS)}, and to --engine-cmd; the built-in models model it)"
        )
    if scene.events:  # each state's body must be held too: a cut right through frees a piece
        from verification.events import states

        for state in states(scene)[1:]:
            check_held(state.scene)
    if warn:
        from verification.progress import log

        for line in implausible(scene):
            log(f"tissuebench: warning: {scene.path}: {line}")
    return scene


def _write_vtk(target: str, name: str, res) -> None:
    """A result's displacements at every output time as a ParaView series (--vtk)."""
    from verification.vtk import write_series

    write_series(target, name, res.points, res.tets, res.times, {"displacement": res.displacement})


def cmd_check(args) -> int:
    """Read a scene as every command does (mesh, regions, loading, a model) and describe it, solving
    nothing: the check to run before a long study."""
    from verification.cli.describe import check_text, describe

    scene = _scene(args, warn=False, solves=False)  # check prints them with the rest
    out = describe(scene)
    if args.picture:
        from meshes.io import atomic_write
        from verification.report.scene_picture import scene_picture

        if Path(args.picture).suffix.lower() != ".png":
            return _fail(f"tissuebench: --picture {args.picture}: give a .png file", 2)
        data = scene_picture(scene)
        out["picture"] = str(atomic_write(args.picture, lambda tmp: Path(tmp).write_bytes(data)))
    _emit(args, out, check_text)
    return 0


def _write_levels(target: str, name: str, res) -> None:
    """An adaptive reference's meshes, one step of a ParaView series a level, each with its P2 displacement
    at the vertices and its cells' indicator (--vtk)."""
    from verification.cache import entry
    from verification.runs.reference import levels_path, read_levels
    from verification.vtk import write_levels

    path = levels_path(entry("reference", res.meta["scene"], res.meta["cache_key"], ".npz"))
    if not path.exists():
        raise SceneError(f"--vtk: the adaptive reference's levels are not kept (solved with --no-cache?): {path}")
    written = write_levels(target, name, read_levels(path))
    print(f"wrote {written} (one step a level: the displacement and the indicator eta^2)", file=sys.stderr)


def cmd_reference(args) -> int:
    from verification.runs.reference import contact_summary, reference_result

    scene = _scene(args)
    estimate = False if args.no_estimate else {"p3": "p3", "adaptive": "adaptive"}.get(args.estimate, True)
    adapt = None
    if estimate == "adaptive":
        adapt = {"target": args.target, "budget_s": args.budget, "max_levels": args.levels}
    elif args.target is not None or args.budget is not None:
        raise SceneError("--target and --budget steer --estimate adaptive; add it, or leave them out")
    res = reference_result(
        scene,
        degree=args.degree,
        refine=args.refine,
        estimate=estimate,
        use_cache=not args.no_cache,
        newton_steps=args.load_steps,
        petsc_options=args.petsc_option,
        adapt=adapt,
    )
    from mpi4py import MPI

    if args.out and MPI.COMM_WORLD.rank == 0:
        res.save(args.out)
    if args.vtk and MPI.COMM_WORLD.rank == 0:
        _write_vtk(args.vtk, f"{scene.name}-reference", res)
        if estimate == "adaptive":
            _write_levels(args.vtk, f"{scene.name}-reference-levels", res)
    summary = {
        "scene": scene.name,
        "out": args.out,
        "max_displacement": float(abs(res.displacement).max()),
        "reaction": res.reaction[-1].tolist(),
        "contact": contact_summary(res.meta),
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
            for row in summary["contact"]:
                force, area = (("unknown" if b is None else f"{b:.2g}") for b in (row["force_bar"], row["area_bar"]))
                print(
                    f"  tool[{row['tool']}]: force [{', '.join(f'{f:.4g}' for f in row['force'])}] N (bar {force}), "
                    f"contact area {row['area']:.4g} m^2 (bar {area})"
                )
    return 0


def cmd_run(args) -> int:
    from verification.runs.simulate import run_model

    scene = _scene(args)
    res = run_model(
        scene, args.model, dt=args.dt, integrator=args.integrator, max_steps=args.max_steps, options=args.engine_option
    )
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
    row = compare(
        scene,
        args.model,
        dt=args.dt,
        integrator=args.integrator,
        degree=args.degree,
        refine=args.refine,
        petsc_options=args.petsc_option,
        max_steps=args.max_steps,
        vtk=args.vtk,
        options=args.engine_option,
    )
    if args.rate and row.ok:
        from verification.studies.frame import frame_budget

        row = row.replace(frame=frame_budget(row, args.rate, scene.time.mode == "dynamic"))
    if row.unbounded:  # the scene's own answer is past the blow-up guard: its input, not a step
        return _fail(f"tissuebench: {_one_line(row.message)}", 2)
    if args.json:
        _print_json(row)
    elif not row.ok:
        print(row.message)
    else:
        _print_row(scene, args, row)
    return 0 if row.ok else 1


def _print_row(scene, args, row) -> None:
    """A compare row as text: its metrics, error budget, frame budget and what the model did not represent."""
    from verification.runs.compare import cancelling
    from verification.studies.frame import reference_bar, true_range, with_bar

    at = "its quasi-static update" if row.dt is None else f"dt = {row.dt:.3g} s"
    print(f"{scene.name} / {args.model} at {at}:")
    for k in (*METRICS, "ref_err_estimate", "step_us", "realtime_factor", "rate_hz"):
        v = getattr(row, k)
        span = true_range(v, reference_bar(row, k)) if k in ("rel_l2", "surface_rel_l2", "reaction_rel_err") else ""
        true = f"   {span} (the reference's bar)" if span else ""
        print(f"  {k:<18} {'-' if v is None else f'{v:.4g}'}{true}")
    b = row.error_budget or {}
    if b.get("mesh") is not None:
        parts = ", ".join(f"{p} {b[p]:.3g}" for p in ("mesh", "model", "time") if b.get(p) is not None)
        print(f"  {'error_budget':<18} {parts}: the {b['dominant']}'s part dominates")
        if cancelling(row.rel_l2, b["mesh"], b.get("model")):
            print(
                f"  {'':<18} errors cancelling: rel_l2 {row.rel_l2:.3g} is below the mesh's part with a model part "
                f"of {b['model']:.3g}: the model's error offsets P1's, right for a wrong reason; a finer mesh "
                "shrinks the mesh's part, not the model's"
            )
    for c in row.contact:
        span = true_range(c["area_rel_err"], c["ref_area_bar"])
        area = "-" if c["area"] is None else f"{c['area']:.4g} m^2"
        err = "-" if c["area_rel_err"] is None else f"{c['area_rel_err']:.4g}"
        bar = f"   {span} (the reference's bar)" if span else ""
        truth = "-" if c["ref_area"] is None else f"{c['ref_area']:.4g}"
        print(f"  {'contact area':<18} tool {c['tool']}: {area} against the reference's {truth}: {err}{bar}")
    law = row.own_law or {}
    if law.get("rel_l2") is not None:
        print(f"  {'own law':<18} {law['rel_l2']:.3g} from P1 of {law['law']} on the same mesh: its numerics alone")
    elif law:
        print(f"  {'own law':<18} {law['law']}: no P1 answer ({law['why']})")
    if row.adaptation:
        a = row.adaptation
        print(
            f"  {'adaptation':<18} {a['tets_first']} tetrahedra at rest, {a['tets_max']} at most, {a['tets_last']} at the "
            f"end ({a['changes']} changes in {a['checks']} checks)"
        )
    for k, st in enumerate(row.states):
        model = (b.get("states") or [{}] * len(row.states))[k].get("model")
        part = "" if model is None else f", model part {model:.3g}"
        print(
            f"  state t = {st['time']:g} s   rel_l2 {with_bar(st['rel_l2'], st['ref_err_estimate'])}{part}: {st['label']}"
        )
    if row.frame:
        f = row.frame
        print(f"  {'frame':<18} {'holds' if f['holds'] else 'does not hold'} {args.rate:g} Hz: {f['why']}")
    for term in row.unrepresented:
        print(f"  {'not represented':<18} {term}: ran without it, and the errors above include what that costs")


def cmd_export(args) -> int:
    from verification.engines.export import export
    from verification.inputs import scene_inputs

    scene = _scene(args)
    extra = None
    if scene.events:  # one static problem per state: the body as meshed here, each later one in state-K/
        from verification.events import states

        every = states(scene)
        listed = [
            {"state": k, "time_s": s.time, "label": s.label, "directory": "." if k == 0 else f"state-{k}"}
            for k, s in enumerate(every)
        ]
        for k, s in list(enumerate(every))[1:]:
            extra = {"states": listed, "state": listed[k]}
            export(scene_inputs(s.scene), Path(args.directory) / f"state-{k}", extra)
        extra = {"states": listed, "state": listed[0]}
    path = export(scene_inputs(scene), args.directory, extra)
    out = {"scene": scene.name, "written": str(path.parent), "files": sorted(p.name for p in path.parent.iterdir())}
    _emit(args, out, lambda o: f"{o['scene']}: {', '.join(o['files'])} in {o['written']}")
    return 0


def cmd_judge(args) -> int:
    from verification.studies.judge import format_judgement, judge

    scene = _scene(args)
    out = judge(scene, args.result, scale=args.scale, outside=args.outside, step_us=args.step_us, state=args.state)
    _emit(args, out, format_judgement)
    return 0


def cmd_report(args) -> int:
    from verification.report.page import write_report
    from verification.report.seeds_page import seeds_report_dir, write_seeds_report

    if args.seeds:
        if args.scenes:
            return _fail("tissuebench: report --seeds takes no scenes (it is the page of the seeds experiments)", 2)
        from verification.studies.seeds import run_seeds

        seeds_report_dir(args.out)  # a directory that cannot be made fails before half an hour of runs
        path = write_seeds_report(run_seeds(), out=args.out)
    else:
        from verification.report.sections import Question

        question = Question(tol=args.tol, rate=args.rate, haptic_rate=args.haptic_rate)
        path = write_report(args.scenes or None, out=args.out, fractions=args.fractions, question=question)
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
        from meshes.io import atomic_write_text

        atomic_write_text(args.csv, sweep_csv(out))
    _emit(args, out, format_sweep)
    return 0


def cmd_converge(args) -> int:
    from verification.studies.converge import converge_manufactured, converge_space, converge_time, format_converge

    scene = _scene(args, solves=False)
    if scene.manufactured:
        out = converge_manufactured(scene)
    elif args.in_ == "time":
        out = converge_time(scene, models=args.models or (linear_tm.NAME,))
    else:
        out = converge_space(scene, models=args.models or (linear_tm.NAME, stvk_tm.NAME), levels=args.levels)
    _emit(args, out, format_converge)
    return 0


def cmd_effectivity(args) -> int:
    import json

    from meshes.io import atomic_write_text
    from verification.studies.effectivity import effectivity_table, format_markdown

    out = effectivity_table(args.cases, args.returned, use_cache=not args.no_cache)
    if args.markdown:
        atomic_write_text(args.markdown, format_markdown(out))
    if args.out:
        atomic_write_text(args.out, json.dumps(out, indent=1, default=_default))
    _emit(args, out, format_markdown)
    return 0


def cmd_stability(args) -> int:
    from verification.studies.stability import format_stability, stability

    out = stability(_scene(args), models=args.models, tol=args.tol, use_cache=not args.no_cache)
    _emit(args, out, format_stability)
    return 0


def cmd_advise(args) -> int:
    from verification.studies.advise import advise, check_question, format_advice

    comm = _mpi_comm()
    scene = _scene(args)
    check_question(scene, args.tol, args.rate, args.metric, args.haptic_rate, args.force_tol)  # before any solve
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
        haptic_rate=args.haptic_rate,
        force_tol=args.force_tol,
        truth_budget=args.truth_budget,
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
    if args.advice:
        from verification.bench.advice import format_table, run

        out = run(cases=args.cases)
    elif args.solvers:
        from mpi4py import MPI

        from verification.bench.solvers import format_table, run

        out = run(cases=args.cases)
        if MPI.COMM_WORLD.rank:
            return 0
    elif args.reference:
        from mpi4py import MPI

        from verification.bench.reference import format_table, run

        out = run(cases=args.cases, newton=args.newton)
        if MPI.COMM_WORLD.rank:  # under mpirun every rank solved; the first reports
            return 0
    else:
        from verification.bench.suite import run
        from verification.bench.table import format_table

        out = run(meshes=args.meshes, repeats=args.repeats)
        if args.markdown:
            from verification.bench.table import write_markdown

            write_markdown(args.markdown, out)
    if args.out:
        from meshes.io import atomic_write_text

        atomic_write_text(args.out, json.dumps(out, indent=1, default=_default))
    _emit(args, out, format_table)
    return 0


def _one_line(exc: BaseException) -> str:
    return " ".join(str(exc).split())


def _fail(message: str, status: int) -> int:
    print(message, file=sys.stderr)
    return status
