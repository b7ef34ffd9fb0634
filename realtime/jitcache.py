"""Keep numba's on-disk cache of the engine consistent with the engine's sources.

numba invalidates a cached function when its own file changes, not when a function it calls or takes
as an argument does. The integrators' step loops take the model's force kernel as an argument, so their
cache index gains one entry per version of each kernel, each holding a pickled copy of that version's
function: after a few edits (or upgrades) the index held 59 of them, and saving it failed with
numba's "ReferenceError: underlying object has vanished" (numba issue 9348) in the middle of a run.

The rule here: the engine's compiled functions are cached together, under a stamp of all its sources
and numba's version. On import, when the stamp differs, the engine's cache files (``*.nbi``, ``*.nbc``)
are removed and compiled again on first use; nothing else in the directory is touched.
"""

from __future__ import annotations

import hashlib
import os
import tempfile
from pathlib import Path

import numba

STAMP = "tissuebench-realtime.sha256"


def sources_digest(sources: list[Path]) -> str:
    """SHA-256 of numba's version and the bytes of ``sources``, in sorted order."""
    h = hashlib.sha256(numba.__version__.encode())
    for path in sorted(sources):
        h.update(path.name.encode())
        h.update(path.read_bytes())
    return h.hexdigest()


def clear_if_stale(cache_dir: Path, sources: list[Path]) -> bool:
    """Remove the numba cache files in ``cache_dir`` unless its stamp matches ``sources``; then stamp it.
    Returns whether anything was cleared. A directory that cannot be written is left alone (numba then
    does not cache there either)."""
    cache_dir = Path(cache_dir)
    digest = sources_digest(sources)
    stamp = cache_dir / STAMP
    try:
        if stamp.read_text() == digest:
            return False
    except OSError:
        pass
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
        stale = [p for p in cache_dir.iterdir() if p.suffix in (".nbi", ".nbc")]
        for p in stale:
            p.unlink(missing_ok=True)
        fd, tmp = tempfile.mkstemp(dir=cache_dir, prefix=".tmp-stamp-")
        with os.fdopen(fd, "w") as fh:
            fh.write(digest)
        os.replace(tmp, stamp)
    except OSError:
        return False
    return bool(stale)


def guard() -> None:
    """clear_if_stale for the directory numba caches the engine's functions in (the step loops' own)."""
    from .steppers import _run_symplectic_euler

    cache = getattr(_run_symplectic_euler, "_cache", None)
    path = getattr(cache, "cache_path", None)
    if path:
        clear_if_stale(Path(path), list(Path(__file__).parent.glob("*.py")))
