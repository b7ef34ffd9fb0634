"""realtime.precompile: what it compiles ahead is what a run then finds in numba's cache."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import pytest

#: A child that counts the engine's functions numba compiles (not those it loads from its cache: numba
#: fires "numba:compile" only on a cache miss) while it runs the command line, and prints them.
_COUNT_COMPILES = """
import json, sys
from numba.core import event

compiled = []


class Count(event.Listener):
    def on_start(self, ev):
        fn = ev.data["dispatcher"].py_func
        if str(fn.__module__).startswith("realtime"):
            compiled.append(f"{fn.__module__}.{fn.__qualname__}")

    def on_end(self, ev):
        pass


event.register("numba:compile", Count())
from verification.cli import main

for args in json.loads(sys.argv[1]):
    assert main(args) == 0, args
print(json.dumps(compiled))
"""


@pytest.mark.slow
def test_a_run_after_precompile_compiles_nothing_of_the_engine(tmp_path):
    """precompile builds its models on a mesh of its own and calls the engine as it sees fit; a run
    builds them from a scene and calls the engine through the runner. If the two passed different
    argument types anywhere (an array's layout, an int for a float), the run would compile again and
    the step ahead would be wasted. On a cold cache (its own numba cache folder), precompile one model,
    then run it through the command line, dynamic with each integrator and static, in a new process:
    not one of the engine's functions may compile there."""
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    ahead = subprocess.run(
        [
            sys.executable,
            "-c",
            "from realtime.precompile import precompile; precompile(processes=1, todo=[('mass-spring', 'float64', 1)])",
        ],
        env=env,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert ahead.returncode == 0, ahead.stderr
    assert "precompile: done" in ahead.stderr
    runs = [
        ["run", "cantilever-dynamic", "--model", "mass-spring", "--integrator", name, "--json"]
        for name in ("symplectic-euler", "central-difference", "implicit-euler")
    ] + [["run", "cantilever", "--model", "mass-spring", "--json"]]
    child = subprocess.run(
        [sys.executable, "-c", _COUNT_COMPILES, json.dumps(runs)], env=env, capture_output=True, text=True, timeout=600
    )
    assert child.returncode == 0, child.stderr
    assert json.loads(child.stdout.splitlines()[-1]) == []


def test_the_precompile_stamp_is_for_numbas_target(monkeypatch):
    """numba keys its cache entries by its target (CPU name and features), which realtime.target chooses
    and a user may set: a cache compiled ahead for another target must not be taken as current, or the
    first step would compile after all (8 to 45 s a model)."""
    from realtime import precompile

    here = precompile._digest()
    triple, name, features = precompile._target()
    monkeypatch.setattr(precompile, "_target", lambda: (triple, name, features + ",-avx512f"))
    assert precompile._digest() != here
