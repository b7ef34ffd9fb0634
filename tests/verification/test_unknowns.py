"""A missing number decides nothing: every rule that reads a bar, an error, a build time, a settling count
or a model part, fed None, says "unknown" or "cannot decide" and names what is missing, never reads it
as zero or as success. Each rule is fed a constructed row, so each test runs in milliseconds."""

import math

import numpy as np
import pytest

from verification.runs.row import Row
from verification.studies import proposal, truth
from verification.studies.frame import (
    QUALIFIES,
    UNDECIDED,
    cost,
    frame_budget,
    judgement,
    predict,
)


def _row(err=0.02, bar=1e-3, settle=1000, **kw):
    row = Row("a scene", "linear-tm", "symplectic-euler", "ok", dt=1e-5, step_us=10.0, settle_steps=settle)
    return row.replace(rel_l2=err, ref_err_estimate=bar, **kw)


def _framed(row, **haptic):
    return row.replace(frame=frame_budget(row, 60.0, False, haptic=haptic or None))


def test_a_verdict_without_the_references_bar_cannot_decide_and_names_the_bar():
    """0.02 against a 5% tolerance qualifies with a bar of 1e-3; with no bar the same measured error
    could be anything the reference's own error allows: undecided, naming the bar."""
    assert judgement(_framed(_row()), "rel_l2", 0.05)[0] == QUALIFIES
    state, line = judgement(_framed(_row(bar=None)), "rel_l2", 0.05)
    assert state == UNDECIDED and "cannot decide, the reference's bar on rel_l2 is unknown" in line


def test_a_verdict_without_the_measured_error_cannot_decide_and_names_it():
    state, line = judgement(_framed(_row(err=None)), "rel_l2", 0.05)
    assert state == UNDECIDED and "rel_l2 was not measured" in line


def test_a_haptic_verdict_without_the_forces_bar_cannot_decide_and_names_it():
    """The shape qualifies; the tool force is 5% off against a 10% tolerance, but the reference has no
    bar on the force: the haptic part, and so the verdict, is undecided, naming the force's bar."""
    row = _row().replace(reaction_rel_err=0.05, reference={"ref_reaction_err_estimate": 1e-3})
    assert judgement(_framed(row, rate=1000.0, force_tol=0.1), "rel_l2", 0.05)[0] == QUALIFIES
    row = row.replace(reference={"ref_reaction_err_estimate": None})
    state, line = judgement(_framed(row, rate=1000.0, force_tol=0.1), "rel_l2", 0.05)
    assert state == UNDECIDED and "the reference's bar on reaction_rel_err is unknown" in line


def test_a_static_run_with_no_settling_count_has_an_unknown_time_to_its_answer():
    """A static run that did not say how many steps it settled in: its time to the answer is unknown
    (not one step's), it ranks after every known cost, and refined it stays unknown."""
    known = frame_budget(_row(settle=1000), 60.0, False)
    assert known["time_to_answer_s"] == pytest.approx(1000 * 10e-6)
    b = frame_budget(_row(settle=None), 60.0, False)
    assert b["time_to_answer_s"] is None and "its settling steps are unknown" in b["why"]
    assert cost(_row(settle=None).replace(frame=b), dynamic=False) == math.inf
    assert predict(_row(settle=None), 1, False, 60.0)["time_to_answer_s"] is None


def test_own_part_is_unknown_without_the_model_part():
    assert proposal.own_part(_row(error_budget={"mesh": 0.1, "model": 0.02, "time": None})) == 0.02
    assert proposal.own_part(_row(error_budget={"mesh": 0.1, "model": 0.01, "time": 0.01})) == 0.02
    assert proposal.own_part(_row(error_budget={"mesh": None, "model": None, "time": None})) is None


class _Scene:
    """What proposal._plans, run_plans, propose_mesh and sharp_reference read of a scene: its name, time
    mode, mesh's sizes and refined scenes (itself: the stubs answer the same at every level)."""

    name = "a scene"
    events = ()

    def refined(self, level):
        return self

    class time:
        mode = "static"

    class mesh:
        n_vertices = 100
        surface_vertices = range(60)
        tets = np.zeros((0, 4), dtype=np.int64)

    class problem:  # held and pressed nowhere: no load at points (scene.point_held)
        fixed = ()
        loads = ()


def test_a_precomputation_with_no_build_time_is_unknown_never_in_time():
    """A quasi-static candidate whose row has no build time: its predicted build is unknown, not zero,
    so it is not run on a refined mesh (nothing bounds the wait); one with a build time is."""
    base = Row("a scene", "precomputed", "quasi-static", "ok", step_us=10.0, rel_l2=0.1, ref_err_estimate=1e-3)
    base = base.replace(error_budget={"mesh": 0.1, "model": 1e-3, "time": None})
    plans = proposal._plans(_Scene, [base.replace(build_s=None)], 0.05, 2.0, 0.08, 60.0)
    assert plans and all(p["predicted_build_s"] is None and p["builds_in_time"] is None for p in plans)
    run = {"level": plans[0]["level"], "plans": plans}
    assert proposal.run_plans(_Scene, run, "rel_l2", 0.08, 60.0, False) == (None, [])
    timed = proposal._plans(_Scene, [base.replace(build_s=0.5)], 0.05, 2.0, 0.08, 60.0)
    assert timed and timed[0]["builds_in_time"] is True


def test_a_mesh_proposal_without_the_references_bar_proposes_nothing_and_says_why(monkeypatch):
    """The proposal leaves room for the reference's bar in the tolerance; an unknown bar leaves no room
    it can compute (it read as zero before): no level, naming the bar."""

    class Solved:
        def __init__(self, scale):
            self.displacement = scale * np.ones((1, 3, 3))

    # the truth, and P1 on the mesh refined once 10% from it: the mesh's part falls at order 2
    truth_, fine = Solved(1.0), Solved(0.9)
    monkeypatch.setattr(proposal, "reference_result", lambda scene, **opts: fine if opts.get("own_mesh") else truth_)
    monkeypatch.setattr(_Scene.mesh, "n_vertices", 3)
    rows = [_row(error_budget={"mesh": 0.4, "model": 0.01, "time": None})]
    out = proposal.propose_mesh(_Scene(), rows, "rel_l2", 0.05, 60.0, False, None, None)
    assert out["level"] is None and "the reference's bar is unknown" in out["why"]


class _Ref:
    def __init__(self, **meta):
        self.meta = {"solves": [{"n_dofs": 1000, "wall_s": 1.0}], **meta}


def test_the_sharp_truth_names_an_unknown_bar_and_does_not_refine_for_it(monkeypatch):
    """A reference with no estimate: refining does not make one, so nothing is solved again, and the
    answer says the bar is unknown instead of judging by the measured errors alone."""
    solved = []
    monkeypatch.setattr(truth, "reference_result", lambda scene, **opts: solved.append(opts) or _Ref())

    _, said = truth.sharp_reference(_Scene, 0.05, "rel_l2")
    assert len(solved) == 1 and not said["sharp"] and said["bar"] is None
    assert "the reference's bar on rel_l2 is unknown" in said["why"]


def _adapted_ref(shape, force, returned=2, stop="the bar is within"):
    levels = [{"level": k, "n_dofs": 1000 * 2**k} for k in range(returned + 1)]
    meta = {"estimator": "adaptive", "adaptive": {"levels": levels, "returned": returned, "stop": stop}}
    return _Ref(**meta, ref_err_estimate=shape, ref_reaction_err_estimate=force)


def test_the_haptic_truth_adapts_for_the_forces_bar_and_names_it_when_it_blocks(monkeypatch):
    """With a haptic loop the force's bar is asked for as the shape's is: the shape's 0.004 is sharp for
    5% but the force's 0.18 is not for 10%, so the static truth is adapted where its error lives, asked
    for the force's 0.03 (SHARP of 10%) too; adapted, the force's bar 0.06 still blocks, and the answer
    names the force's bar at the value it reached."""
    solved = []

    def reference_result(scene, **opts):
        solved.append(opts)
        if opts.get("estimate") == "adaptive":
            return _adapted_ref(0.002, 0.06)
        return _Ref(ref_err_estimate=0.004, ref_reaction_err_estimate=0.18)

    monkeypatch.setattr(truth, "reference_result", reference_result)

    _, said = truth.sharp_reference(_Scene, 0.05, "rel_l2", {"rate": 1000.0, "force_tol": 0.1})
    assert [o.get("estimate") for o in solved] == [True, "adaptive"] and said["estimate"] == "adaptive"
    assert solved[1]["adapt"]["force_target"] == pytest.approx(0.03) and said["blocking"] == ["the tool force"]
    assert said["force_bar"] == 0.06 and "the reference's bar on the tool force 0.06 is over 0.3" in said["why"]
    # without the haptic question the shape's bar alone is asked for: sharp at once, nothing adapted
    solved.clear()
    _, said = truth.sharp_reference(_Scene, 0.05, "rel_l2")
    assert said["sharp"] and len(solved) == 1 and said["force_bar"] is None


def test_an_adapted_truth_is_asked_for_the_bar_the_candidates_need_and_kept_only_if_sharper(monkeypatch):
    """A static truth whose bar (0.03) is over what the undecided candidates need (0.01) is adapted with
    that target and judged with when its bar is sharper (0.008: sharp); one that stopped with a worse bar
    (its next level inverted elements: 0.057) is not taken, and the answer says why it stopped."""
    solved = []
    adapted = [_adapted_ref(0.008, None)]

    def reference_result(scene, **opts):
        solved.append(opts)
        return adapted[0] if opts.get("estimate") == "adaptive" else _Ref(ref_err_estimate=0.03)

    monkeypatch.setattr(truth, "reference_result", reference_result)
    opts, said = truth.sharp_reference(_Scene, 0.05, "rel_l2", target=0.01)
    assert solved[1]["adapt"]["target"] == 0.01 and opts["estimate"] == "adaptive"
    assert said["sharp"] and said["bar"] == 0.008 and "adapted twice where its error lives" in said["why"]
    assert "the 0.01 the undecided candidates need" in said["why"]
    adapted[0] = _adapted_ref(0.057, None, returned=0, stop="level 1: its P3 check: Newton found no equilibrium")
    opts, said = truth.sharp_reference(_Scene, 0.05, "rel_l2", target=0.01)
    assert opts.get("estimate") is True and said["bar"] == 0.03 and not said["sharp"]
    assert "its bar was 0.057: level 1: its P3 check: Newton found no equilibrium" in said["why"]
    # asked not to tighten, the defaults' reference is described as it is
    solved.clear()
    _, said = truth.sharp_reference(_Scene, 0.05, "rel_l2", tighten=False)
    assert len(solved) == 1 and not said["sharp"] and said["bar"] == 0.03


def test_two_steps_of_one_model_are_one_refined_run(monkeypatch):
    """Two level-0 rows of mass-spring at 0.5 and 0.9 of the critical step both run at 0.9 on the refined
    mesh (the fraction is clamped there): the advisor runs that once and tries another model next, so
    MAX_TRIALS counts distinct runs (on cantilever-dynamic it had tried each run twice)."""
    calls = []

    def run(scene, model, integrator, dt, fraction, **opts):
        calls.append((model, fraction))
        return Row("a scene", model, integrator, "ok", rel_l2=0.5, ref_err_estimate=1e-3, dt=1e-5, step_us=1.0)

    monkeypatch.setattr(proposal, "compare_or_unsettled", run)
    rows = [
        Row("a scene", m, "symplectic-euler", "ok", dt=1e-5, fraction=f, step_us=1.0, settle_steps=10)
        for m, f in (("mass-spring", 0.9), ("mass-spring", 1.0), ("linear-tm", 0.9))
    ]
    plan = {"hopeful": True, "fits_memory": True, "builds_in_time": True, "level": 1}
    out = proposal.run_plans(
        _Scene(), {"level": 1, "plans": [{**plan, "row": r} for r in rows]}, "rel_l2", 0.05, 60.0, False
    )
    assert calls == [("mass-spring", 0.9), ("linear-tm", 0.9)] and len(out[1]) == 2
