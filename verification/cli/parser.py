"""The command line of ``tissuebench``: one sub-parser per command, and the argument types that turn
a bad value into a one-line error."""

from __future__ import annotations

import argparse
import re

from meshes.store import stored_names
from realtime import INTEGRATORS, MODELS
from realtime.errors import did_you_mean
from verification.cli.commands import (
    cmd_advise,
    cmd_bench,
    cmd_check,
    cmd_compare,
    cmd_converge,
    cmd_effectivity,
    cmd_export,
    cmd_gate,
    cmd_judge,
    cmd_reference,
    cmd_report,
    cmd_run,
    cmd_scenes,
    cmd_seeds,
    cmd_stability,
    cmd_sweep,
)
from verification.cli.engines import cmd_engines

ENGINE_HELP = (
    "an engine whose models --model may name: an adapter (newton, mujoco, pybullet, mujoco-warp) or a plug-in (package.module:Class or "
    "file.py:Class); repeatable"
)
ENGINE_CMD_HELP = (
    "an engine in its own process: a command that reads the exported scene at {scene} and writes its answer "
    "to {result} (.npz); --model names what it runs"
)
VTK_HELP = "also write the displacements (and, for compare, the error) at every output time for ParaView: DIR or F.pvd"


class _Parser(argparse.ArgumentParser):
    """argparse with its errors on one line (the usage is in --help) and exit status 2."""

    def error(self, message):
        # argparse's "invalid choice: 'compar' (choose from 'scenes', ...)": the closest choice named first
        wrong = re.match(r"argument [^:]+: invalid choice: '([^']*)' \(choose from (.*)\)$", message)
        if wrong:
            message = message.replace(
                " (choose from", did_you_mean(wrong[1], re.findall(r"'([^']*)'", wrong[2])) + " (choose from", 1
            )
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
    "a PETSc option for the reference's linear solves, over the choice by memory (MUMPS LDL^T where its "
    "factor is predicted to fit in half the available memory, GAMG elsewhere); a pc_type replaces the "
    "choice; repeatable"
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


def _scenes(sub) -> None:
    s = sub.add_parser("scenes", help="list built-in scenes")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_scenes)


def _check(sub) -> None:
    s = sub.add_parser("check", help="read a scene (mesh, regions, loading) and describe it, solving nothing")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument(
        "--picture",
        metavar="FILE.png",
        help="also draw the scene from three sides (axes in m, each held region, tool and cut labelled)",
    )
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_check)


def _reference(sub) -> None:
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
    s.add_argument(
        "--estimate",
        choices=("difference", "p3", "adaptive"),
        default="difference",
        help="the bar: the difference of two refinements, twice the distance to P3 on the returned mesh "
        "(P2; dynamic: plus 4/3 of the distance to dt / 2 there; docs/effectivity.md), or that P3 bar on a "
        "mesh refined where the error lives (static)",
    )
    s.add_argument(
        "--target",
        type=_positive,
        metavar="BAR",
        help="--estimate adaptive: refine until the bar is at most BAR (default: until --budget or --levels)",
    )
    s.add_argument(
        "--budget",
        type=_positive,
        metavar="S",
        help="--estimate adaptive: stop before a level predicted to end past S seconds (default: none)",
    )
    s.add_argument(
        "--levels", type=_count, default=6, metavar="N", help="--estimate adaptive: at most N refinements (default 6)"
    )
    s.add_argument("--petsc-option", type=_petsc_option, action=_Merge, metavar="KEY=VALUE", help=PETSC_HELP)
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_reference)


def _run_compare(sub) -> None:
    for name, func, helptext in (
        ("run", cmd_run, "run a real-time model on a scene"),
        ("compare", cmd_compare, "metrics of a model against the reference"),
    ):
        s = sub.add_parser(name, help=helptext)
        s.add_argument("scene")
        s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
        s.add_argument("--model", required=True, help=f"a built-in model ({', '.join(sorted(MODELS))}) or a plug-in's")
        s.add_argument("--engine", action="append", metavar="MODULE:CLASS", help=ENGINE_HELP)
        s.add_argument("--engine-cmd", metavar="COMMAND", help=ENGINE_CMD_HELP)
        s.add_argument(
            "--engine-timeout", type=_positive, default=600.0, metavar="S", help="seconds a plug-in's run may take"
        )
        s.add_argument("--dt", type=_positive, help="time step, s (default 0.9 x the critical one)")
        s.add_argument(
            "--engine-option",
            type=_engine_option,
            action=_Merge,
            metavar="KEY=VALUE",
            help="a knob of the model (iterations=50, substeps=4, criterion=stress, levels=3); repeatable",
        )
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


def _report(sub) -> None:
    s = sub.add_parser("report", help="HTML report with plots and data")
    s.add_argument(
        "scenes",
        nargs="*",
        help="scenes (default: cantilever cantilever-pull cantilever-dynamic stiff-inclusion liver-press, with the "
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
    s.add_argument("--tol", type=_positive, default=0.05, help="the advisor's tolerance on rel_l2 (default 0.05)")
    s.add_argument("--rate", type=_positive, default=1000.0, help="the advisor's update rate, Hz (default 1000)")
    s.add_argument(
        "--haptic-rate", type=_positive, metavar="HZ", help="the advisor also asks the tool force within --tol there"
    )
    s.add_argument("--seeds", action="store_true", help="the page of the seeds experiments (reports/seeds)")
    s.add_argument("--engine", action="append", metavar="MODULE:CLASS", help=ENGINE_HELP)
    s.set_defaults(func=cmd_report)


def _seeds(sub) -> None:
    s = sub.add_parser("seeds", help="the source documents' experiments: each claim measured, with a verdict")
    s.add_argument("--only", nargs="+", metavar="KEY", help="run only these experiments (by key)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_seeds)


def _sweep(sub) -> None:
    s = sub.add_parser("sweep", help="error against step time for models x time steps, with the Pareto front")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--models", nargs="+", help="the models to sweep (default: every model, plug-ins' too)")
    s.add_argument("--engine", action="append", metavar="MODULE:CLASS", help=ENGINE_HELP)
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


def _converge(sub) -> None:
    s = sub.add_parser("converge", help="observed orders in space (mesh refinement) or time (dt halving)")
    s.add_argument("scene")
    s.add_argument("--in", dest="in_", choices=("space", "time"), default="space")
    s.add_argument("--models", nargs="+", choices=sorted(MODELS))
    s.add_argument("--levels", type=_count, default=3, help="mesh levels h, h/2, ... (space)")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_converge)


def _effectivity(sub) -> None:
    from verification.studies.effectivity import CASES

    s = sub.add_parser(
        "effectivity", help="the reference's bar against its true error on cases that span what users bring"
    )
    s.add_argument("--cases", nargs="+", choices=list(CASES), help="default: every case")
    s.add_argument("--returned", type=int, default=1, choices=(0, 1), help="the refinement the reference returns")
    s.add_argument("--markdown", help="write the table there (docs/effectivity.md)")
    s.add_argument("--out", help="write the table's JSON there")
    s.add_argument("--no-cache", action="store_true", help="measure every case again")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_effectivity)


def _stability(sub) -> None:
    s = sub.add_parser(
        "stability", help="largest stable steps and the extremes (nu, E, rotation, compression, slivers)"
    )
    s.add_argument("scene")
    s.add_argument("--models", nargs="+", choices=sorted(MODELS))
    s.add_argument("--tol", type=_positive, default=0.1, help="rel_l2 above which a model is called inaccurate")
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_stability)


def _advise(sub) -> None:
    s = sub.add_parser("advise", help="the cheapest model, integrator and dt meeting a tolerance at a rate")
    s.add_argument("scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--tol", type=_positive, required=True, help="largest acceptable error (relative)")
    s.add_argument("--rate", type=_positive, required=True, help="update rate the model must sustain, Hz")
    s.add_argument("--metric", default="rel_l2", choices=("rel_l2", "surface_rel_l2", "reaction_rel_err"))
    s.add_argument(
        "--haptic-rate",
        type=_positive,
        metavar="HZ",
        help="also a haptic loop at this rate (Hz): the model steps there, and the tool's force is judged there",
    )
    s.add_argument(
        "--force-tol", type=_positive, help="largest acceptable error of the tool's force (relative; default --tol)"
    )
    s.add_argument(
        "--truth-budget",
        type=_positive,
        metavar="SECONDS",
        help="time a sharper truth may take where the default one leaves candidates undecided (default 180 "
        "adapting a static truth, 120 refining a dynamic one)",
    )
    s.add_argument("--models", nargs="+", help="choose among these only (default: every model, plug-ins' too)")
    s.add_argument("--engine", action="append", metavar="MODULE:CLASS", help=ENGINE_HELP)
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_advise)


def _gate(sub) -> None:
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


def _bench(sub) -> None:
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
    s.add_argument(
        "--solvers",
        action="store_true",
        help="the reference's linear solvers side by side (GAMG, ML, BoomerAMG, MUMPS: iterations, seconds, memory)",
    )
    s.add_argument(
        "--advice",
        action="store_true",
        help="advise on SOFA's liver and a user's liver at 5%% and 60 Hz, each from an empty cache: seconds, answer",
    )
    s.add_argument(
        "--cases",
        nargs="+",
        help="with --reference, --solvers or --advice: only the cases whose label contains one of these",
    )
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


def _export(sub) -> None:
    s = sub.add_parser("export", help="write a scene as data any engine can read (JSON, arrays, VTU and gmsh 2.2)")
    s.add_argument("scene")
    s.add_argument("directory", help="where scene.json, arrays.npz, mesh.vtu and mesh.msh go")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_export)


def _judge(sub) -> None:
    s = sub.add_parser("judge", help="what another engine wrote, against the scene's reference")
    s.add_argument("scene")
    s.add_argument("result", help="its displacement: .npz, .vtu/.vtk, a ParaView .pvd series or .xdmf")
    s.add_argument("--scale", type=_positive, default=1.0, help="metres per unit of the result (0.001: mm)")
    s.add_argument(
        "--outside",
        type=_positive,
        default=1e-3,
        help="how far outside the body, relative to its size, a result point may lie (judged at the surface)",
    )
    s.add_argument("--step-us", type=_positive, help="the engine's own step time, us (reported as the engine's)")
    s.add_argument(
        "--state",
        type=int,
        metavar="K",
        help="a scene with events (a cut): judge the result of state K alone (0: as meshed), on that state's "
        "mesh as the export writes it",
    )
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_judge)


def _engine_option(text: str) -> dict:
    """KEY=VALUE: one knob of a model, VALUE an integer, a number or a name (iterations=50,
    threshold=0.5, criterion=stress)."""
    key, sep, value = text.partition("=")
    if not sep or not key or not value:
        raise argparse.ArgumentTypeError(f"{text!r}: give KEY=VALUE (iterations=50, threshold=0.5, criterion=stress)")
    for kind in (int, float):
        try:
            return {key: kind(value)}
        except ValueError:
            pass
    return {key: value}


def _engines(sub) -> None:
    s = sub.add_parser(
        "engines",
        help="the engines users pick (newton, MuJoCo) against the reference: error by their own knobs, largest stable "
        "step, whether the answer depends on the iteration count",
    )
    s.add_argument("scenes", nargs="+", metavar="scene")
    s.add_argument("--mesh-refine", type=_level, default=0, metavar="K", help=MESH_REFINE_HELP)
    s.add_argument(
        "--engine",
        action="append",
        metavar="NAME",
        help="an adapter (newton, mujoco, pybullet, mujoco-warp; default: newton, mujoco and pybullet)",
    )
    s.add_argument(
        "--device",
        metavar="DEVICE",
        help="warp's device for the engines built on it (newton, MuJoCo Warp): cpu (default), cuda or cuda:N",
    )
    s.add_argument(
        "--jobs",
        type=int,
        metavar="N",
        help="runs at once, each an engine's process (default: the cores this process may use, over the MPI ranks)",
    )
    s.add_argument("--report", metavar="DIR", help="also write the engines page (DIR/index.html, DIR/data.json)")
    s.add_argument("--models", nargs="+", help="only these of the adapters' models (newton-vbd, mujoco-flex, ...)")
    s.add_argument(
        "--engine-timeout", type=_positive, default=600.0, metavar="S", help="seconds one of their runs may take"
    )
    s.add_argument("--builtin", action="store_true", help="the built-in models beside them, measured in the same run")
    s.add_argument("--plot", help="also write the error-against-step-time plot here (.png; one scene)")
    s.add_argument("--no-cache", action="store_true")
    s.add_argument("--json", action="store_true")
    s.set_defaults(func=cmd_engines)


def build_parser() -> argparse.ArgumentParser:
    p = _Parser(prog="tissuebench", description="What real-time soft-tissue models give up for their speed.")
    sub = p.add_subparsers(dest="command", required=True)
    for add in (
        _scenes,
        _check,
        _reference,
        _run_compare,
        _export,
        _judge,
        _report,
        _seeds,
        _sweep,
        _converge,
        _effectivity,
        _stability,
        _advise,
        _engines,
        _gate,
        _bench,
    ):
        add(sub)
    return p
