"""The advice on the organs users bring, timed cold (``tissuebench bench --advice``): ``advise SCENE
--tol 0.05 --rate 60`` on SOFA's liver and on a user's liver pressed by a 5 mm tool
(``scenes/bench/user-liver.toml``), each in a process of its own with an empty cache (its references,
runs, settlings and compiled kernels made afresh), and whether it decided: a pick whose whole interval
is within the tolerance, or "no model" with a truth whose bar is at most a third of it. "Cannot decide"
is not a decision.

Speed is measured here, never in tests; the numbers are this machine's, written with its description.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

from verification.bench.suite import machine
from verification.progress import log

#: (label, scene, tolerance, rate Hz): the questions the advisor must decide within five minutes.
CASES = (
    ("sofa-liver", "sofa-liver", 0.05, 60.0),
    ("user-liver", str(Path(__file__).parents[1] / "scenes" / "bench" / "user-liver.toml"), 0.05, 60.0),
)
#: A "no model" answer decides only with a truth this sharp: its bar at most this share of the tolerance.
NO_MODEL_BAR = 1.0 / 3.0


def decided(out: dict, tol: float) -> tuple[bool, str]:
    """Whether an advice (``advise --json``) decided, and what it said: a pick (its interval within
    ``tol`` by the verdict rule), or no model with a truth whose bar is at most NO_MODEL_BAR ``tol`` and
    no candidate left undecided."""
    if out.get("model"):
        return True, f"{out['model']} ({out['integrator']}) on the mesh refined {out.get('refine') or 0} times"
    bar = (out.get("reference") or {}).get("bar")
    if out.get("undecided") or bar is None or bar > NO_MODEL_BAR * tol:
        return False, "cannot decide" if out.get("undecided") else f"no model, the truth's bar {bar} too wide"
    return True, "no model"


def _one(label: str, scene: str, tol: float, rate: float) -> dict:
    """One cold advice: its wall time, answer and whether it decided."""
    with tempfile.TemporaryDirectory(prefix=f"tissuebench-advice-{label}-") as cache:
        env = {**os.environ, "TISSUEBENCH_CACHE": cache}
        cmd = [
            sys.executable,
            "-m",
            "verification.cli",
            "advise",
            scene,
            "--tol",
            str(tol),
            "--rate",
            str(rate),
            "--json",
        ]
        log(f"bench --advice: {label}: {' '.join(cmd[2:])}, cache {cache}")
        t0 = time.perf_counter()
        proc = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True)  # its progress to our stderr
        wall = time.perf_counter() - t0
    row = {"case": label, "scene": scene, "tol": tol, "rate_hz": rate, "wall_s": wall, "exit": proc.returncode}
    if proc.returncode != 0:
        return {**row, "decided": False, "answer": f"exit {proc.returncode}"}
    out = json.loads(proc.stdout)
    ok, answer = decided(out, tol)
    truth = out.get("reference") or {}
    return {**row, "decided": ok, "answer": answer, "interval": out.get("interval"), "truth_bar": truth.get("bar"),
            "truth": truth.get("why"), "why": out.get("why")}  # fmt: skip


def run(cases=None) -> dict:
    """Every case of CASES (or those whose label contains one of ``cases``), one after the other."""
    chosen = [c for c in CASES if not cases or any(k in c[0] for k in cases)]
    return {"machine": machine(), "rows": [_one(*c) for c in chosen]}


def format_table(out: dict) -> str:
    m = out["machine"]
    lines = [f"advice from cold caches on {m['cpu']} ({m['cores']} cores), commit {m['commit']}, {m['date']}"]
    lines += [
        f"  {r['case']}: {'decided' if r['decided'] else 'NOT decided'} in {r['wall_s']:.0f} s: {r['answer']}"
        + (f"; interval {r['interval']}" if r.get("interval") else "")
        + (f"; truth's bar {r['truth_bar']:.3g}" if r.get("truth_bar") is not None else "")
        for r in out["rows"]
    ]
    return "\n".join(lines)
