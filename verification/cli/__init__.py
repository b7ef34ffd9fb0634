"""The ``tissuebench`` command (docs/data-flow.md).

Exit status: 0 on success; 1 when a model's run blows up (divergence: the step, dt and the critical
one are named); 2 for input the tool cannot use (a scene file, a mesh, an option, a gates file, or a
problem the reference or the model cannot bring to equilibrium as stated), with one line on stderr that
names the file, the key or the element and the value. Any other exception is a bug and keeps its
traceback. With --json, stdout carries one JSON object and nothing else.
"""

from __future__ import annotations

from realtime import DivergenceError, InputError, NotConvergedError
from reference.errors import ReferenceSolveError
from verification.cli.commands import _fail, _one_line
from verification.cli.parser import build_parser
from verification.engines import ENGINES, engine_for, load_engine
from verification.engines.settling import UnboundedAnswerError


def main(argv=None) -> int:
    args = build_parser().parse_args(argv)
    from verification.runs import simulate

    # the plug-ins this command names, and their time bound, for this command only
    engines, timeout = dict(ENGINES), simulate.PLUG_IN_TIMEOUT
    try:
        return _run(args)
    finally:
        ENGINES.clear()
        ENGINES.update(engines)
        simulate.PLUG_IN_TIMEOUT = timeout


def _run(args) -> int:
    """The command, its plug-ins registered first; its errors mapped to exit statuses (module docstring)."""
    from verification.runs import simulate

    where = f"{args.scene}: " if isinstance(getattr(args, "scene", None), str) else ""
    try:
        for spec in getattr(args, "engine", None) or ():
            load_engine(spec)
        if getattr(args, "engine_timeout", None):
            simulate.PLUG_IN_TIMEOUT = args.engine_timeout
        if getattr(args, "engine_cmd", None):
            from verification.engines.command import CommandEngine

            command = CommandEngine(args.engine_cmd, args.model, args.engine_timeout)
            ENGINES[command.name] = command
        if getattr(args, "model", None):
            engine_for(args.model)  # an unknown model is named before any work
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
