"""The one home of the harness's caches: where every entry lives (``entry``, one folder a kind,
``KINDS``), what it is keyed by and stamped with (digests of fields and of the code, the commit, the
machine and the library versions), and how an entry is read (a damaged one is absent)
(docs/data-flow.md). numba's compiled kernels are realtime's own (``realtime.jitcache``)."""

from __future__ import annotations

import functools
import hashlib
import json
import os
import platform
import subprocess
import zipfile
from pathlib import Path

import numpy as np

from .progress import log


def cache_dir() -> Path:
    """The cache's folder: $TISSUEBENCH_CACHE, else ~/.cache/tissuebench."""
    return Path(os.environ.get("TISSUEBENCH_CACHE", Path.home() / ".cache" / "tissuebench"))


#: Every kind of entry, its folder under ``cache_dir()``, and what one holds.
KINDS = {
    "reference": "a scene's ground truth (runs.reference): its displacements, reactions and bar, and an "
    "adaptive truth's levels; the truth evaluated at another engine's points",
    "runs": "a compare row (runs.store) and, where a study asked, its run's displacements beside it; a largest "
    "stable step (studies.stable_step); a seeds experiment's settled answer (studies.seeds.common)",
    "settled": "the built-in engine's static equilibria (engines.settling), the state a timed run starts from",
    "effectivity": "one case of the effectivity table (studies.effectivity)",
}


def entry(kind: str, stem: str, key: str, suffix: str) -> Path:
    """The path of the cache entry ``stem``-``key`` + ``suffix`` of ``kind`` (a key of KINDS), ``key`` the
    digest of everything its content depends on. ValueError for a kind KINDS does not list."""
    if kind not in KINDS:
        raise ValueError(f"cache: kind {kind!r} is not one of {', '.join(KINDS)}")
    return cache_dir() / kind / f"{stem}-{key}{suffix}"


def git_commit(root: Path | None = None) -> str:
    """The short hash of the commit the code in ``root`` (this project's, by default) ran at, with
    "-dirty" when a tracked file differs from that commit: a number from changed code is not that
    commit's, and a baseline or a report that named only the commit would say it was. "unknown"
    outside a git checkout."""

    def git(*args) -> str:
        out = subprocess.run(
            ["git", *args], capture_output=True, text=True, cwd=root or Path(__file__).parent, timeout=5
        )
        return out.stdout.strip() if out.returncode == 0 else ""

    try:
        head = git("rev-parse", "--short", "HEAD")
        if not head:
            return "unknown"
        return head + ("-dirty" if git("status", "--porcelain", "--untracked-files=no") else "")
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def digest(fields: dict) -> str:
    """A cache key: 24 hex digits of the SHA-256 of ``fields`` as sorted JSON."""
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest()[:24]


ROOT = Path(__file__).resolve().parents[1]

#: The code a reference result depends on: its solvers, the region rule both sides share, the constants.
REFERENCE_CODE = ("reference/*.py", "meshes/regions.py", "realtime/material.py")

#: The code a run's row depends on: the engine, its seam, the adapters of other engines and the versions
#: they pin, the runs, the inputs and metrics, and the reference it is compared with.
RUN_CODE = (
    "realtime/*.py",
    "realtime/models/*.py",
    "verification/inputs.py",
    "verification/metrics.py",
    "verification/engines/*.py",
    "verification/runs/*.py",
    "adapters/*.py",
    "adapters/requirements.txt",
    *REFERENCE_CODE,
)


@functools.cache
def code_digest(patterns: tuple[str, ...]) -> str:
    """Digest of the source files matching ``patterns`` (relative to the project root): part of every
    cache key, so that a cached result is never one that other code made."""
    files = sorted({f for pattern in patterns for f in ROOT.glob(pattern)})
    return digest({str(f.relative_to(ROOT)): hashlib.sha256(f.read_bytes()).hexdigest() for f in files})


@functools.cache
def machine_id() -> dict:
    """What a timing depends on: the architecture, the processor's name and the number of cores."""
    model = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {"arch": platform.machine(), "cpu": model, "cores": os.cpu_count()}


#: The Python distributions a cached result's numbers depend on: the engine's arrays and kernels (numpy,
#: numba and its LLVM), the reference's finite elements and solvers (dolfinx with its form compiler,
#: PETSc's bindings, MPI's), scipy's sparse algebra and meshio's readers.
LIBRARIES = (
    "numpy",
    "scipy",
    "numba",
    "llvmlite",
    "fenics-dolfinx",
    "fenics-basix",
    "fenics-ffcx",
    "fenics-ufl",
    "petsc4py",
    "mpi4py",
    "meshio",
)


@functools.cache
def library_versions() -> dict:
    """The installed versions of LIBRARIES (None for one that is not installed) and of the PETSc library
    itself (Debian updates it apart from its bindings): part of the run and reference keys, so that a
    result cached before an upgrade is not read as this installation's."""
    from importlib.metadata import PackageNotFoundError, version

    out = {}
    for name in LIBRARIES:
        try:
            out[name] = version(name)
        except PackageNotFoundError:
            out[name] = None
    try:
        from petsc4py import PETSc

        out["PETSc"] = ".".join(str(v) for v in PETSc.Sys.getVersion())
    except ImportError:
        out["PETSc"] = None
    return out


@functools.cache
def installed_versions(python: Path) -> dict:
    """Every distribution installed for the interpreter ``python`` (another venv's: the engines'), name
    -> version, read by that interpreter; {} when it is not there or does not answer. Part of an adapter
    run's key: the requirements file pins what the engines' venv was asked to hold, not what it holds."""
    code = "import importlib.metadata as m, json; print(json.dumps({d.metadata['Name']: d.version for d in m.distributions()}))"
    if not Path(python).exists():
        return {}
    try:
        run = subprocess.run([str(python), "-c", code], capture_output=True, text=True, timeout=60)
        return dict(sorted(json.loads(run.stdout).items())) if run.returncode == 0 else {}
    except (OSError, ValueError, subprocess.SubprocessError):
        return {}


def versions() -> dict:
    import numba
    import scipy

    return {
        "python": platform.python_version(),
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": numba.__version__,
    }


def read_cached(path: Path, read):
    """``read(path)`` for a cache entry, or None if there is none or it is damaged (truncated by a full
    disk or a copy, not a zip or JSON file, a key missing): the caller computes it again and writes it
    over, so a damaged entry costs a recomputation, never a traceback. Says so on stderr."""
    if not path.exists():
        return None
    try:
        return read(path)
    except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile) as exc:
        why = " ".join(str(exc).split()) or type(exc).__name__
        log(f"cache: {path}: damaged ({why}); computing it again")
        return None
