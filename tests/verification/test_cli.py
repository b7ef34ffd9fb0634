"""The command line: compare --json, run --out, reference --out, report."""

import json

import numpy as np
import pytest

from verification.cli import main
from verification.runs.results import Result
from verification.scene import SCENES_DIR

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
    # the cantilever's error is the mesh's: P1 locks in bending (the P1 solution itself is 28% off), and the
    # linear model adds a few percent; the parts are distances over the reference's norm, so the triangle
    # inequality bounds the total both ways (1e-12: the round-off of three norms)
    b = out["error_budget"]
    assert b["dominant"] == "mesh" and b["mesh"] > 0.2 and b["model"] < 0.1 and b["time"] is None
    assert abs(b["mesh"] - b["model"]) - 1e-12 <= out["rel_l2"] <= b["mesh"] + b["model"] + 1e-12


def test_compare_flags_errors_cancelling_and_only_then(capsys):
    """mass-spring on the cantilever is 0.084 from the truth where P1 on the same mesh is 0.284: its own
    part (0.20) offsets P1's locking, right for a wrong reason, and a newcomer read it as the best model.
    compare says so, as the engines study does; linear-tm (model part 0.02, total above the mesh's part)
    gets no such line."""
    from verification.runs.compare import cancelling

    assert cancelling(0.084, 0.284, 0.201) and not cancelling(0.29, 0.284, 0.02) and not cancelling(0.1, 0.284, 0.1)
    assert not cancelling(0.084, None, 0.201) and not cancelling(None, 0.284, 0.201)  # unknown: never a flag
    assert main(["compare", "cantilever", "--model", "mass-spring"]) == 0
    assert "errors cancelling: rel_l2" in capsys.readouterr().out
    assert main(["compare", "cantilever", "--model", "linear-tm"]) == 0
    assert "errors cancelling" not in capsys.readouterr().out


def test_error_budget_of_a_dynamic_run_has_a_time_part(capsys):
    """cantilever-dynamic at 0.9 dt_crit: the time part is the model against itself at dt / 8; the model
    part is then measured at dt / 8, so nothing is counted twice."""
    assert main(["compare", "cantilever-dynamic", "--model", "linear-tm", "--degree", "1", "--json"]) == 0
    b = json.loads(capsys.readouterr().out)["error_budget"]
    # the P1 reference returns its refined solution, so the mesh part is exactly its spatial difference
    from verification.runs.reference import reference_result
    from verification.scene_file import load_scene

    ref = reference_result(load_scene("cantilever-dynamic"), degree=1, refine=0, estimate=True)
    assert b["mesh"] == pytest.approx(ref.meta["ref_err_space"], rel=1e-12)
    assert b["time"] > 0 and b["model"] > 0


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


def test_a_result_file_is_written_under_the_name_given_or_refused_in_one_line(tmp_path, capsys):
    """run --out NAME writes NAME itself whatever its suffix (numpy's savez wrote NAME.npz's temporary
    twin and renamed the empty temporary file to NAME, leaving the data behind in a hidden file), and a
    name that cannot be a file (a directory, a path through a file) is one line with exit 2, leaving
    nothing behind."""
    run = ["run", "cantilever-pull", "--model", "linear-tm", "--out"]
    assert main([*run, str(tmp_path / "result.txt")]) == 0
    capsys.readouterr()
    assert Result.load(tmp_path / "result.txt").meta["model"] == "linear-tm"
    (tmp_path / "adir").mkdir()
    (tmp_path / "a-file").write_text("x")
    for target, why in (("adir", "is a directory"), ("a-file/run.npz", f"{tmp_path / 'a-file'} is a file")):
        assert main([*run, str(tmp_path / target)]) == 2
        err = capsys.readouterr().err
        assert err.startswith(f"tissuebench: {tmp_path / target}: ") and why in err and err.count("\n") == 1, err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a-file", "adir", "result.txt"]


def test_scenes_lists_builtins(capsys):
    assert main(["scenes", "--json"]) == 0
    names = {s["name"] for s in json.loads(capsys.readouterr().out)["scenes"]}
    assert {"cantilever", "cantilever-pull"} <= names


@pytest.mark.slow
def test_report_has_plots_and_data(tmp_path, monkeypatch):
    from tests.verification.test_engine_seam import DirectP1
    from verification import engines
    from verification.report.page import write_report

    # a plug-in engine beside the built-in models: on the same plot and in the same tables
    monkeypatch.setattr(engines, "ENGINES", {**engines.ENGINES, "direct-p1": DirectP1()})
    from verification.report.sections import Question

    # the user's own question (the report's was fixed at 5% and 1 kHz): 10% at 60 Hz, a 500 Hz haptic loop
    question = Question(0.1, 60.0, 500.0)
    path = write_report(
        ["cantilever-pull"], out=tmp_path / "r", fractions=(0.9, 1.1), question=question
    )  # 0.9: the advisor's too
    text = path.read_text()
    data = json.loads((tmp_path / "r" / "data.json").read_text())
    advice = data["scenes"][0]["advice"]
    assert data["question"] == {"tol": 0.1, "rate_hz": 60.0, "haptic_rate_hz": 500.0}
    assert (advice["tol"], advice["rate"], advice["haptic"]["rate"]) == (0.1, 60.0, 500.0)
    assert "rel_l2 &le; 0.1 at 60 Hz, tool force within 0.1 at 500 Hz" in text and "1000 Hz" not in text
    assert text.count("data:image/png;base64,") >= 2  # the error/speed plot and a deformation picture
    assert "diverged at step" in text  # 1.1 x the critical step blows up, and the page says so
    assert {r["status"] for r in data["scenes"][0]["sweep"]["rows"]} == {"ok", "diverged"}
    assert data["scenes"][0]["advice"]["why"]
    assert "<th>Pareto</th>" in text and "<h3>Advisor</h3>" in text
    assert "<h3>Error budget</h3>" in text and "whose error is it?" not in text  # the title is inside the plot
    budget = data["scenes"][0]["budget"]
    assert budget["rows"] and budget["verdict"].startswith("The P1 finite-element solution on this mesh is")
    assert (tmp_path / "r" / "runs.csv").read_text().startswith("scene,model")
    plug = [r for r in data["scenes"][0]["sweep"]["rows"] if r["model"] == "direct-p1"]
    assert len(plug) == 1 and plug[0]["status"] == "ok" and "<td>direct-p1</td>" in text
    assert any(c["model"] == "direct-p1" for c in data["scenes"][0]["advice"]["candidates"])
    # the first screen answers: the pick's table comes before any section, names the advisor's pick with its
    # error and the interval the reference's bar allows; the runs that blew up on purpose are folded
    first = text.index("<table class='first'>")
    assert first < text.index("<section")
    pick = data["scenes"][0]["advice"]
    opening = text[first : text.index("</table>", first)]
    assert f"<b>{pick['model']}</b>" in opening and f"{pick['value']:.3g} (" in opening
    assert text.index("<details><summary>") < text.index("diverged at step")


def _read_pvd(pvd):
    """(times, [meshio.Mesh per time]) of a ParaView collection, read as ParaView does: the XML, then each
    listed .vtu."""
    import xml.etree.ElementTree as ET

    import meshio

    root = ET.parse(pvd).getroot()
    assert root.get("type") == "Collection"
    sets = root.find("Collection").findall("DataSet")
    return [float(d.get("timestep")) for d in sets], [meshio.read(pvd.parent / d.get("file")) for d in sets]


def test_compare_vtk_writes_a_paraview_time_series(tmp_path, capsys):
    """A dynamic scene: one .vtu per output time with both displacements and the error, listed with their
    times in one .pvd; every value matches the run's own result files."""
    from verification.scene_file import load_scene

    scene = load_scene("cantilever-dynamic")
    args = ["--degree", "1", "--json", "--vtk", str(tmp_path / "vtk")]
    assert main(["compare", "cantilever-dynamic", "--model", "linear-tm", *args]) == 0
    out = json.loads(capsys.readouterr().out)
    times, grids = _read_pvd(tmp_path / "vtk" / "cantilever-dynamic-linear-tm.pvd")
    n_out = round(scene.time.end / scene.time.output_every) + 1
    assert times == pytest.approx(np.arange(n_out) * scene.time.output_every, rel=1e-12, abs=1e-15)
    mesh = scene.mesh
    for g in grids:
        assert set(g.point_data) == {"reference_displacement", "model_displacement", "error", "error_magnitude"}
        assert g.points.shape == (mesh.n_vertices, 3) and g.cells_dict["tetra"].shape == (mesh.n_tets, 4)
        assert g.point_data["error"].shape == (mesh.n_vertices, 3)
        assert g.point_data["error_magnitude"].shape == (mesh.n_vertices,)
        assert np.allclose(
            g.point_data["error"], g.point_data["model_displacement"] - g.point_data["reference_displacement"]
        )
    # the largest pointwise error of the series is the metric compare printed
    assert max(g.point_data["error_magnitude"].max() for g in grids) == pytest.approx(out["max_err"], rel=1e-12)
    assert not list((tmp_path / "vtk").glob(".tmp*"))


def test_run_and_reference_vtk_to_a_pvd_path(tmp_path, capsys):
    assert main(["run", "cantilever-pull", "--model", "linear-tm", "--vtk", str(tmp_path / "run.pvd")]) == 0
    times, grids = _read_pvd(tmp_path / "run.pvd")
    assert times == [0.0] and list(grids[0].point_data) == ["displacement"]
    assert main(["reference", "cantilever-pull", "--degree", "1", "--no-estimate", "--vtk", str(tmp_path / "ref")]) == 0
    times, grids = _read_pvd(tmp_path / "ref" / "cantilever-pull-reference.pvd")
    assert grids[0].point_data["displacement"].shape == (len(grids[0].points), 3)


@pytest.mark.slow
def test_compare_on_a_real_sofa_liver(capsys):
    """SOFA's liver2.msh (gmsh format 1) held at its back, a tool pressing its lobe: every metric."""
    assert main(["compare", "sofa-liver", "--model", "linear-tm", "--degree", "1", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["status"] == "ok" and out["n_vertices"] == 507 and out["n_tets"] == 1493
    for k in METRICS:
        assert out[k] is not None and np.isfinite(out[k]), k
    assert 0 < out["rel_l2"] < 1 and out["reaction_rel_err"] > 0


def test_petsc_options_are_merged_and_a_malformed_one_is_one_line(capsys):
    from verification.cli.parser import build_parser

    args = build_parser().parse_args(
        [
            "reference",
            "cantilever",
            "--petsc-option",
            "pc_type=lu",
            "--petsc-option=-pc_factor_mat_solver_type=mumps",  # PETSc's own spelling, dash and all
        ]
    )
    assert args.petsc_option == {"pc_type": "lu", "pc_factor_mat_solver_type": "mumps"}
    with pytest.raises(SystemExit) as exc:
        main(["reference", "cantilever", "--petsc-option", "pc_type"])
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "'pc_type' is not KEY=VALUE" in err[0]


def test_a_damaged_cache_entry_is_computed_again(tmp_path, capsys, monkeypatch):
    """A cache file cut short (a full disk, an interrupted copy) or not what it should be was a
    BadZipFile or JSON traceback: each kind of entry (the reference, a settled state, a compared run)
    is computed again, with a line on stderr, and the answer is the one computed the first time."""
    from verification.cache import cache_dir
    from verification.runs.reference import reference_result
    from verification.runs.store import cached_compare
    from verification.scene_file import load_scene

    monkeypatch.setenv("TISSUEBENCH_CACHE", str(tmp_path))
    scene = load_scene("cantilever-pull")
    opts = {"degree": 1, "estimate": False}
    first = cached_compare(scene, "linear-tm", ref_opts=opts)
    assert first.cached is False
    entries = sorted(p for p in cache_dir().rglob("*") if p.is_file())
    kinds = {p.parent.name for p in entries}
    assert {"reference", "settled", "runs"} <= kinds, entries
    for path in entries:
        data = path.read_bytes()
        path.write_bytes(data[: len(data) // 3] if path.suffix == ".npz" else b"[1, 2")
    ref = reference_result(scene, **opts)
    again = cached_compare(scene, "linear-tm", ref_opts=opts)
    err = capsys.readouterr().err
    for kind in ("reference", "settled", "runs"):
        assert f"/{kind}/" in err and "damaged" in err, err
    assert again.cached is False and again.rel_l2 == first.rel_l2
    assert ref.meta["degree"] == 1
    assert cached_compare(scene, "linear-tm", ref_opts=opts).cached is True


@pytest.mark.slow
def test_a_model_run_without_a_term_of_the_material_says_so(tmp_path, capsys):
    """block-press with the volume penalty: linear-tm runs without it (its error measures what that
    costs) and its row, its text and the sweep's table say so; stvk-tm represents it and says nothing."""
    from verification.runs.row import Row
    from verification.studies.sweep import format_sweep

    text = (SCENES_DIR / "block-press.toml").read_text().replace("poisson = ", "volume_penalty = 5.0e5\npoisson = ", 1)
    path = tmp_path / "penalty.toml"
    path.write_text(text)
    rows = {}
    for model in ("linear-tm", "stvk-tm"):
        assert main(["compare", str(path), "--model", model, "--json"]) == 0
        rows[model] = json.loads(capsys.readouterr().out)
    assert rows["linear-tm"]["unrepresented"] == ["the volume penalty (volume_penalty = 500000 Pa)"]
    assert rows["stvk-tm"]["unrepresented"] == []
    assert main(["compare", str(path), "--model", "linear-tm"]) == 0
    assert "not represented    the volume penalty (volume_penalty = 500000 Pa)" in capsys.readouterr().out
    # the rows as a sweep holds them: its JSON is a Row's, read back whole
    typed = [Row.from_json(r) for r in rows.values()]
    result = {"scene": "penalty", "reference": rows["stvk-tm"]["reference"], "rows": typed}
    result.update(pareto=[], computed=2, cached=0)
    table = format_sweep(result)
    assert table.count("(without the volume penalty") == 1


def test_the_reports_sweep_table_says_what_became_of_a_run_that_did_not_settle():
    """A sweep's run that does not settle is a row "not settled" with its reason (studies.sweep); the
    report's table of runs that did not finish printed every such row as "diverged at step None"."""
    from verification.report.sections import _diverged_html
    from verification.runs.row import Row

    rows = [
        Row("s", "stvk-tm", "symplectic-euler", "diverged", dt=2e-4, dt_crit=1e-4, step=17),
        Row("s", "hybrid-tm", "symplectic-euler", "not settled", message="reached 5.9e-03 in 50000 steps"),
    ]
    page = _diverged_html(rows)
    assert "diverged at step 17" in page and "1 runs beyond their stable step" in page
    assert "not settled: reached 5.9e-03 in 50000 steps" in page and "1 runs that did not settle" in page
    assert "step None" not in page


def test_the_sweeps_text_table_says_what_became_of_a_run_that_did_not_finish():
    """tissuebench sweep printed every row that was not "ok" as diverged, and a model that cannot represent
    the scene (precomputed beside a rigid tool: no step, dt None) crashed the table; each now says its
    status and reason."""
    from verification.runs.row import Row
    from verification.studies.sweep import format_sweep

    rows = [
        Row("s", "stvk-tm", "symplectic-euler", "diverged", dt=2e-4, dt_crit=1e-4, step=17),
        Row("s", "precomputed", "quasi-static", "not applicable", message="precomputed: the loading has 1 rigid tool"),
    ]
    table = format_sweep({"scene": "s", "reference": {}, "rows": rows, "pareto": [], "computed": 2, "cached": 0})
    assert "diverged at step 17" in table
    assert "not applicable: precomputed: the loading has 1 rigid tool" in table
