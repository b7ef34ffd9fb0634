"""A user's own liver through every command: the four scenes a newcomer writes from SOFA's liver2.msh
(verification/scenes/organs: in the file's own units, cut, with a stiff inclusion, pressed by a tool of
three vertices). Each command either answers or says in one line what to change; none ends in a
traceback. The cut is the one that broke commands (converge, report, judge, export), so most of the
checks below are on it."""

import json
from pathlib import Path

import numpy as np
import pytest

from verification.cli import main
from verification.events import states
from verification.runs.compare import compare
from verification.runs.simulate import run_model
from verification.scene_file import load_scene

ORGANS = Path(__file__).resolve().parents[2] / "verification" / "scenes" / "organs"
SCENES = sorted(str(p) for p in ORGANS.glob("*.toml"))
CUT = str(ORGANS / "liver-cut.toml")


def test_the_four_scenes_are_there_and_check_describes_each(capsys):
    """check answers on each: the units hint on the one in the file's units, a small tool's warning on the
    three-vertex tool, the two materials of the inclusion and the states of the cut."""
    assert [Path(s).stem for s in SCENES] == ["liver-3-vertex-tool", "liver-cut", "liver-inclusion", "liver-units"]
    said = {}
    for s in SCENES:
        assert main(["check", s]) == 0
        said[Path(s).stem] = capsys.readouterr().out
    assert "if the file is in centimetres" in said["liver-units"] and "decimetres (scale = 0.1" in said["liver-units"]
    assert "holds 3 vertices: a tool this small" in said["liver-3-vertex-tool"]
    assert "material[1]" in said["liver-inclusion"]
    assert "state t = 1 s: cut at t = 1 s" in said["liver-cut"]


def test_a_cut_scene_is_judged_whole_or_state_by_state(tmp_path, capsys):
    """The whole result (one field per state on the union of their vertices, as run --out writes it)
    scores what compare scores for the same run, to round-off; one state's result on that state's own
    mesh scores what compare scores on that state's scene, exactly (the same reference, the same
    metrics); anything else is one line naming both ways, exit 2."""
    assert main(["run", CUT, "--model", "linear-tm", "--out", str(tmp_path / "whole.npz")]) == 0
    capsys.readouterr()
    assert main(["judge", CUT, str(tmp_path / "whole.npz"), "--json"]) == 0
    whole = json.loads(capsys.readouterr().out)
    row = compare(load_scene(CUT), "linear-tm")
    assert whole["rel_l2"] == pytest.approx(row.rel_l2, rel=1e-12)  # same arrays, summed in another order
    assert [s["label"] for s in whole["states"]] == [s["label"] for s in row.states]

    cut = states(load_scene(CUT))[1].scene
    run_model(cut, "linear-tm").save(tmp_path / "state1.npz")
    assert main(["judge", CUT, str(tmp_path / "state1.npz"), "--state", "1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["rel_l2"] == compare(cut, "linear-tm").rel_l2

    assert main(["judge", CUT, str(tmp_path / "state1.npz")]) == 2  # one field at one state's vertices
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "has 2 states" in err and "--state K" in err and "514 vertices" in err
    assert main(["judge", CUT, str(tmp_path / "state1.npz"), "--state", "2"]) == 2
    assert "the scene's states are 0: as meshed (t = 0 s); 1: cut" in capsys.readouterr().err


def test_a_cut_scene_exports_each_state(tmp_path, capsys):
    """The export of a cut scene holds every state's body: the body as meshed at the top, the cut one in
    state-1/ with the lips' vertices doubled, each scene.json naming the states and its own."""
    assert main(["export", CUT, str(tmp_path / "x")]) == 0
    top = json.loads((tmp_path / "x" / "scene.json").read_text())
    sub = json.loads((tmp_path / "x" / "state-1" / "scene.json").read_text())
    every = states(load_scene(CUT))
    assert [s["directory"] for s in top["states"]] == [".", "state-1"] and top["state"]["state"] == 0
    assert sub["state"]["state"] == 1 and sub["mesh"]["n_vertices"] == every[1].scene.mesh.n_vertices
    with np.load(tmp_path / "x" / "state-1" / "arrays.npz") as z:
        assert np.array_equal(z["points"], every[1].scene.mesh.points)
        assert np.array_equal(z["tets"], every[1].scene.mesh.tets)


def test_converge_studies_a_cut_scene_in_the_state_its_events_leave(capsys):
    """converge refined the meshed body and compared it with the cut state's run (a traceback: 514
    against 507 vertices); it now studies the state the events leave, and says which."""
    assert main(["converge", CUT, "--models", "linear-tm", "--levels", "2", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["state"].startswith("cut at t = 1 s")
    errors = {s["label"]: s["error"] for s in out["series"]}
    assert len(errors["linear-tm"]) == 2 and errors["linear-tm"][1] < errors["linear-tm"][0]


def test_the_report_draws_a_cut_scene_on_its_cut_mesh(tmp_path):
    """The report's deformed shapes of a cut scene: its runs live on the union of the states' vertices
    (514), not the meshed body's (507): the picture broke the report after its sweep."""
    from verification.report.sections import _pictures
    from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
    from verification.studies.sweep import sweep

    scene = load_scene(CUT)
    rows = sweep(scene, models=["linear-tm"], fractions=[0.9])["rows"]
    pictures, _ = _pictures(scene, reference_result(scene, **REFERENCE_DEFAULTS), rows)
    assert len(pictures) == 1 and len(pictures[0]) > 1000  # a PNG's base64, drawn
    assert len(run_model(scene, "linear-tm").points) == 514  # what it is drawn on: the union, cut open


def test_check_draws_the_scene_with_its_regions_where_the_scene_puts_them(tmp_path, capsys):
    """check --picture: a PNG of the body from three sides in which the held patch and the tool are
    drawn in their colours (found among its pixels), at the vertices their regions hold (the picture's
    regions are the scene's, counted as check counts them), the tool's arrow along its motion; the
    cut's opened faces on the cut scene. A file that is not .png is one line, exit 2."""
    import matplotlib.colors
    import matplotlib.image

    from verification.report.scene_picture import HELD_COLOURS, LOAD_COLOURS, _regions

    assert main(["check", "sofa-liver", "--picture", str(tmp_path / "liver.png")]) == 0
    assert "picture: " in capsys.readouterr().out
    pixels = matplotlib.image.imread(tmp_path / "liver.png")[:, :, :3].reshape(-1, 3)
    for colour in (HELD_COLOURS[0], LOAD_COLOURS[0]):
        rgb = np.array(matplotlib.colors.to_rgb(colour))
        assert (np.abs(pixels - rgb).max(axis=1) < 0.02).sum() > 50, colour  # markers of that colour drawn
    scene = load_scene("sofa-liver")
    held, tool = _regions(scene)
    assert np.array_equal(held["vertices"], scene.problem.fixed[0].region.vertices(scene.mesh))
    assert np.linalg.norm(scene.mesh.points[held["vertices"]] - [-0.029, 0.053, -0.013], axis=1).max() <= 0.025
    assert np.allclose(tool["direction"], [0.0, 0.0, -0.01]) and tool["label"].startswith("load[0]: tool")
    cut = _regions(load_scene(CUT))[-1]
    assert cut["label"].startswith("cut at t = 1 s") and len(cut["faces"]) > 0

    assert main(["check", "sofa-liver", "--picture", str(tmp_path / "liver.jpg")]) == 2
    assert capsys.readouterr().err.strip() == f"tissuebench: --picture {tmp_path / 'liver.jpg'}: give a .png file"


def test_the_reports_question_drops_its_haptic_part_where_no_tool_gives_a_force():
    """report --haptic-rate on a page with a cut liver hung under gravity: that section's advisor asks
    the rate alone (advise refuses a haptic question without a tool); a pressed liver keeps it."""
    from verification.report.sections import Question

    q = Question(0.6, 60.0, 500.0)
    assert str(q) == "rel_l2 &le; 0.6 at 60 Hz, tool force within 0.6 at 500 Hz"
    assert q.of(load_scene(CUT)) == Question(0.6, 60.0, None)
    assert q.of(load_scene(str(ORGANS / "liver-inclusion.toml"))) == q
    assert Question.answered({"tol": 0.6, "rate": 60.0, "haptic": {"rate": 500.0}}) == q
