"""Keep numba's on-disk cache of the engine consistent with the engine's sources.

numba invalidates a cached function when its own file changes, not when a function it calls or takes
as an argument does. The integrators' step loops take the model's force kernel as an argument, so their
cache index gains one entry per version of each kernel, each holding a pickled copy of that version's
function: after a few edits (or upgrades) the index held 59 of them, and saving it failed with
numba's "ReferenceError: underlying object has vanished" (numba issue 9348) in the middle of a run.

The rule here: the engine's compiled functions are cached together, under a stamp of all its sources
and numba's version. On import, when the stamp differs, the engine's cache files (``*.nbi``, ``*.nbc``)
are removed and compiled again on first use; nothing else in the directory is touched.

The same error comes without stale versions when processes share the directory: one process saves a
step loop's specialisation for a kernel, another loads that index, compiles a specialisation of its own,
and re-pickling the first key fails (its kernel's type refers to a dispatcher that only the index's
unpickling held). The report's workers settling scenes at once met it. A failed save of an index loses
nothing but the caching of that one specialisation (the index on disk is left as it was), so
``tolerate_vanished`` makes the engine's functions skip such a save instead of failing the run.

A step loop's cached specialisation is found again only if its key, which holds the kernel's dispatcher,
unpickles to the kernel this process imported. numba pickles a dispatcher as a random identity drawn on
first use and, unpickling, returns the live dispatcher of that identity or else builds (and compiles) a
new one, whose type matches nothing. So no process ever found another's step loops: the report's main
process compiled them again in every run, 16 s of its cantilever section, and each settling worker did
too. ``stable_identities`` gives each of the engine's compiled functions an identity drawn from its name
and the sources' stamp instead, the same in every process of one version of the engine.

numba saves a new specialisation by reading the function's index, taking the first data file number
the index does not use, and writing the index and then the data file. Two processes saving at once
(four test workers or studies compiling on a cold cache) read the same index, gave their two keys the
same data file, and each wrote an index holding its own key alone: one specialisation was lost, and
the surviving key could name the other's machine code, which numba then files under that code's own
signature (a miss, compiled again by every later process). ``serialise_saves`` makes every numba
cache save in the process hold an exclusive lock on its folder (``cache_lock``) from the reading of
the index to the writing of the data; ``clear_if_stale`` holds the same lock.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path

import numba
from numba.core import caching
from numba.core.dispatcher import Dispatcher

STAMP = "tissuebench-realtime.sha256"
#: The file in a numba cache folder whose lock the processes saving there take in turn.
LOCK = "tissuebench-cache.lock"


@contextmanager
def cache_lock(folder):
    """Hold an exclusive lock, across processes, on the numba cache folder ``folder`` (flock on LOCK in
    it; closing the file releases it, also when the process dies). A folder that cannot be written is
    not locked: numba does not cache there either."""
    try:
        fd = os.open(os.path.join(folder, LOCK), os.O_RDWR | os.O_CREAT, 0o666)
    except OSError:
        fd = None
    try:
        if fd is not None:
            fcntl.flock(fd, fcntl.LOCK_EX)
        yield
    finally:
        if fd is not None:
            os.close(fd)


def serialise_saves() -> None:
    """Make numba's cache save (index read, data file chosen, index and data written) one step under
    ``cache_lock`` for every cached function of this process (module docstring). Idempotent."""
    save = caching.IndexDataCacheFile.save
    if getattr(save, "serialised", False):
        return

    def locked_save(self, key, data):
        with cache_lock(self._cache_path):
            save(self, key, data)

    locked_save.serialised = True
    caching.IndexDataCacheFile.save = locked_save


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

    def current() -> bool:
        try:
            return stamp.read_text() == digest
        except OSError:
            return False

    if current():
        return False
    try:
        cache_dir.mkdir(parents=True, exist_ok=True)
    except OSError:
        return False
    with cache_lock(cache_dir):
        if current():  # another process cleared and stamped it since the stamp was read
            return False
        try:
            stale = [p for p in cache_dir.iterdir() if p.suffix in (".nbi", ".nbc")]
            for p in stale:
                p.unlink(missing_ok=True)
        except OSError:
            return False
        return write_stamp(stamp, digest) and bool(stale)


def write_stamp(path: Path, digest: str) -> bool:
    """Write ``digest`` to ``path`` through a temporary file and a rename. Returns False, leaving the
    folder alone, where it cannot be written (numba does not cache there either)."""
    try:
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=".tmp-stamp-")
        with os.fdopen(fd, "w") as fh:
            fh.write(digest)
        os.replace(tmp, path)
    except OSError:
        return False
    return True


def guard() -> None:
    """serialise_saves, clear_if_stale for the directory numba caches the engine's functions in (the step
    loops' own), and tolerate_vanished on every compiled function of the engine."""
    from .steppers import _run_symplectic_euler

    serialise_saves()
    sources = list(Path(__file__).parent.glob("*.py"))
    cache = getattr(_run_symplectic_euler, "_cache", None)
    path = getattr(cache, "cache_path", None)
    if path:
        clear_if_stale(Path(path), sources)
    import sys

    dispatchers = [
        obj
        for name, module in list(sys.modules.items())
        if name.startswith(__package__ + ".")
        for obj in list(vars(module).values())
        if isinstance(obj, Dispatcher)
    ]
    stable_identities(dispatchers, sources_digest(sources))
    for obj in dispatchers:
        tolerate_vanished(obj)


def stable_identities(dispatchers: list[Dispatcher], stamp: str) -> None:
    """Give each of ``dispatchers`` the identity numba pickles it as (its ``_uuid``), drawn from ``stamp``
    and its module and qualified name rather than at random (module docstring), where numba allows it:
    before its first pickling, and where no other live dispatcher holds that identity. The others keep
    numba's random identity (their step loops compile in each process, as before)."""
    for d in dispatchers:
        fn = getattr(d, "py_func", None)
        if fn is None or getattr(d, "_MemoMixin__uuid", "") is not None or not hasattr(d, "_set_uuid"):
            continue
        ident = f"tissuebench-{stamp[:16]}-{fn.__module__}.{fn.__qualname__}"
        if d._memo.get(ident) is None:
            d._set_uuid(ident)


def tolerate_vanished(dispatcher: Dispatcher) -> None:
    """Make ``dispatcher``'s cache skip saving a specialisation when numba cannot re-pickle its index
    ("ReferenceError: underlying object has vanished", numba issue 9348; module docstring): the
    specialisation is compiled and used, only not cached."""
    cache = getattr(dispatcher, "_cache", None)
    save = getattr(cache, "save_overload", None)
    if save is None or getattr(save, "tolerates_vanished", False):
        return

    def save_overload(sig, data):
        try:
            save(sig, data)
        except ReferenceError:
            pass

    save_overload.tolerates_vanished = True
    cache.save_overload = save_overload
