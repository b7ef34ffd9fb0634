"""The advisor that keeps time and names the mesh, and the refined scenes it names.

The decisive tests re-run the advisor's pick as a user would, with the ``compare`` command it prints,
and check that the pick meets the tolerance and holds the rate: the advice is judged by a run made
after it, not by the numbers it was made from.
"""

import json
import shlex
import tomllib

import numpy as np
import pytest

from realtime import MODELS
from verification.cli import main
from verification.runs.reference import reference_result
from verification.runs.row import Row
from verification.scene import SceneError
from verification.scene_file import load_scene, parse
from verification.studies.frame import FRAME_SHARE, frame_budget, merge_same_answers

from .test_input_errors import builtin, write_scene


def _row(model="linear-tm", dt=1e-5, step_us=10.0, settle=1000, err=0.1, integrator="symplectic-euler"):
    return Row("a scene", model, integrator, "ok", dt=dt, step_us=step_us, settle_steps=settle, rel_l2=err)


# ---------------------------------------------------------------------------------------------
# frame budget: closed-form cases


def test_frame_budget_of_a_dynamic_run_is_its_real_time_factor():
    # dt = 1e-4 s: a 1 ms frame advances 10 steps; at 90 us per step that is 900 us, it holds at 100% of
    # the frame and not at 80%; at 110 us per step (real-time factor 0.91) it does not hold at all
    assert frame_budget(_row(dt=1e-4, step_us=90.0), 1000.0, dynamic=True, share=1.0)["holds"]
    b = frame_budget(_row(dt=1e-4, step_us=90.0), 1000.0, dynamic=True, share=0.8)
    assert not b["holds"] and b["steps_per_frame"] == 10 and b["work_us"] == pytest.approx(900.0)
    assert not frame_budget(_row(dt=1e-4, step_us=110.0), 1000.0, dynamic=True, share=1.0)["holds"]
    # every command takes the same share of a frame: compare --rate decides as advise does
    assert frame_budget(_row(dt=1e-4, step_us=90.0), 1000.0, dynamic=True)["share"] == FRAME_SHARE
    # the case: 50 kHz step rate (20 us) at dt = 1e-5 s runs at half real time
    half = frame_budget(_row(dt=1e-5, step_us=20.0), 1000.0, dynamic=True)
    assert not half["holds"] and half["steps_per_frame"] == 100 and "real-time factor 0.50" in half["why"]
    # a step longer than the frame: the state changes less often than the display, however cheap it is
    slow = frame_budget(_row(dt=2e-3, step_us=1.0), 1000.0, dynamic=True)
    assert not slow["holds"] and "longer than a frame" in slow["why"]


def test_frame_budget_of_a_static_run_is_its_time_to_settle():
    # 10 us steps: 80 fit in 80% of a 1 ms frame; 1000 steps to settle take 10 ms of wall time
    b = frame_budget(_row(step_us=10.0, settle=1000), 1000.0, dynamic=False, share=0.8)
    assert b["holds"] and b["steps_per_frame"] == 80
    assert b["time_to_answer_s"] == pytest.approx(1000 * 10e-6)
    assert "13 frames" in b["why"]  # ceil(1000 / 80)
    # a step that does not fit in a frame does not hold the rate, whatever its accuracy
    assert not frame_budget(_row(step_us=900.0), 1000.0, dynamic=False, share=0.8)["holds"]
    # a quasi-static model answers in one update (its settling is that one update)
    q = frame_budget(_row(model="precomputed", dt=None, step_us=50.0, settle=1), 1000.0, dynamic=False)
    assert q["holds"] and q["time_to_answer_s"] == pytest.approx(50e-6)
    # an engine command's answer of 400 iterations with no time step is costed by its iterations
    c = frame_budget(_row(model="its-own", dt=None, step_us=50.0, settle=400), 1000.0, dynamic=False, share=0.8)
    assert c["steps_per_frame"] == 16 and c["time_to_answer_s"] == pytest.approx(400 * 50e-6)


def test_rows_whose_step_changes_nothing_are_one_row_ranked_by_time_to_settle():
    """On a static scene the step changes neither the answer nor (much) the cost of a step: three
    steps of linear-tm are one candidate, the one that settles soonest, not the one with the fastest
    step (the issue's case: the pick among a model's rows was timing noise, and it needed 3.5x the
    steps)."""
    rows = [
        _row(dt=1e-5, step_us=9.0, settle=35000, err=0.2),
        _row(dt=3e-5, step_us=10.0, settle=10000, err=0.2 * (1 + 1e-9)),
        _row(dt=2e-5, step_us=9.5, settle=17000, err=0.2),
        _row(model="stvk-tm", dt=3e-5, step_us=20.0, settle=20000, err=0.1),
    ]
    rows = [r.replace(frame=frame_budget(r, 1000.0, dynamic=False)) for r in rows]
    merged = merge_same_answers(rows, "rel_l2", dynamic=False)
    assert [r.model for r in merged] == ["linear-tm", "stvk-tm"]
    assert merged[0].dt == 3e-5 and merged[0].merged_dt == (1e-5, 2e-5, 3e-5)
    # on a dynamic scene the step changes the answer: rows with different errors stay apart
    dyn = [_row(dt=1e-5, err=0.01), _row(dt=2e-5, err=0.02)]
    dyn = [r.replace(frame=frame_budget(r, 1000.0, dynamic=True)) for r in dyn]
    assert len(merge_same_answers(dyn, "rel_l2", dynamic=True)) == 2


# ---------------------------------------------------------------------------------------------
# refined scenes


def test_a_refined_scene_poses_the_base_problem_on_nested_vertices():
    base = load_scene("block-press")
    fine = load_scene("block-press", refine=1)
    assert fine.level == 1 and fine.base is not None
    n = base.mesh.n_vertices
    assert np.array_equal(fine.mesh.points[:n], base.mesh.points)
    assert fine.mesh.n_tets == 8 * base.mesh.n_tets
    # the clamped face and the pressed face: every refined vertex on them, and none elsewhere
    for region, z in ((fine.problem.fixed[0].region, 0.0), (fine.problem.loads[0].region, 0.04)):
        on = np.flatnonzero(np.isclose(fine.mesh.points[:, 2], z, atol=1e-12))
        assert np.array_equal(np.sort(region.vertices(fine.mesh)), on)
    assert fine.sha256() != base.sha256()


def test_the_reference_of_a_refined_scene_is_the_base_reference_at_its_vertices():
    """The truth does not depend on the mesh a model runs on: at the base vertices (the first N of
    the refined mesh) it is the base scene's reference to round-off (the same solve, evaluated at the
    same points; 1e-12 relative allows MUMPS's pivoting to differ between two factorisations)."""
    base = load_scene("block-press")
    fine = base.refined(1)
    a = reference_result(base, degree=2, refine=0, estimate=False)
    b = reference_result(fine, degree=2, refine=0, estimate=False)
    n = base.mesh.n_vertices
    assert b.displacement.shape[1] == fine.mesh.n_vertices
    assert np.linalg.norm(b.displacement[:, :n] - a.displacement) <= 1e-12 * np.linalg.norm(a.displacement)
    # the budget's P1 solution is on the model's own mesh: closer to the truth than on the base mesh
    p1_base = reference_result(base, degree=1, refine=0, estimate=False)
    p1_fine = reference_result(fine, degree=1, refine=0, estimate=False, own_mesh=True)
    err = [np.linalg.norm(p.displacement[:, :n] - a.displacement) for p in (p1_base, p1_fine)]
    assert err[1] < 0.6 * err[0]  # P1 converges at about order 2 in L2: a quarter, far below 0.6


def test_a_refined_truth_asked_in_another_process_reuses_the_kept_base_solve(monkeypatch):
    """The report solves its references in worker processes and the advice asks, in the main one, for
    a refined scene's truth: the base solve with its estimate, evaluated at the refined vertices. The
    base solve keeps its fields beside its result, so the main process rebuilds it (its spaces, checked
    to number their dofs at the same points) instead of solving again: the same values and estimate as
    the solve itself (1e-12: the same dofs evaluated at the same points), and no Newton iteration."""
    from verification.runs import reference as runner

    base = load_scene("block-press")
    fine = base.refined(1)
    runner._SOLVED.clear()
    direct = reference_result(fine, use_cache=False)  # solved here: the truth to compare with
    for path in (runner.reference_path(base), runner.reference_path(fine)):
        path.unlink(missing_ok=True)
    reference_result(base)  # the base with its estimate, solved: cached with its fields
    assert runner._fields_path(runner.reference_path(base)).exists()
    runner._SOLVED.clear()  # as in another process
    monkeypatch.setattr("reference.driver.solve_static", _no_solve)
    restored = reference_result(fine)
    assert np.linalg.norm(restored.displacement - direct.displacement) <= 1e-12 * np.linalg.norm(direct.displacement)
    assert restored.meta["ref_err_estimate"] == pytest.approx(direct.meta["ref_err_estimate"], rel=1e-12)


def _no_solve(*args, **kwargs):
    raise AssertionError("solved again: the kept fields were not used")


def test_mesh_refine_key_is_checked(tmp_path):
    text = load_scene("block-press").path.read_text()
    for bad in ("-1", "9", "1.5", "true"):
        data = tomllib.loads(text.replace("[mesh]\n", f"[mesh]\nrefine = {bad}\n"))
        with pytest.raises(SceneError, match=r"mesh\.refine: must be a whole number from 0 to 4"):
            parse(tmp_path / "s.toml", data)
    with pytest.raises(SceneError, match="refine = 7"):
        load_scene("block-press", refine=7)


# ---------------------------------------------------------------------------------------------
# the advisor's picks, re-run


def _rerun(out, capsys) -> dict:
    """Run the advisor's ``command`` through the command line and return compare's JSON."""
    argv = shlex.split(out["command"])
    assert argv[0] == "tissuebench"
    capsys.readouterr()
    assert main(argv[1:] + ["--json"]) == 0
    return json.loads(capsys.readouterr().out)


@pytest.mark.slow
def test_advisor_pick_rerun_with_compare_meets_tolerance_and_rate(capsys):
    """block-press at 8%: the pick, re-run, is within the tolerance and holds the rate by the same rule
    (FRAME_SHARE of each frame). The rate, 10 Hz, is one every machine holds with a thousandfold margin
    (a step here takes tens of microseconds of a 100 ms frame): whether a rate is held is the machine's
    speed, measured by make bench; what is tested is that the advice and its re-run agree."""
    assert main(["advise", "block-press", "--tol", "0.08", "--rate", "10", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["model"] is not None and out["refine"] == 0
    again = _rerun(out, capsys)
    # the printed command also runs as printed, in text mode (a quasi-static pick has no dt to print)
    assert main(shlex.split(out["command"])[1:]) == 0
    assert "holds 10 Hz" in capsys.readouterr().out
    assert again["rel_l2"] <= 0.08
    assert again["frame"]["holds"], again["frame"]["why"]


@pytest.mark.slow
def test_advisor_names_a_finer_mesh_when_the_mesh_part_exceeds_the_tolerance(capsys):
    """block-press at 4% among the models that run on the scene's mesh (adaptive-tm refines it itself):
    P1 on its mesh is 5.3% off the truth for every one of them, so none qualifies there; the advisor
    observes the mesh's order on one refinement, names the refined mesh and a model, and the pick, re-run
    on that mesh, meets both (at 10 Hz, which every machine holds with a hundredfold margin on the refined
    mesh: the test is of the mesh, not of the machine's speed). The truth's bar is 0.6%: a candidate
    qualifies at 3.4% at most, which the mesh refined once allows (at 3%, twice: a 70 000-tetrahedron
    run)."""
    others = [m for m in MODELS if m != "adaptive-tm"]
    assert main(["advise", "block-press", "--tol", "0.04", "--rate", "10", "--json", "--models", *others]) == 0
    out = json.loads(capsys.readouterr().out)
    prop = out["proposal"]
    assert prop["mesh_part"][0] > 0.04 and prop["observed_order"] > 1.0
    assert out["model"] is not None and out["refine"] >= 1, out["why"]
    assert out["mesh"]["n_vertices"] > load_scene("block-press").mesh.n_vertices
    assert "--mesh-refine" in out["command"]
    assert all(line.startswith("on the scene's mesh") for line in out["cheaper_failed"])
    again = _rerun(out, capsys)
    assert again["rel_l2"] <= 0.04 and again["frame"]["holds"], again["frame"]["why"]
    assert again["error_budget"]["mesh"] < prop["mesh_part"][0]


def _steps_taking(step_us: float):
    """A stand-in for runs.simulate.time_steps whose steps take ``step_us`` each (the simulation moves on
    as the real one's does): what the advisor decides from a step time, apart from this machine's."""

    def timed(sim, n=100, repeats=9):
        sim.step(1 + n * repeats)
        return {"step_us": step_us, "step_us_min": step_us, "step_us_max": step_us, "timing_steps": n,
                "timing_repeats": repeats}  # fmt: skip

    return timed


@pytest.mark.parametrize("step_us", [1e6, 1e-3])
def test_the_advisor_does_not_run_what_its_rate_rules_out(monkeypatch, capsys, step_us):
    """On a dynamic scene a candidate whose steps, timed ahead, cannot keep up with the clock even in
    OPTIMISM x FRAME_SHARE of a frame is not run: its row says "over budget" with its step and step time
    and has no error (the stiff beam's adaptive-tm would have taken 2.3 million steps for it). Steps of
    a second each rule out every time-stepping candidate at 10 Hz; steps of a nanosecond rule out none,
    and every one is run to its error. Without the run cache: a row another test cached holds a real
    timing, which the stand-in would not have made."""
    from verification.runs import simulate

    monkeypatch.setattr(simulate, "time_steps", _steps_taking(step_us))
    args = ["advise", "cantilever-dynamic", "--tol", "0.05", "--rate", "10", "--json", "--models", "linear-tm"]
    assert main([*args, "--no-cache"]) == 0
    stepping = [c for c in json.loads(capsys.readouterr().out)["candidates"] if c["integrator"] != "quasi-static"]
    assert {c["integrator"] for c in stepping} == {"symplectic-euler", "implicit-euler"}
    for c in stepping:
        assert c["step_us"] == step_us
        if step_us > 1.0:
            assert (
                c["rel_l2"] is None and not c["qualifies"] and "over budget (not run: its steps timed ahead" in c["why"]
            )
        else:
            assert c["rel_l2"] is not None and "over budget" not in c["why"]


@pytest.mark.slow
def test_advice_on_a_dynamic_scene_tries_implicit_steps_and_its_command_holds(capsys):
    """cantilever-dynamic at 5% and 10 Hz: besides the explicit steps, implicit Euler at one, 4 and 16
    steps a frame; the pick (condensed, quasi-static, here) re-run with the printed command, which names
    no integrator for a quasi-static model (it printed "--integrator quasi-static", which compare
    refuses), meets the tolerance and holds the rate (every machine holds 10 Hz with a hundredfold
    margin: what is tested is that the advice and its re-run agree)."""
    assert (
        main(
            [
                "advise",
                "cantilever-dynamic",
                "--tol",
                "0.05",
                "--rate",
                "10",
                "--json",
                "--models",
                "linear-tm",
                "condensed",
            ]
        )
        == 0
    )
    out = json.loads(capsys.readouterr().out)
    implicit = sorted(c["dt"] for c in out["candidates"] if c["integrator"] == "implicit-euler")
    assert implicit == pytest.approx([1 / 160, 1 / 40, 1 / 10], rel=1e-12)
    assert out["model"] is not None
    again = _rerun(out, capsys)
    assert again["rel_l2"] <= 0.05 and again["frame"]["holds"], again["frame"]["why"]


def test_a_candidate_that_does_not_settle_is_a_failed_candidate_not_the_end_of_the_advice(monkeypatch, capsys):
    """hybrid-tm did not settle in 2 million steps on a newcomer's liver scene, and the advice ended
    with that error instead of an answer. A sweep's run that does not settle is a row "not settled"
    with the reason; the advisor lists it among the candidates that failed and answers from the rest.
    The non-settling run is made here by a stand-in for hybrid-tm's (the real one takes a minute)."""
    from realtime import NotConvergedError
    from verification.runs import store

    real = store.cached_compare

    def unsettled_hybrid(scene, model, *args, **kwargs):
        if model == "hybrid-tm":
            raise NotConvergedError("hybrid-tm: damped dynamics reached 5.88e-03 in 2000000 steps")
        return real(scene, model, *args, **kwargs)

    monkeypatch.setattr(store, "cached_compare", unsettled_hybrid)
    args = ["advise", "block-press", "--tol", "0.2", "--rate", "10", "--json", "--models", "linear-tm", "hybrid-tm"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    hybrid = [c for c in out["candidates"] if c["model"] == "hybrid-tm"]
    assert hybrid and all(
        not c["qualifies"] and "not settled" in c["why"] and "2000000 steps" in c["why"] for c in hybrid
    )
    assert out["model"] == "linear-tm"


def test_a_model_that_cannot_represent_the_scene_is_a_candidate_not_applicable_not_the_end_of_the_advice(
    tmp_path, capsys
):
    """A newcomer's 5 mm tool reached a vertex inside their liver, and the advice ended with
    precomputed's restriction (its responses exist for surface vertices only) although every other model
    could run. Here the block's pressed plate reaches its second layer of vertices, inside the block:
    ``compare`` of precomputed alone still stops with the one line, and the advice lists precomputed as
    not applicable and answers from the others."""
    data = builtin("block-press")
    data["load"][0]["box"] = [[-1.0, -1.0, 0.0299], [1.0, 1.0, 1.0]]
    path = write_scene(tmp_path / "deep-press.toml", data)
    assert main(["check", str(path)]) == 0
    said = [line for line in capsys.readouterr().out.splitlines() if line.strip().startswith("load[0]")]
    p = load_scene(str(path)).mesh.points
    inside = np.all((p > 1e-9) & (p < 0.04 - 1e-9), axis=1) & (p[:, 2] > 0.0299)  # held, off the cube's faces
    assert said and f"{int(inside.sum())} inside the body (precomputed" in said[0]
    assert main(["compare", str(path), "--model", "precomputed"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith("tissuebench: precomputed: tool vertex") and "not on the surface" in err[-1]
    args = ["advise", str(path), "--tol", "0.2", "--rate", "10", "--json", "--models", "linear-tm", "precomputed"]
    assert main(args) == 0
    out = json.loads(capsys.readouterr().out)
    pre = [c for c in out["candidates"] if c["model"] == "precomputed"]
    assert pre and all(not c["qualifies"] and "not applicable" in c["why"] for c in pre)
    assert out["model"] == "linear-tm"


def test_advice_with_no_model_names_each_candidates_best_tolerance_and_the_cheapest_change():
    """Where nothing qualifies the advice still gives something to act on: the smallest tolerance each
    candidate holding the rate can be said to meet (the top of its interval; a candidate over the frame,
    or with no interval, has none), and the cheapest refined mesh the proposal predicts to meet the
    tolerance and the rate, leaving out a plan tried there that failed."""
    from verification.studies.advise import format_advice

    def cand(model, integrator, interval, holds=True):
        best = interval[1] if interval and holds else None
        return {"model": model, "integrator": integrator, "interval": interval, "best_tol": best}

    def plan(model, level, err, build):
        return {"model": model, "integrator": "symplectic-euler", "level": level, "predicted_error": err,
                "error_bound": 2 * err, "predicted_frame": "8 steps of 900 us per frame", "holds": True,
                "hopeful": True, "fits_memory": True, "predicted_build_s": build}  # fmt: skip

    out = {
        "model": None, "why": "no model meets rel_l2 <= 0.05 at 60 Hz on this mesh", "rate": 60.0, "metric": "rel_l2",
        "candidates": [
            cand("stvk-tm", "symplectic-euler", (0.17, 0.57)), cand("stvk-tm", "symplectic-euler", (0.15, 0.55)),
            cand("linear-tm", "implicit-euler", (0.2, 0.6)), cand("hybrid-tm", "symplectic-euler", (0.1, 0.3), False),
            cand("ffd", "quasi-static", None),
        ],
        "proposal": {"tried": [{"model": "linear-tm", "integrator": "symplectic-euler", "level": 1, "ok": False}],
                     "predicted": [plan("linear-tm", 1, 0.04, 3.0), plan("stvk-tm", 2, 0.03, 40.0),
                                   plan("stvk-tm", 1, 0.045, 5.0)]},
    }  # fmt: skip
    lines = format_advice(out).splitlines()
    assert lines[1] == (
        "best tolerance at 60 Hz on the scene's mesh: stvk-tm (symplectic-euler) 0.55, linear-tm (implicit-euler) 0.6"
    )
    assert lines[2] == (
        "cheapest change: the mesh refined once for stvk-tm (symplectic-euler): rel_l2 predicted 0.045 (at most "
        "0.09); 8 steps of 900 us per frame, its first answer in about 5 s"
    )
    # with a haptic loop the tool force has its best tolerances too, and the change says what it does not
    # predict: the force, which is what failed (SOFA's liver at 25%: shapes within 0.16, forces 0.86 at best)
    out["haptic"] = {"rate": 1000.0, "force_tol": 0.05}
    out["candidates"][0]["best_force_tol"], out["candidates"][2]["best_force_tol"] = 0.86, 2.27
    lines = format_advice(out).splitlines()
    assert lines[2] == (
        "best tolerance of the tool force at 1000 Hz on the scene's mesh: stvk-tm (symplectic-euler) 0.86, "
        "linear-tm (implicit-euler) 2.27"
    )
    assert lines[3].endswith("; its tool force there is not predicted, only measured once run")


def test_a_pick_on_a_refined_mesh_is_named_as_the_change_with_what_was_predicted_and_measured():
    """SOFA's liver at 5% and 60 Hz: the pick is stvk-tm on the mesh refined twice. The advice names that
    refinement as the change to make, with the proposal's prediction (error and frame, before the run)
    beside the run's measurement; a pick on the scene's own mesh has no change line."""
    from verification.studies.advise import _change_made

    plan = {"model": "stvk-tm", "integrator": "symplectic-euler", "level": 2, "predicted_error": 0.0209,
            "error_bound": 0.0209, "predicted_frame": "13 steps of 978 us per frame", "predicted_build_s": 21.9}  # fmt: skip
    out = {"model": "stvk-tm", "integrator": "symplectic-euler", "refine": 2, "metric": "rel_l2", "value": 0.0201,
           "mesh": {"n_vertices": 19535}, "frame": {"why": "11 steps of 1.17e+03 us per frame"},
           "proposal": {"predicted": [{**plan, "level": 1}, plan]}}  # fmt: skip
    assert _change_made(out) == [
        "change: the scene's mesh refined twice (19535 vertices): predicted rel_l2 0.0209 (at most 0.0209), 13 steps "
        "of 978 us per frame, its first answer in about 21.9 s; measured rel_l2 0.0201, 11 steps of 1.17e+03 us per frame"
    ]
    assert _change_made({**out, "refine": 0}) == []


def test_the_sentence_of_no_model_names_the_part_of_the_question_that_fails():
    """SOFA's liver at 25%, 60 Hz and a 1 kHz haptic loop: the sentence said "no model meets rel_l2 <=
    0.25" beside a list of shapes within 0.16; the question's failing part was the tool force. It names
    the whole question, the most accurate shape and the most accurate tool force."""
    from verification.studies.advise import _why_none

    rows = [_row(err=0.0851, step_us=30.0).replace(reaction_rel_err=1.6), _row(err=0.13).replace(reaction_rel_err=0.57)]
    why = _why_none(rows, "rel_l2", 0.25, 60.0, None, [], {"rate": 1000.0, "force_tol": 0.25})
    assert why.startswith("no model meets rel_l2 <= 0.25 at 60 Hz with its tool force within 0.25 at 1000 Hz")
    assert "with 0.0851, the most accurate tool force " in why and "'s with 0.57" in why
    assert "tool force" not in _why_none(rows, "rel_l2", 0.25, 60.0, None, [])  # no haptic loop: not named


# ---------------------------------------------------------------------------------------------
# a truth sharp enough for the question


def _judged(err, bar, step_us=10.0):
    from verification.studies.frame import judgement

    row = _row(err=err, step_us=step_us).replace(ref_err_estimate=bar)
    row = row.replace(frame=frame_budget(row, 10.0, dynamic=False))
    return judgement(row, "rel_l2", 0.05)


def test_a_verdict_is_decided_only_outside_the_interval_the_references_bar_leaves():
    """SOFA's liver at 5%: a bar of 2.5% leaves the true error of a run measured at 4.3% anywhere in
    [1.8%, 6.8%]: undecided, and never picked; 2% is within 5% whatever the truth's own error, 8% is
    over it. Without a bar nothing bounds the truth's own error: undecided, naming the missing bar."""
    from verification.studies.frame import FAILS, QUALIFIES, UNDECIDED

    state, line = _judged(0.043, 0.025)
    assert state == UNDECIDED and "true 0.018 to 0.068" in line and "undecided" in line
    assert _judged(0.02, 0.025)[0] == QUALIFIES
    assert _judged(0.08, 0.025)[0] == FAILS
    assert _judged(0.043, 0.025, step_us=2e5)[0] == FAILS  # a frame it cannot hold decides alone
    state, line = _judged(0.043, None)
    assert state == UNDECIDED and "the reference's bar on rel_l2 is unknown" in line


def test_the_cost_of_a_sharper_reference_is_predicted_from_the_levels_solved():
    """SOFA's liver's finer P2 level (58 605 dofs in 4.5 s): one more refinement solves it again and 8
    times as many dofs, at dofs^2, a direct factorisation's growth in 3D: 4.5 (1 + 64) s, 292 s, over the
    advisor's budget (a fit to the small levels' dofs^1.28 promised 78 s for a solve that took minutes)."""
    from verification.studies.truth import GROWTH, TIGHTEN_BUDGET_S, reference_cost

    meta = {"solves": [{"n_dofs": 8808, "wall_s": 0.4}, {"n_dofs": 58605, "wall_s": 4.5}]}
    c = reference_cost(meta)
    assert GROWTH == 2.0 and c["n_dofs"] == 8 * 58605
    assert c["seconds"] == pytest.approx(4.5 * 65) and c["seconds"] > TIGHTEN_BUDGET_S
    assert reference_cost({}) is None


@pytest.mark.parametrize("budget", [1e9, 0.0])
def test_a_coarse_dynamic_truth_is_refined_within_the_budget_or_the_advice_says_it_cannot_decide(monkeypatch, budget):
    """A dynamic truth (no P3 check, so nothing to adapt by) whose bar (2.5%) is over SHARP of the
    tolerance (5%) is solved refined once more when that is predicted within the truth's budget
    (``advise --truth-budget``), and the advice judges with it; past the budget the advice keeps it and
    says what a sharper one would take, and which option allows it.
    The references are stand-ins (what is tested is the rule, not the solver): each refinement divides
    the bar by 8."""
    from types import SimpleNamespace

    from verification.studies import truth

    asked = []

    def fake(scene, degree=2, refine=0, estimate=True, **kw):
        asked.append(refine)
        solves = [{"n_dofs": 1000 * 8**k, "wall_s": 8.0**k} for k in (refine, refine + 1)]
        return SimpleNamespace(meta={"ref_err_estimate": 0.025 / 8**refine, "solves": solves})

    monkeypatch.setattr(truth, "reference_result", fake)
    opts, said = truth.sharp_reference(load_scene("cantilever-dynamic"), 0.05, "rel_l2", budget_s=budget)
    if budget:
        assert opts["refine"] == 1 and asked == [0, 1] and said["sharp"]
        assert said["bar"] == pytest.approx(0.025 / 8) and "refined once more" in said["why"]
    else:
        assert opts["refine"] == 0 and asked == [0] and not said["sharp"]
        assert "predicted to take" in said["why"] and "(--truth-budget)" in said["why"] and "undecided" in said["why"]


@pytest.mark.parametrize("p3_bar", [0.004, 0.03, None])
def test_a_dynamic_truth_is_read_by_p3_before_it_is_refined(monkeypatch, p3_bar):
    """A dynamic truth whose default bar (2.5%) blocks a 5% question is first read again by P3 and
    dt / 2 on the mesh it returns (the same trajectory; the default bar was 4.4 to 5.7 times the error
    on the dynamic beam, the p3 one 2.3 to 2.6), predicted within the budget from the default's solves;
    kept where it lowers the bar (then nothing is refined), dropped where it does not (then the truth
    is refined as before), as where the P3 run finds no answer (None). Stand-in references: the rule is
    tested, not the solver."""
    from types import SimpleNamespace

    from reference.errors import ReferenceSolveError
    from verification.studies import truth

    asked = []

    def fake(scene, degree=2, refine=0, estimate=True, **kw):
        asked.append((refine, estimate))
        if estimate == "p3" and p3_bar is None:
            raise ReferenceSolveError("Newton found no equilibrium without inverted elements")
        solves = [{"n_dofs": 1000 * 8**k, "wall_s": 0.1 * 8**k} for k in (refine, refine + 1, refine)]
        bar = p3_bar if estimate == "p3" else 0.025 / 8**refine
        return SimpleNamespace(meta={"ref_err_estimate": bar, "solves": solves, "estimator": estimate})

    monkeypatch.setattr(truth, "reference_result", fake)
    predicted = truth.p3_cost({"solves": [{"n_dofs": 1000, "wall_s": 0.1}, {"n_dofs": 8000, "wall_s": 0.8}, {}]})
    assert predicted is None  # a solve without its cost: nothing predicted
    predicted = truth.p3_cost(fake(None).meta)
    assert predicted["n_dofs"] == int(truth.P3_DOFS * 8000) and predicted["seconds"] == pytest.approx(
        0.8 * (3 + 3.1**2)
    )
    asked.clear()
    opts, said = truth.sharp_reference(load_scene("cantilever-dynamic"), 0.05, "rel_l2")
    if p3_bar is not None and p3_bar < 0.025:
        assert asked == [(0, True), (0, "p3")] and opts["estimate"] == "p3" and opts["refine"] == 0
        assert said["sharp"] and said["bar"] == p3_bar and "read by P3 and dt / 2" in said["why"]
    else:
        assert asked == [(0, True), (0, "p3"), (1, True)] and opts["estimate"] is True and opts["refine"] == 1


def test_the_truth_is_asked_for_what_the_undecided_candidates_cheaper_than_a_sure_pick_need():
    """With a bar of 0.02 at 5%: a candidate measured 0.06 is undecided (0.04 to 0.08) and needs a bar
    under its distance 0.01 to the tolerance, asked with MARGIN; a dearer undecided one (0.045) matters
    only while no cheaper candidate surely qualifies; none undecided asks for nothing."""
    from verification.studies.advise import needed_bar
    from verification.studies.truth import MARGIN

    def row(err, step_us):
        r = _row(err=err, step_us=step_us, settle=10).replace(ref_err_estimate=0.02)
        return r.replace(frame=frame_budget(r, 60.0, False))

    rows = [row(0.06, 10.0), row(0.045, 50.0)]
    assert needed_bar(rows, "rel_l2", 0.05, False) == pytest.approx(MARGIN * 0.005)
    assert needed_bar([row(0.01, 20.0), *rows], "rel_l2", 0.05, False) == pytest.approx(MARGIN * 0.01)
    assert needed_bar([row(0.01, 1.0), *rows], "rel_l2", 0.05, False) is None
    assert needed_bar([row(0.2, 1.0)], "rel_l2", 0.05, False) is None


@pytest.mark.slow
def test_candidates_the_default_truth_leaves_undecided_are_decided_by_a_truth_adapted_for_them(capsys):
    """The cantilever at 29%: its models sit 0.284 to 0.286 from the default truth, whose bar leaves
    them undecided; the truth is asked for 0.8 of their smallest distance to the tolerance, adapted where
    its error lives until it is there, and the candidates judged again against it: a pick whose whole
    interval is within the tolerance."""
    args = ["advise", "cantilever", "--tol", "0.29", "--rate", "60", "--models", "linear-tm", "stvk-tm"]
    assert main([*args, "--json"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    truth = out["reference"]
    assert "undecided; the truth's bar asked" in captured.err
    assert truth["estimate"] == "adaptive" and truth["sharp"] and "where its error lives" in truth["why"]
    assert out["model"] is not None and max(out["interval"]) <= 0.29 and not out["undecided"]


def test_a_truth_held_at_a_point_is_not_made_sharper_and_the_advice_says_why(tmp_path, monkeypatch):
    """A user's 5 mm tool on SOFA's liver held one vertex: the advisor adapted its truth for 80 s, its bar
    grew (0.45, then 0.62) as a point load's does, and it answered "cannot decide" without the reason.
    A scene pressed at a point has no converging truth (``scene.point_held``): the truth is not refined
    for it, and its line names the load. The block pressed at one corner vertex, asked a bar no default
    truth has."""
    from verification.runs import reference as runs_reference
    from verification.studies.truth import sharp_reference

    data = builtin("block-press")
    data["load"][0] = {**data["load"][0], "sphere": {"center": [0.04, 0.04, 0.04], "radius": 0.001}}
    del data["load"][0]["box"]
    scene = load_scene(str(write_scene(tmp_path / "corner.toml", data)))
    solved = []
    real = runs_reference.reference_result

    def counted(sc, **opts):
        solved.append(opts)
        return real(sc, **opts)

    monkeypatch.setattr("verification.studies.truth.reference_result", counted)
    opts, truth = sharp_reference(scene, 0.05, "rel_l2", target=1e-9)
    assert opts == runs_reference.REFERENCE_DEFAULTS and solved == [runs_reference.REFERENCE_DEFAULTS]
    assert not truth["sharp"] and "not made sharper: load[0]" in truth["why"] and "holds 1 vertex" in truth["why"]


# ---------------------------------------------------------------------------------------------
# haptic verdicts: the shape at the visual rate, the tool force at the haptic one


def _haptic_row(err=0.02, force_err=0.91, step_us=10.0):
    row = _row(err=err, step_us=step_us).replace(
        ref_err_estimate=1e-3, reaction_rel_err=force_err, reference={"ref_reaction_err_estimate": 1e-3}
    )
    return row.replace(frame=frame_budget(row, 60.0, False, haptic={"rate": 1000.0, "force_tol": 0.1}))


def test_a_tool_force_out_of_tolerance_fails_beside_a_passing_shape():
    """A liver whose shape is 2% off and whose tool force is 91% off: the shape alone qualifies at 60 Hz,
    the haptic loop at 1 kHz does not, and the line says so; with the force 5% off it qualifies; with
    steps too slow for the haptic frame (900 us of a 1 ms frame: over 80%) it fails on the frame."""
    from verification.studies.frame import FAILS, QUALIFIES, judgement

    state, line = judgement(_haptic_row(), "rel_l2", 0.05)
    assert state == FAILS and "haptic loop at 1000 Hz: reaction_rel_err 0.91" in line and "> 0.1" in line
    assert judgement(_haptic_row(force_err=0.05), "rel_l2", 0.05)[0] == QUALIFIES
    state, line = judgement(_haptic_row(force_err=0.05, step_us=900.0), "rel_l2", 0.05)
    assert state == FAILS and "over 80% of a 1e+03 us frame" in line


def test_haptic_advice_judges_the_tool_force_and_its_pick_holds_the_haptic_rate(capsys):
    """block-press at 20% and 10 Hz with a 1 kHz haptic loop and the tool force within 20%: every
    candidate's line judges the force at 1 kHz; the pick, re-run with its printed command (whose rate is
    the haptic one), holds it, with its force within the tolerance. A scene without a tool has no force
    for a haptic device: the command says so in one line."""
    args = ["advise", "block-press", "--tol", "0.2", "--rate", "10", "--haptic-rate", "1000", "--force-tol", "0.2"]
    assert main([*args, "--json", "--models", "linear-tm", "condensed"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["haptic"] == {"rate": 1000.0, "force_tol": 0.2}
    ok = [c for c in out["candidates"] if c["qualifies"]]
    assert all("haptic loop at 1000 Hz" in c["why"] for c in out["candidates"] if c["rel_l2"] is not None)
    assert out["model"] is not None and ok, out["why"]
    assert "--rate 1000" in out["command"]
    again = _rerun(out, capsys)
    assert again["reaction_rel_err"] <= 0.2 and again["frame"]["holds"], again["frame"]["why"]
    assert main(["advise", "cantilever", "--tol", "0.2", "--rate", "10", "--haptic-rate", "1000"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--haptic-rate judges the tool's force" in err and "\n" not in err
