"""Progress of a long study on stderr: a one-line bar on a terminal, silent elsewhere (CI, pipes), and
the harness's lines (``log``) from the first MPI rank. The lines themselves, and the ticker of a long
loop, are ``reference.progress``'s, which both sides use."""

from __future__ import annotations

import sys
import time

from reference.progress import line


class Bar:
    """A one-line progress bar on a terminal (stderr); silent when stderr is not a TTY (CI, pipes)."""

    def __init__(self, total: int, label: str):
        self.total, self.label, self.done, self.t0 = total, label, 0, time.perf_counter()
        self.tty = sys.stderr.isatty()

    def step(self, what: str) -> None:
        self.done += 1
        if not self.tty:
            return
        width = 30
        fill = int(width * self.done / max(self.total, 1))
        elapsed = time.perf_counter() - self.t0
        sys.stderr.write(
            f"\r{self.label} [{'#' * fill}{'.' * (width - fill)}] {self.done}/{self.total} "
            f"{elapsed:5.0f}s {what[:40]:<40}"
        )
        if self.done >= self.total:
            sys.stderr.write("\n")
        sys.stderr.flush()


def mpi_rank() -> int:
    """This process's MPI rank as mpirun set it (0 outside mpirun)."""
    from verification import _RANK

    return int(_RANK or 0)


def log(msg: str) -> None:
    """Progress to stderr (stdout is kept for --json), from the first MPI rank only (under mpirun every
    rank runs the same driver, and each line came once per rank), in one write (reference.progress)."""
    line(msg, mpi_rank())
