"""A plug-in engine's run in a process of its own (``runs.simulate._plug_in``): whatever its code does there
(raises, hangs inside a C call no signal interrupts, crashes the interpreter) stops that process only,
and the harness says what happened in one line and goes on.

The worker is a fork of the harness, so the plug-in, the scene and everything the harness had computed
are there as they are, without pickling; its answer (the run's Result) comes back through a pipe, and so
does what it raised, re-raised here with its type, or described in a PlugInError when it cannot travel.
A fork keeps MPI out of it: the worker leaves with ``os._exit`` and never finalises MPI. Where ``fork``
is not available the run stays in this process, bound by SIGALRM (Python code only).
"""

from __future__ import annotations

import multiprocessing
import os
import pickle
import signal

from realtime import DivergenceError
from realtime.errors import InputError


class PlugInError(InputError):
    """A plug-in engine that failed: it raised, crashed, hung, or answered with an array that is not a
    displacement of the scene's vertices in metres; ``str()`` names the engine, the model and what went
    wrong."""


class PlugInDivergence(DivergenceError):
    """A plug-in's DivergenceError that came back from its worker: the step, dt and critical dt it gave."""

    def __init__(self, message: str, step, dt, dt_crit, reason: str = ""):
        self.step, self.dt, self.dt_crit, self.reason = step, dt, dt_crit, reason
        RuntimeError.__init__(self, message)


def forks() -> bool:
    """Whether a plug-in can run in a forked worker here."""
    return "fork" in multiprocessing.get_all_start_methods()


def _travels(exc: BaseException) -> bool:
    try:
        pickle.loads(pickle.dumps(exc))
        return True
    except Exception:  # noqa: BLE001 - whatever the plug-in's exception does when pickled
        return False


def _outcome(fn) -> tuple:
    """What ``fn()`` gave, as something the pipe carries: ("ok", value), ("raised", exception),
    ("diverged", its fields) or ("text", type name, message)."""
    try:
        return "ok", fn()
    except DivergenceError as exc:
        fields = {k: getattr(exc, k, None) for k in ("step", "dt", "dt_crit", "reason")}
        return "diverged", str(exc), fields
    except BaseException as exc:  # noqa: BLE001 - the plug-in's own, sent back to be named there
        return ("raised", exc) if _travels(exc) else ("text", type(exc).__name__, str(exc))


def in_worker(fn, seconds: float, what: str):
    """``fn()`` run in a forked process, bound by ``seconds``; its value, or what it raised raised here.
    A worker that runs past the bound is killed, and one that dies (a signal, an exit) is named: both as
    a PlugInError naming ``what``."""
    ctx = multiprocessing.get_context("fork")
    receive, send = ctx.Pipe(duplex=False)

    def work():
        # a crash kills the worker at once: not PETSc's handler (it calls MPI_Abort, which waits forever in
        # a fork of an MPI process), not the parent's faulthandler
        for sig in (signal.SIGSEGV, signal.SIGBUS, signal.SIGFPE, signal.SIGILL, signal.SIGABRT):
            signal.signal(sig, signal.SIG_DFL)
        outcome = _outcome(fn)
        try:
            send.send(outcome)
        except Exception as exc:  # noqa: BLE001 - a value that does not pickle
            send.send(("text", type(exc).__name__, f"its answer cannot be sent back: {exc}"))
        send.close()
        os._exit(0)  # never the harness's exit handlers (MPI's among them) in a fork

    worker = ctx.Process(target=work, daemon=True)
    worker.start()
    send.close()
    try:
        if not receive.poll(seconds):
            raise PlugInError(f"{what}: still running after {seconds:g} s, stopped")
        try:
            outcome = receive.recv()
        except EOFError:
            worker.join(5.0)
            code = worker.exitcode
            how = f"signal {signal.Signals(-code).name}" if code is not None and code < 0 else f"exit status {code}"
            raise PlugInError(f"{what}: its process died ({how}) before it answered") from None
    finally:
        if worker.is_alive():
            worker.kill()
        worker.join(5.0)
        receive.close()
    kind = outcome[0]
    if kind == "ok":
        return outcome[1]
    if kind == "raised":
        raise outcome[1]
    if kind == "diverged":
        raise PlugInDivergence(outcome[1], **outcome[2])
    raise PlugInError(f"{what}: {outcome[1]}: {' '.join(outcome[2].split())}")
