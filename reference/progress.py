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

#: Seconds between two progress lines of one loop.
EVERY = 5.0


def line(msg: str, rank: int = 0) -> None:
    """``msg`` and its newline on stderr in one write, from rank 0 only."""
    if rank == 0:
        sys.stderr.write(msg + "\n")
        sys.stderr.flush()


class Progress:
    """Reports a loop's progress: ``tick(done, detail)`` writes "{what} {done} of {total}{detail} (T s)"
    when ``every`` seconds have passed since the loop began or since its last line."""

    def __init__(self, what: str, total: int | None = None, rank: int = 0, every: float | None = None):
        self.what, self.total, self.rank = what, total, rank
        self.every = EVERY if every is None else every
        self.start = self.last = time.perf_counter()

    def tick(self, done: int, detail: str = "") -> bool:
        """Write a line if it is time; returns whether one was written."""
        now = time.perf_counter()
        if now - self.last < self.every:
            return False
        self.last = now
        of = f" of {self.total}" if self.total is not None else ""
        line(f"{self.what} {done}{of}{detail} ({now - self.start:.0f} s)", self.rank)
        return True
