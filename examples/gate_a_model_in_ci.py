"""Gate a model in CI: fail the build when what a model gives up on your scene grows past what you decided.

    .venv/bin/python examples/gate_a_model_in_ci.py [--scene cantilever-pull] [--model linear-tm]
                                                    [--metric rel_l2] [--bound 0.02] [--out gates.toml]

The script

1. writes a gates file with one gate: a scene, a model, a metric and its bound. The bound is a
   decision, written by hand and never by a tool;
2. measures the gate once and records the measurement as its baseline, with where it came from (the
   commit, the mesh's and the scene's hashes, the reference's solver options, the date): what
   ``tissuebench gate --update-baselines`` does;
3. runs the gates as CI does (``tissuebench gate --config gates.toml``, exit 1 on a miss). A gate
   fails when the value exceeds its bound, when the truth's own bar lets the true value reach over the
   bound (a pass the truth cannot confirm is no pass), when the value moved from its baseline by more
   than its drift (10%: a change nobody decided on, better or worse), or when the baseline no longer
   describes the scene;
4. shows a failure: the same gate with its bound just below the measured value, and the line that says
   why. Exit status: 0 when step 3 passed and step 4 failed, as they should.

In your CI, keep the gates file in your repository and run step 3 alone.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from meshes.io import atomic_write_text
from realtime.models import SPECS, linear_tm
from verification.metrics import METRICS
from verification.scene import SceneError
from verification.studies.gates import format_gates, load_gates, run_gates, update_baselines

# %% 1. The gate, as a decision
#
# ``fraction`` is the time step as a fraction of the model's critical one (0.9: what a simulator would
# run at). ``note`` says why the bound is what it is, for whoever meets the failure.


def gate_text(scene: str, model: str, metric: str, bound: float) -> str:
    return f"""[[gate]]
scene = "{scene}"
model = "{model}"
fraction = 0.9
metric = "{metric}"
bound = {bound!r}
note = "what {model} may give up on {scene}: decided by hand"
"""


# %% 2. The baseline, as a measurement
#
# ``run_gates(..., baselines=False)`` checks the bounds only; ``update_baselines`` rewrites the file
# with each gate's value and provenance. The ground truth and the run are cached: the next runs read them.


def measure_baseline(path: Path) -> None:
    rows = run_gates(path, baselines=False)
    update_baselines(path, rows)
    print(f"baseline recorded in {path}: {rows[0]['value']:.4g} ({rows[0]['metric']})")


# %% 3. and 4. The gates as CI runs them, and one that fails


def check(path: Path) -> bool:
    rows = run_gates(path)
    print(format_gates(rows))
    return all(r["passed"] for r in rows)


def tightened(path: Path) -> Path:
    """A copy of the gates file with the first gate's bound 1% below its baseline."""
    gate = load_gates(path)[0]
    bound = 0.99 * gate["baseline"]["value"]
    text = path.read_text().replace(f"bound = {gate['bound']!r}", f"bound = {bound!r}", 1)
    return atomic_write_text(path.with_name(path.stem + "-tightened.toml"), text)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scene", default="cantilever-pull", help="a built-in scene's name or a scene file")
    ap.add_argument("--model", default=linear_tm.NAME, choices=list(SPECS))
    ap.add_argument("--metric", default="rel_l2", choices=list(METRICS))
    ap.add_argument("--bound", type=float, default=0.02)
    ap.add_argument("--out", type=Path, default=Path("gates.toml"))
    args = ap.parse_args(argv)
    try:
        path = atomic_write_text(args.out, gate_text(args.scene, args.model, args.metric, args.bound))
        measure_baseline(path)
        print("as CI runs it:")
        passed = check(path)
        print("with the bound 1% below the baseline:")
        failed = not check(tightened(path))
    except (SceneError, OSError) as exc:
        print(f"gate_a_model_in_ci: {exc}", file=sys.stderr)
        return 2
    return 0 if passed and failed else 1


if __name__ == "__main__":
    sys.exit(main())
