"""The command line: compare --json, run --out, reference --out, report."""

import json

import numpy as np
import pytest

from verification.cli import main
from verification.results import Result

METRICS = [
    "rel_l2",
    "surface_rel_l2",
    "max_err",
    "reaction_rel_err",
    "volume_err",
    "step_us",
    "realtime_factor",
    "rate_hz",
    "ref_err_estimate",
]


@pytest.mark.slow
def test_compare_json_prints_the_metrics(capsys):
    assert main(["compare", "cantilever", "--model", "linear-tm", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)  # stdout is one JSON object and nothing else
    for k in METRICS:
        assert k in out
    assert 0 < out["rel_l2"] < 1 and out["step_us"] > 0
    assert out["ref_err_estimate"] > 0  # P2 at refinements 0 and 1 differ


def test_run_and_reference_write_result_files(tmp_path, capsys):
    assert main(["run", "cantilever-pull", "--model", "linear-tm", "--out", str(tmp_path / "run.npz")]) == 0
    run = Result.load(tmp_path / "run.npz")
    assert run.displacement.shape == (1, len(run.points), 3) and run.meta["model"] == "linear-tm"
    assert np.linalg.norm(run.reaction) > 0
    assert (
        main(["reference", "cantilever-pull", "--degree", "1", "--no-estimate", "--out", str(tmp_path / "ref.npz")])
        == 0
    )
    ref = Result.load(tmp_path / "ref.npz")
    assert ref.points.shape == run.points.shape and ref.meta["degree"] == 1
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


def test_scenes_lists_builtins(capsys):
    assert main(["scenes", "--json"]) == 0
    names = {s["name"] for s in json.loads(capsys.readouterr().out)["scenes"]}
    assert {"cantilever", "cantilever-pull"} <= names


@pytest.mark.slow
def test_report_has_plots_and_data(tmp_path):
    from verification.report import write_report

    path = write_report(["cantilever-pull"], out=tmp_path / "r", fractions=(0.5, 1.1))
    text = path.read_text()
    assert text.count("data:image/png;base64,") >= 2  # the error/speed plot and a deformation picture
    assert "diverged at step" in text  # 1.1 x the critical step blows up, and the page says so
    data = json.loads((tmp_path / "r" / "data.json").read_text())
    assert {r["status"] for r in data["scenes"][0]["sweep"]["rows"]} == {"ok", "diverged"}
    assert data["scenes"][0]["advice"]["why"]
    assert "<th>Pareto</th>" in text and "<h3>Advisor</h3>" in text
    assert (tmp_path / "r" / "runs.csv").read_text().startswith("scene,model")
