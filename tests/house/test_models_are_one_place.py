"""A model is one file (docs/contributing.md): adding one is adding its file under realtime/models/, and
its name is a string in at most three files besides it, the tests and the docs. Read from the sources
and from a copy of the engine with one more model, so that a table of names that creeps back, or a
fact a new model would have to add elsewhere, fails here, naming where."""

import ast
import os
import re
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from realtime.models import SPECS

ROOT = Path(__file__).resolve().parents[2]
#: Where a model's name may be written as a string without limit: its own file, the tests, the docs.
FREE = ("realtime/models/", "tests/", "docs/")
#: The files outside those that may still name models as strings: data that chooses models (the CI
#: gates' table), not code that knows them.
MAX_FILES = 3


def _named_in_python(source: str, names: set[str]) -> list[int]:
    """The lines of ``source`` where a string constant is exactly a model's name."""
    return [
        node.lineno
        for node in ast.walk(ast.parse(source))
        if isinstance(node, ast.Constant) and isinstance(node.value, str) and node.value in names
    ]


def _named_in_text(text: str, names: set[str]) -> list[int]:
    """The lines of a data file (TOML, JSON, a Makefile) where a quoted string is exactly a model's name."""
    alternatives = "|".join(re.escape(n) for n in names)
    quoted = re.compile(r"""(["'])(""" + alternatives + r""")\1""")
    return [k + 1 for k, line in enumerate(text.splitlines()) if quoted.search(line)]


def _files_naming_models() -> dict[str, list[int]]:
    names = set(SPECS)
    tracked = subprocess.run(["git", "ls-files"], cwd=ROOT, capture_output=True, text=True, check=True).stdout
    out = {}
    for rel in tracked.split():
        path = ROOT / rel
        if rel.startswith(FREE) or rel.endswith(".md") or not path.is_file():
            continue
        if rel.endswith(".py"):
            lines = _named_in_python(path.read_text(), names)
        elif path.suffix in (".toml", ".json", ".cfg", ".txt", ".yaml", ".yml") or path.name == "Makefile":
            lines = _named_in_text(path.read_text(errors="replace"), names)
        else:
            continue
        if lines:
            out[rel] = lines
    return out


def test_the_finder_sees_a_name_in_code_and_in_data_but_not_in_prose():
    names = {"stvk-tm"}
    code = 'MODELS = ("stvk-tm",)\nx = f"{y} stvk-tm"\n"""stvk-tm\'s docstring"""\n'
    assert _named_in_python(code, names) == [1]
    assert _named_in_text('model = "stvk-tm"\n# stvk-tm, in prose\n', names) == [1]


def test_model_names_are_strings_in_at_most_three_files_outside_the_models_tests_and_docs():
    found = _files_naming_models()
    where = "; ".join(f"{f}:{','.join(map(str, lines))}" for f, lines in sorted(found.items()))
    assert len(found) <= MAX_FILES, f"model names as strings in {len(found)} files (at most {MAX_FILES}): {where}"


TWIN = '''
"""linear-tm-twin: linear-tm under another name, to show that a model is one file."""

from ..model import Model
from . import linear_tm
from .base import ModelSpec

NAME = "linear-tm-twin"


def build(points, tets, material, loading=None) -> Model:
    """linear-tm, named NAME."""
    model = linear_tm.build(points, tets, material, loading)
    return Model(**{**model.__dict__, "name": NAME})


SPEC = ModelSpec(name=NAME, build=build, law="linear-tm's", linear=True, integrators=("symplectic-euler", "implicit-euler"), cost=1, rank=99)
'''

PROBE = """
import numpy as np
import realtime
from realtime import Material
from verification.cli.parser import build_parser
from verification.engines import engine_for, offered, spec_of

name = "linear-tm-twin"
assert realtime.__file__.startswith(COPY), realtime.__file__
assert name in realtime.SPECS and name in offered() and engine_for(name).name == "realtime"
spec = spec_of(name)
assert spec.linear and "implicit-euler" in spec.integrators and not spec.quasi_static
args = build_parser().parse_args(["stability", "cantilever", "--models", name])
assert args.models == [name]
points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], dtype=float) * 0.01
model = realtime.build_model(name, points, np.array([[0, 1, 2, 3]]), Material(1e4, 0.3, 1000.0))
assert model.name == name and np.isfinite(model.internal_force(np.full((4, 3), 1e-4))).all()
print("ok")
"""


def test_a_model_added_as_one_file_is_built_listed_and_read_by_the_harness(tmp_path):
    """A copy of the engine with one more file in realtime/models/ (linear-tm under another name): the
    registry builds it, the seam offers it with its spec's facts, the command line takes it. Nothing
    else was edited."""
    copy = tmp_path / "realtime"
    shutil.copytree(ROOT / "realtime", copy, ignore=shutil.ignore_patterns("__pycache__"))
    (copy / "models" / "linear_tm_twin.py").write_text(textwrap.dedent(TWIN))
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(tmp_path), str(ROOT)])}
    probe = f"COPY = {str(copy)!r}\n" + PROBE
    out = subprocess.run([sys.executable, "-c", probe], env=env, cwd=tmp_path, capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == "ok", out.stderr[-3000:]


def test_every_cache_entry_is_named_by_the_caches_one_home():
    """The harness's caches have one home (verification/cache.py: ``entry`` and its KINDS): no other
    module builds a path under the cache's folder itself, so that every kind of entry is listed there
    with what it holds. An unknown kind is refused."""
    from verification.cache import KINDS, entry

    outside = [
        f"{path.relative_to(ROOT)}:{node.lineno}"
        for pkg in ("verification", "reference", "realtime", "meshes")
        for path in sorted((ROOT / pkg).rglob("*.py"))
        if path != ROOT / "verification" / "cache.py"
        for node in ast.walk(ast.parse(path.read_text()))
        if isinstance(node, ast.BinOp)
        and isinstance(node.op, ast.Div)
        and isinstance(node.left, ast.Call)
        and getattr(node.left.func, "id", getattr(node.left.func, "attr", None)) == "cache_dir"
    ]
    assert not outside, "a cache path built outside verification.cache.entry: " + ", ".join(outside)
    assert entry("runs", "s", "k", ".json").parent.name == "runs" and set(KINDS) >= {"reference", "settled"}
    with pytest.raises(ValueError, match="'scratch'"):
        entry("scratch", "s", "k", ".json")
