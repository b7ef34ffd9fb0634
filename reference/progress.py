"""Progress on stderr for a user who waits: whole lines, at most every few seconds, from rank 0.

Several processes (the studies' workers, MPI ranks) share one terminal, so a line is written in one
``write`` call: ``print`` writes the text and its newline separately, and two workers' lines ran
together on one line between them. A loop whose passes are short but whose whole takes minutes (a
Newmark run, Newton's iterations on a large mesh) reports through ``Progress``: a line when EVERY
seconds have passed since the last, so that a silent stretch lasts at most one pass beyond it.
"""

from __future__ import annotations

import sys
import time

#: Seconds between two progress lines: a loop reports when this long has passed since the last line
#: of this process, whoever wrote it, so that the joins between loops and blocks stay under 10 s.
EVERY = 3.0
#: When this process last wrote a line (time.perf_counter()).
_LAST = [time.perf_counter()]
#: What the lines of a loop or a heartbeat are part of (``within``): the adaptive reference's level and
#: bar so far, said in every such line so that a user who waits sees where it stands.
_WITHIN: list[str] = []


class within:
    """A context manager: while it is open, ``line``'s, ``Progress``'s and ``Heartbeat``'s lines start with ``what``
    ("reference: adaptive level 2 (bar 0.0061, asked 0.005)") in place of "reference:"."""

    def __init__(self, what: str):
        self.what = what

    def __enter__(self):
        _WITHIN.append(self.what)
        return self

    def __exit__(self, *exc):
        _WITHIN.pop()
        return False


def _placed(what: str) -> str:
    """``what`` with the innermost ``within`` in place of its "reference:"."""
    if _WITHIN and what.startswith("reference: "):
        return f"{_WITHIN[-1]}: {what.removeprefix('reference: ')}"
    return what


def line(msg: str, rank: int = 0) -> None:
    """``msg`` and its newline on stderr in one write, from rank 0 only (within a ``within``, said as part of it)."""
    if rank == 0:
        sys.stderr.write(_placed(msg) + "\n")
        sys.stderr.flush()
        _LAST[0] = time.perf_counter()


class Progress:
    """Reports a loop's progress: ``tick(done, detail)`` writes "{what} {done} of {total}{detail} (T s)",
    T since the loop began, when ``every`` seconds have passed since this process's last line."""

    def __init__(self, what: str, total: int | None = None, rank: int = 0, every: float | None = None):
        self.what, self.total, self.rank = what, total, rank
        self.every = EVERY if every is None else every
        self.start = time.perf_counter()

    def tick(self, done: int, detail: str = "") -> bool:
        """Write a line if it is time; returns whether one was written."""
        now = time.perf_counter()
        if now - _LAST[0] < self.every:
            return False
        of = f" of {self.total}" if self.total is not None else ""
        line(f"{self.what} {done}{of}{detail} ({now - self.start:.0f} s)", self.rank)
        return True


#: The heartbeat's watcher: writes "{what} ({T} s)" on stderr every ``every`` seconds until its stdin
#: closes (the block ended, or the process that started it died).
_WATCHER = """
import select, sys, time
what, every, start = sys.argv[1], float(sys.argv[2]), time.perf_counter()
while not select.select([sys.stdin], [], [], every)[0]:
    sys.stderr.write(f"{what} ({time.perf_counter() - start:.0f} s)\\n")
    sys.stderr.flush()
"""


class Heartbeat:
    """A line every ``every`` seconds (EVERY, at least 1) while a block that reports nothing of its own
    runs: a factorisation, the set-up of a refined level (``stop`` may end it before the block does).
    PETSc's and dolfinx's bindings hold Python's lock while they work, so a thread could not speak
    then: a small watcher process writes the lines and ends when the block ends (or this process dies,
    which closes its stdin). Rank 0 only; a context manager."""

    def __init__(self, what: str, rank: int = 0, every: float | None = None):
        self.what, self.rank = what, rank
        self.every = max(EVERY if every is None else every, 1.0)
        self._watcher = None

    def __enter__(self):
        if self.rank == 0:
            import subprocess

            self._watcher = subprocess.Popen(
                [sys.executable, "-c", _WATCHER, _placed(self.what), repr(self.every)], stdin=subprocess.PIPE
            )
        return self

    def stop(self) -> None:
        """End the lines now (idempotent)."""
        if self._watcher is not None:
            self._watcher.stdin.close()
            self._watcher.wait()
            self._watcher = None
            _LAST[0] = time.perf_counter()  # its lines were this process's too

    def __exit__(self, *exc):
        self.stop()
        return False
