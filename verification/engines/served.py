"""Adapter runs served by one process each (adapters/exported.py, ``serve``), not one process a run.

An adapter's run is a command line; started with ``--serve`` instead, the adapter takes command lines on its
stdin, one a run, and ends each with a line of its own on stderr (``SERVED`` and the status the run would
have exited with). Its engine is imported once: newton and warp take 2.6 s to import, and a study of 46 runs
on the liver started 34 newton processes. Each thread of the harness (``tissuebench engines --jobs``) has
its own server per adapter, so runs at once are processes at once, as before. What a run writes, its lines
on stderr, its timeout and its failures are the one-process run's (``command._call``): a run past its
timeout kills its server, and a run that fails otherwise than by exit 2 ends it; the next run starts another.
"""

from __future__ import annotations

import atexit
import json
import queue
import subprocess
import tempfile
import threading
import time

from .command import CommandError

#: adapters/exported.py's SERVED: the adapter's line after each run, with its status
SERVED = "tissuebench-adapter-served:"


class Server:
    """One adapter process serving runs: ``python script --serve`` (``python`` and ``script`` paths)."""

    def __init__(self, python: str, script: str):
        self.work = tempfile.TemporaryDirectory(prefix="tissuebench-served-")
        self.proc = subprocess.Popen(
            [python, script, "--serve"],
            stdin=subprocess.PIPE,
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
            text=True,
            cwd=self.work.name,
        )
        self.lines: queue.Queue = queue.Queue()
        threading.Thread(target=self._read, daemon=True).start()

    def _read(self) -> None:
        for line in self.proc.stderr:
            self.lines.put(line.rstrip("\n"))
        self.lines.put(None)  # the process ended

    def run(self, argv: list[str], timeout: float, relay, label: str) -> tuple[int, str]:
        """One run of command line ``argv`` (the adapter's arguments): its status and its last stderr line,
        each other line passed to ``relay`` as it comes. CommandError naming ``label`` past ``timeout`` s
        (the server is then killed)."""
        try:
            self.proc.stdin.write(json.dumps(argv) + "\n")
            self.proc.stdin.flush()
        except BrokenPipeError:  # the service had ended: the next run starts another
            return self.proc.wait() or 1, "the adapter's service had ended"
        last, deadline = "", time.monotonic() + timeout
        while True:
            try:
                line = self.lines.get(timeout=max(deadline - time.monotonic(), 0.0))
            except queue.Empty:
                self.close()
                raise CommandError(f"{label}: still running after {timeout:g} s, stopped") from None
            if line is None:  # the service ended: the status it exited with
                return self.proc.wait() or 1, last
            if line.startswith(SERVED):
                return int(line[len(SERVED) :]), last
            if line.strip():
                last = line.strip()
                relay(line)

    def close(self) -> None:
        if self.proc.poll() is None:
            self.proc.kill()
        self.proc.wait()
        self.work.cleanup()


_SERVERS: dict[tuple, Server] = {}
_LOCK = threading.Lock()


def served_call(args: list[str], timeout: float, relay, label: str) -> tuple[int, str]:
    """``command._call``'s answer for ``args`` ([python, script, *arguments]) from this thread's server of
    that adapter (started on its first run)."""
    key = (args[0], args[1], threading.get_ident())
    with _LOCK:
        server = _SERVERS.get(key)
        if server is None or server.proc.poll() is not None:
            try:
                server = _SERVERS[key] = Server(args[0], args[1])
            except OSError as exc:
                raise CommandError(f"{label}: cannot start {args[0]}: {exc}") from None
    try:
        status, last = server.run(args[2:], timeout, relay, label)
    except BaseException:  # past its timeout, or an interrupt: the server goes with the run
        _drop(key)
        raise
    if status not in (0, 2):
        _drop(key)
    return status, last


def _drop(key: tuple) -> None:
    with _LOCK:
        server = _SERVERS.pop(key, None)
    if server is not None:
        server.close()


@atexit.register
def close_all() -> None:
    """Every server ends with the harness."""
    for key in list(_SERVERS):
        _drop(key)
