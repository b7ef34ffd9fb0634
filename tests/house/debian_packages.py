"""Which Debian packages the Python modules of a process came from, and whether the Makefile installs them.

A fresh Debian 12 machine has only what ``make`` installs. A module loaded from outside the project's
venv (Debian's ``/usr/lib/python3*``, or ``/usr/local``) must therefore belong to a Debian package that
the Makefile's ``APT_PACKAGES`` installs, directly or as a dependency, or to a Python distribution that
pip installs for the project where Debian's copy is absent; otherwise ``make test`` passes on a
developer's machine and fails on a new one (meshio's XDMF writer importing h5py was such a case).
"""

from __future__ import annotations

import os
import re
import subprocess
import sys
from collections import defaultdict
from pathlib import Path

MAKEFILE = Path(__file__).resolve().parents[2] / "Makefile"

#: Debian packages whose modules a dependency imports only if they are there: package -> (the module,
#: the importer that must still import without it, why). A test imports each importer with the module
#: blocked, so an entry here cannot hide a real dependency.
OPTIONAL = {
    "python3-yaml": ("yaml", "numba", "numba reads a .numba_config.yaml only when PyYAML imports"),
}


def makefile_packages(makefile: Path = MAKEFILE, variable: str = "APT_PACKAGES") -> list[str]:
    """The Debian packages of the Makefile's ``APT_PACKAGES :=`` line (or ``variable``'s)."""
    m = re.search(rf"^{variable}\s*:?=\s*(.*)$", Path(makefile).read_text(), flags=re.MULTILINE)
    if m is None:
        raise ValueError(f"{makefile}: no {variable} line")
    return m.group(1).split()


def _installed() -> tuple[dict[str, list[list[str]]], dict[str, set[str]]]:
    """Installed packages -> their dependencies (a list of alternatives each), and virtual names ->
    the installed packages that provide them."""
    fmt = r"${Package}\t${Status}\t${Pre-Depends}, ${Depends}\t${Provides}\n"
    out = subprocess.run(["dpkg-query", "-W", "-f", fmt], capture_output=True, text=True, check=True).stdout
    depends, provides = {}, defaultdict(set)
    for line in out.splitlines():
        name, status, deps, prov = (line.split("\t") + ["", "", ""])[:4]
        if not status.endswith("installed") or "not-installed" in status or "config-files" in status:
            continue
        groups = []
        for group in deps.split(","):
            alts = [_bare(a) for a in group.split("|") if _bare(a)]
            if alts:
                groups.append(alts)
        depends[name] = groups
        for p in prov.split(","):
            if _bare(p):
                provides[_bare(p)].add(name)
    return depends, provides


def _bare(spec: str) -> str:
    """``libfoo1 (>= 2.0):any`` -> ``libfoo1``."""
    return re.sub(r"\(.*?\)|\[.*?\]|<.*?>", "", spec).strip().split(":")[0]


def dependency_closure(packages: list[str]) -> set[str]:
    """The installed packages that ``packages`` pull in through Depends and Pre-Depends (every installed
    alternative of an ``a | b`` dependency counts, as does every installed provider of a virtual name)."""
    depends, provides = _installed()
    seen, todo = set(), list(packages)
    while todo:
        p = todo.pop()
        for name in {p} | provides.get(p, set()):
            if name in seen or name not in depends:
                continue
            seen.add(name)
            for alts in depends[name]:
                todo.extend(alts)
    return seen


def outside_venv_files(modules: dict | None = None) -> dict[str, list[str]]:
    """One file per top-level module loaded from outside ``sys.prefix`` (the venv) and outside the
    project: file -> the module names it stands for."""
    modules = sys.modules if modules is None else modules
    project = os.path.abspath(MAKEFILE.parent)
    venv = os.path.abspath(sys.prefix)
    files: dict[str, list[str]] = {}
    for name, mod in list(modules.items()):
        f = getattr(mod, "__file__", None)
        if not isinstance(f, str):
            continue
        path = os.path.abspath(f)  # not resolved: dpkg knows the path as installed, links included
        if path.startswith(venv + "/") or path.startswith(project + "/") or not path.startswith("/usr/"):
            continue
        files.setdefault(path, []).append(name)
    return files


def loaded_libraries(maps: str = "/proc/self/maps") -> dict[str, list[str]]:
    """Shared libraries (``*.so*``) mapped into this process from /usr and outside the venv: file -> [its
    name]. numba's threads come from Debian's libtbb, which no Python module names."""
    venv = os.path.abspath(sys.prefix)
    files: dict[str, list[str]] = {}
    try:
        lines = Path(maps).read_text().splitlines()
    except OSError:
        return files
    for line in lines:
        parts = line.split(maxsplit=5)
        path = parts[5] if len(parts) == 6 else ""
        if path.startswith("/usr/") and ".so" in os.path.basename(path) and not path.startswith(venv + "/"):
            files[path] = [os.path.basename(path)]
    return files


def _dpkg_owners(files: list[str]) -> dict[str, str]:
    found = {}
    for i in range(0, len(files), 200):
        out = subprocess.run(["dpkg", "-S", *files[i : i + 200]], capture_output=True, text=True).stdout
        for line in out.splitlines():
            if line.startswith("diversion") or ": " not in line:
                continue
            pkgs, path = line.split(": ", 1)
            found[path] = pkgs.split(",")[0].strip().split(":")[0]
    return found


def owners(files: list[str]) -> dict[str, str | None]:
    """file -> the Debian package that owns it (``dpkg -S``), None for a file no package owns. A path
    through a symbolic link dpkg does not know (dolfinx lives under the /usr/lib/petsc alternative) is
    looked up again as its resolved path, and a /usr/lib path as the /lib path that Debian 12's merged
    /usr lists some libraries under (libc6's)."""
    found = _dpkg_owners(files)
    unknown = [f for f in files if f not in found]
    resolved = {f: os.path.realpath(f) for f in unknown}
    again = _dpkg_owners(sorted(set(resolved.values())))
    merged = {f: resolved[f][len("/usr") :] for f in unknown if resolved[f].startswith("/usr/lib/")}
    merged_found = _dpkg_owners(sorted(set(merged.values())))
    return {f: found.get(f) or again.get(resolved.get(f, "")) or merged_found.get(merged.get(f, "")) for f in files}


def pip_supplied(project: str = "tissuebench") -> set[str]:
    """Normalised names of the Python distributions pip installs for the project (its dependencies with
    the dev extra, recursively). pip skips one that Debian already provides to the venv, but installs
    it on a machine without it, so a module of one of these is no fresh-machine defect."""
    from importlib import metadata

    from packaging.requirements import Requirement

    norm = lambda name: re.sub(r"[-_.]+", "-", name).lower()  # noqa: E731
    seen, todo = set(), [(project, {"dev"})]
    while todo:
        name, extras = todo.pop()
        if norm(name) in seen:
            continue
        seen.add(norm(name))
        try:
            requires = metadata.distribution(name).requires or []
        except metadata.PackageNotFoundError:
            continue
        for text in requires:
            req = Requirement(text)
            if req.marker is None or any(req.marker.evaluate({"extra": e}) for e in extras or {""}):
                todo.append((req.name, set(req.extras)))
    return seen - {norm(project)}


def distribution_of(module: str) -> set[str]:
    """Normalised names of the distributions that provide a top-level module."""
    from importlib import metadata

    return {re.sub(r"[-_.]+", "-", d).lower() for d in metadata.packages_distributions().get(module, [])}


def loaded_files() -> dict[str, list[str]]:
    """What this process loaded from outside the venv and the project: its modules' files
    (outside_venv_files) and its shared libraries (loaded_libraries), file -> the names they stand for."""
    return {**outside_venv_files(), **loaded_libraries()}


def missing_packages(
    makefile: Path = MAKEFILE, files: dict[str, list[str]] | None = None, also: tuple[str, ...] = ()
) -> dict[str, list[str]]:
    """Debian packages (or ``<no package>: FILE``) that loaded files came from and that the Makefile
    neither installs nor pulls in (with its variables ``also``, a target's own packages, beside
    APT_PACKAGES): package -> the modules or libraries. The files are ``files`` if given (what other
    processes loaded, say), else this process's loaded_files()."""
    closure = dependency_closure([p for v in ("APT_PACKAGES", *also) for p in makefile_packages(makefile, v)])
    from_pip = pip_supplied()
    if files is None:
        files = loaded_files()
    missing: dict[str, list[str]] = defaultdict(list)
    for path, pkg in owners(sorted(files)).items():
        if pkg in closure or pkg in OPTIONAL:
            continue
        if any(distribution_of(m.split(".")[0]) & from_pip for m in files[path]):
            continue  # pip installs it where Debian's copy is absent
        missing[f"<no package>: {path}" if pkg is None else pkg].extend(files[path])
    return {k: sorted(v) for k, v in missing.items()}
