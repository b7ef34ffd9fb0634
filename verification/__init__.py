"""The harness: scenes, runs, studies, reports and the command line (docs/architecture.md section 1)."""

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
