"""Adapter runs served by one process (verification/engines/served.py, adapters/exported.py ``serve``): the
same answers as a process a run, a refusal that leaves the service up, and a run past its timeout or a crash
that ends it, the next run starting another. The protocol's cases run on a made-up adapter (Python's own,
no engine); the answers on MuJoCo's flex."""

from __future__ import annotations

import dataclasses
import sys
import textwrap
import threading

import numpy as np
import pytest

from tests.verification.test_adapters_newton_mujoco import hanging_scene, needs_engines
from verification.engines import served
from verification.engines.command import CommandError

#: A made-up adapter speaking the protocol: each run's command line is [what, seconds]: "ok" and "refuse"
#: (exit 2) end the run, "crash" ends the process; each sleeps its seconds first.
FAKE = textwrap.dedent(
    f"""
    import json, os, sys, time
    for line in sys.stdin:
        what, seconds = json.loads(line)
        print(f"fake: pid {{os.getpid()}} runs {{what}}", file=sys.stderr, flush=True)
        time.sleep(float(seconds))
        if what == "crash":
            print("fake: Traceback, as a failing engine writes", file=sys.stderr, flush=True)
            sys.exit(1)
        status = 2 if what == "refuse" else 0
        print("{served.SERVED} " + str(status), file=sys.stderr, flush=True)
    """
)


@pytest.fixture
def fake(tmp_path):
    script = tmp_path / "fake_adapter.py"
    script.write_text(FAKE)
    yield [sys.executable, str(script)]
    served.close_all()


def _pid(lines: list[str]) -> str:
    return next(ln.split()[2] for ln in lines if ln.startswith("fake: pid"))


def test_one_server_serves_runs_and_a_refusal_and_a_crash_ends_it(fake):
    """Two runs and a refusal (exit 2) in one process, each line relayed and the status returned; a crash
    returns its status and last line, and the next run has a process of its own."""
    lines: list[str] = []
    for what, status in (("ok", 0), ("refuse", 2), ("ok", 0)):
        assert served.served_call(fake + [what, "0"], 30.0, lines.append, "fake")[0] == status
    pids = {ln.split()[2] for ln in lines}
    assert len(pids) == 1 and len(lines) == 3
    lines.clear()
    status, last = served.served_call(fake + ["crash", "0"], 30.0, lines.append, "fake")
    assert status == 1 and last == "fake: Traceback, as a failing engine writes"
    crashed = _pid(lines)
    lines.clear()
    assert served.served_call(fake + ["ok", "0"], 30.0, lines.append, "fake")[0] == 0
    assert _pid(lines) != crashed and crashed in pids


def test_a_served_run_past_its_timeout_is_stopped_with_its_server(fake):
    """A run past its timeout is one line naming it (as a process a run's is) and its server is killed and
    dropped: the next run starts another."""
    with pytest.raises(CommandError, match="fake: still running after 2 s, stopped"):
        served.served_call(fake + ["ok", "60"], 2.0, lambda line: None, "fake")
    key = (fake[0], fake[1], threading.get_ident())  # this thread's server of the fake adapter
    assert key not in served._SERVERS  # killed with its run
    lines: list[str] = []
    assert served.served_call(fake + ["ok", "0"], 30.0, lines.append, "fake")[0] == 0
    assert _pid(lines) == str(served._SERVERS[key].proc.pid)


@needs_engines
def test_a_served_run_is_the_run_of_a_process_of_its_own(tmp_path):
    """MuJoCo's flex on a hanging bar at 1 ms, run twice by one server and once by a process of its own: the
    same displacement bit for bit, the same steps (one code, one machine: the process is all that differs)."""
    from verification.engines.adapters import ADAPTERS
    from verification.runs.simulate import run_model

    scene, mujoco = hanging_scene(tmp_path, "stvk", 1e4, length=0.04), ADAPTERS["mujoco"]
    try:
        first, second = (run_model(scene, "mujoco-flex", dt=1e-3, engine=mujoco) for _ in range(2))
    finally:
        served.close_all()
    alone = run_model(scene, "mujoco-flex", dt=1e-3, engine=dataclasses.replace(mujoco, serves=False))
    for r in (first, second):
        assert np.array_equal(r.displacement, alone.displacement)
        assert r.meta["static"]["steps"] == alone.meta["static"]["steps"]
