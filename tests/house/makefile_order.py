"""Which of the Makefile's targets use a venv before the Debian packages are installed, read from make's
own database (``make -pRrnq``), not from the Makefile's text.

A fresh Debian 12 machine has neither dolfinx nor Debian's numpy until the target whose recipe runs
``apt-get install`` has run. Under ``make -j2`` every target that does not wait for it, directly or
through its prerequisites (order-only ones included), may run beside it: a venv made before
``python3-venv`` is there, a pip install whose numpy constraint reads ``numpy==`` (the defect that failed
a fresh machine's first ``make test``). A machine that ran ``make`` once never sees it, so this check
reads the order itself.

A recipe "uses a venv" when it creates one (``-m venv``) or runs anything under a venv's ``bin/`` (the
venvs are the folders some recipe creates). It "waits" when the apt target is in the prerequisite closure
of its target, or when an earlier line of the same recipe ran a sub-make (``$(MAKE) ... T``) of a target
T whose closure holds it: recipe lines run in order.
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass, field
from pathlib import Path

MAKEFILE = Path(__file__).resolve().parents[2] / "Makefile"

_RULE = re.compile(r"^([^\s#:=][^:=]*?):(?!=)\s*(.*)$")
_VARIABLE = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*)\s*(?::{1,3}|\?|\+)?=\s?(.*)$")
_REFERENCE = re.compile(r"\$[({]([A-Za-z_][A-Za-z0-9_]*)[)}]")
_VENV_MADE = re.compile(r"-m\s+venv\s+(?:--?\S+\s+)*([^\s;|&)]+)")


@dataclass
class Rule:
    """One target of make's database: its prerequisites (normal and order-only) and its recipe lines
    with make's variables expanded (``$$`` left as the shell's ``$``)."""

    target: str
    prerequisites: list[str] = field(default_factory=list)
    recipe: list[str] = field(default_factory=list)


def database(makefile: Path = MAKEFILE) -> tuple[dict[str, Rule], dict[str, str]]:
    """The rules and variables make reads from ``makefile``, without running a recipe (-n -q) and without
    its built-in rules and variables (-R -r)."""
    run = subprocess.run(
        ["make", "-pRrnq", "-f", str(makefile)], capture_output=True, text=True, cwd=Path(makefile).parent
    )
    if "# Files" not in run.stdout:
        raise RuntimeError(f"make -pRrnq -f {makefile} printed no database: {run.stderr.strip()[:300]}")
    variables: dict[str, str] = {}
    rules: dict[str, Rule] = {}
    files = run.stdout.split("\n# Files\n", 1)
    for line in files[0].splitlines():
        m = _VARIABLE.match(line)
        if m:
            variables[m.group(1)] = m.group(2)
    current: Rule | None = None
    for line in files[1].splitlines():
        if line.startswith("\t") and current is not None:
            current.recipe.append(line[1:])
            continue
        if not line.strip():
            current = None
            continue
        if line.startswith("#"):
            continue
        m = _RULE.match(line)
        if m and not re.match(r"\.[A-Z_]+$", m.group(1).strip()):  # not .PHONY, .SUFFIXES, ...
            current = rules.setdefault(m.group(1).strip(), Rule(m.group(1).strip()))
            current.prerequisites += [p for p in m.group(2).split() if p != "|"]
    for rule in rules.values():
        rule.recipe = [expand(line, variables) for line in rule.recipe]
    return rules, variables


def expand(text: str, variables: dict[str, str], depth: int = 0) -> str:
    """``text`` with ``$(NAME)`` and ``${NAME}`` replaced by the variables' values, recursively; ``$$``
    becomes ``$``."""
    if depth > 20:
        raise RuntimeError(f"variables nest too deep in {text!r}")
    parts = text.split("$$")
    out = [_REFERENCE.sub(lambda m: expand(variables.get(m.group(1), ""), variables, depth + 1), p) for p in parts]
    return "$".join(out)


def closure(rules: dict[str, Rule], target: str) -> set[str]:
    """Every target ``target`` waits for, directly or through its prerequisites."""
    seen: set[str] = set()
    todo = [target]
    while todo:
        t = todo.pop()
        for p in rules.get(t, Rule(t)).prerequisites:
            if p not in seen:
                seen.add(p)
                todo.append(p)
    return seen


def apt_targets(rules: dict[str, Rule]) -> set[str]:
    """The targets whose recipe installs the Debian packages."""
    return {t for t, r in rules.items() if any("apt-get" in line and "install" in line for line in r.recipe)}


def venvs(rules: dict[str, Rule]) -> set[str]:
    """The folders some recipe creates a venv in (``python3 -m venv ... DIR``)."""
    return {m.group(1).rstrip("/") for r in rules.values() for line in r.recipe for m in _VENV_MADE.finditer(line)}


def _submake_targets(line: str, makecmd: str) -> list[str] | None:
    """The targets a recipe line's sub-make builds, or None when the line runs no sub-make."""
    words = line.split()
    if not words or words[0] not in (makecmd, "make", "$(MAKE)"):
        return None
    return [w for w in words[1:] if not w.startswith("-") and "=" not in w]


def unordered_venv_uses(makefile: Path = MAKEFILE) -> list[str]:
    """One line per recipe line that uses a venv without waiting for the Debian packages: the target and
    the line. Empty when every such use waits."""
    rules, variables = database(makefile)
    apt = apt_targets(rules)
    if not apt:
        raise RuntimeError(f"{makefile}: no target's recipe runs apt-get install")
    folders = venvs(rules)
    uses_venv = re.compile(
        r"-m\s+venv\b|(?:^|[\s;|&('\"=])(?:" + "|".join(re.escape(f) for f in sorted(folders)) + r")/bin/"
    )
    makecmd = expand(variables.get("MAKE", "make"), variables).split()[0] if variables.get("MAKE") else "make"
    bad = []
    for target, rule in sorted(rules.items()):
        waits = bool(closure(rules, target) & apt) or target in apt
        for line in rule.recipe:
            sub = _submake_targets(line, makecmd)
            if sub is not None and any(t in apt or closure(rules, t) & apt for t in sub):
                waits = True
            if not waits and uses_venv.search(line):
                bad.append(f"{target}: {line.strip()}")
    return bad
