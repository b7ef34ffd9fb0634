"""The harness: scenes, runs, studies, reports and the command line (docs/architecture.md)."""

import logging
import os
from pathlib import Path

# Under mpirun every rank compiles the engine's kernels; numba's on-disk cache is not safe for two
# processes writing one index (the second fails with "underlying object has vanished" when it pickles
# the first's entries), so each rank keeps its own. Set before realtime (and numba) is imported.
_RANK = os.environ.get("OMPI_COMM_WORLD_RANK") or os.environ.get("PMI_RANK")
if _RANK is not None and "NUMBA_CACHE_DIR" not in os.environ:
    _base = Path(os.environ.get("TISSUEBENCH_CACHE", Path.home() / ".cache" / "tissuebench"))
    os.environ["NUMBA_CACHE_DIR"] = str(_base / "numba" / f"rank{_RANK}")

# The reference's factorisations (MUMPS) run their dense kernels in Debian's OpenBLAS (the Makefile installs
# it: Debian's default reference BLAS factorised the stiff beam's 121 000 P2 dofs in 15 s, OpenBLAS in 4),
# one thread a process: the studies solve references on a worker per core, where OpenBLAS's spinning
# threads would contend (two threads gained 3 s of 47 on one solve, with 27 s of system time). Read when
# the library loads, with numpy: set before realtime imports it; a user's setting stands.
os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")

# The engine before anything that loads GNU OpenMP (dolfinx, gmsh): it sets the spin count its
# threaded kernels' threads wait with (realtime/__init__.py), which OpenMP reads only when it loads.
import realtime  # noqa: E402,F401


def quiet_compilers() -> None:
    """Keep FFCx's JIT compiler calls ("INFO:root:x86_64-linux-gnu-gcc ...") off stderr: cffi lowers the
    root logger's threshold to INFO while it compiles, so a level is not enough; a filter on the root
    logger drops those records. Called on import, so that every process of the harness (the command,
    the studies' spawned workers, MPI ranks) is quiet, not only the one that parsed the command line."""
    root = logging.getLogger()
    root.setLevel(logging.WARNING)
    if not any(getattr(f, "tissuebench", False) for f in root.filters):
        only_warnings = logging.Filter()
        only_warnings.filter = lambda record: record.levelno >= logging.WARNING
        only_warnings.tissuebench = True
        root.addFilter(only_warnings)


quiet_compilers()
