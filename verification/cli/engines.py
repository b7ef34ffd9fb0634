"""The ``engines`` command: the engines users pick, studied on one scene or several (docs/engines.md), with
the engines page (``--report DIR``)."""

from __future__ import annotations

import os
import sys
import time
from pathlib import Path

from verification.cli.commands import _emit, _mpi_comm, _rank0, _scene
from verification.scene import SceneError


def cmd_engines(args) -> int:
    """``tissuebench engines SCENE...``: the study on each scene (docs/engines.md), its page with --report."""
    from verification.engines import load_engine
    from verification.engines.adapters import ADAPTERS
    from verification.studies.engines import engines_study, format_engines, run_line

    if args.plot and len(args.scenes) > 1:
        raise SceneError(f"--plot {args.plot}: one plot is one scene's; for {len(args.scenes)} give --report DIR")
    if args.jobs is not None and args.jobs < 1:
        raise SceneError(f"--jobs {args.jobs}: at least 1")
    names = args.engine or [n for n, a in ADAPTERS.items() if a.default]  # those named, else the default ones
    for name in names:
        load_engine(name)
    if args.device is not None:  # checked before any truth: warp's device, for the engines built on warp
        warp = [ADAPTERS[n] for n in names if "device" in ADAPTERS[n].knobs]
        if not warp:
            raise SceneError(
                f"--device {args.device}: none of {', '.join(names)} runs on warp (newton, mujoco-warp do)"
            )
        for engine in warp:
            engine.check_options(next(iter(engine.models)), {"device": args.device})
    scenes = []
    for name in args.scenes:  # every scene read first: a bad one fails before any run
        args.scene = name
        scenes.append(_scene(args))
    page = None
    if args.report:
        from verification.report.common import make_report_dir

        page = make_report_dir(Path(args.report))
    comm = _mpi_comm()
    ranks = comm.size if comm is not None else 1
    jobs = args.jobs or max(1, len(os.sched_getaffinity(0)) // ranks)
    # each run's row on stdout as it finishes (the study takes minutes a run); --json keeps stdout whole
    on_run = None if args.json else (lambda r: print(run_line(r), flush=True))
    studies, t0 = [], time.perf_counter()
    for scene in scenes:
        studies.append(
            engines_study(
                scene,
                models=args.models,
                use_cache=not args.no_cache,
                comm=comm,
                builtin=args.builtin or page is not None,
                on_run=on_run,
                jobs=jobs,
                device=args.device,
            )
        )
        if studies[-1].get("stopped"):
            break
    if not _rank0(comm):
        return 0
    if args.plot:
        import base64

        from meshes.io import atomic_write
        from verification.report.plots import plot_engines

        data = base64.b64decode(plot_engines(studies[0]))
        atomic_write(args.plot, lambda tmp: Path(tmp).write_bytes(data))
    if page is not None:
        from verification.report.engines_page import write_engines_page

        print(f"engines page: {write_engines_page(studies, page, time.perf_counter() - t0)}", file=sys.stderr)
    if len(studies) == 1:
        _emit(args, studies[0], format_engines)
    else:
        _emit(args, studies, lambda ss: "\n\n".join(format_engines(s) for s in ss))
    return 130 if studies[-1].get("stopped") else 0
