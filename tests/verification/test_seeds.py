"""The seeds experiments on small meshes, each figure against an expectation that does not come from
the code that measured it: a closed form, an asymptotic limit, a cross-code agreement, an eigenvalue.
Then the page that shows them, loaded in a real headless browser."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from tests.browser import images_in_browser
from verification.engines.builtin import scene_model
from verification.metrics import rel_l2
from verification.runs.reference import reference_result
from verification.studies import seeds
from verification.studies.seeds import common, e2_partial_rotation, e3_tubes

pytestmark = pytest.mark.slow

_RUNS: dict = {}


def finding(key: str) -> dict:
    """One experiment at common.SMALL, run once per session (the page test reuses all nine)."""
    if key not in _RUNS:
        _RUNS[key] = seeds.EXPERIMENTS[key](common.SMALL)
    return _RUNS[key]


def test_global_rotation_energy_and_volume_by_closed_form():
    f = finding("global-rotation")
    young, nu, volume = 5.0e4, 0.45, f["data"]["mesh"]["volume_m3"]
    lam, mu = young * nu / ((1 + nu) * (1 - 2 * nu)), young / (2 * (1 + nu))
    for r in f["table"]:
        t = math.radians(r["angle_deg"])
        eps = (math.cos(t) - 1.0) * np.diag([1.0, 1.0, 0.0])  # small strain of a turn about z
        w = 0.5 * lam * np.trace(eps) ** 2 + mu * np.sum(eps * eps)
        scale = max(w * volume, 1e-30)
        # an affine field is exact in P1: only round-off separates the model's energy from the integral
        assert abs(r["linear-tm_energy_J"] - w * volume) <= 1e-12 * scale + 1e-30
        for m in ("corotational-tm", "stvk-tm"):
            assert abs(r[f"{m}_energy_J"]) <= 1e-12 * scale + 1e-30
            assert abs(r[f"{m}_volume_change"]) < 1e-12
        # released, the linear body keeps the rigid part of the turn: det(I + sin t [a]x) = 1 + sin^2 t.
        # The mesh's second moment of mass is isotropic to about 1e-8, so the continuum value holds to 1e-7;
        # against the discrete projection only the damped run's settling tolerance is left.
        assert abs(r["linear-tm_volume_change"] - math.sin(t) ** 2) < 1e-7
        assert abs(r["linear-tm_volume_change"] - r["projection_volume_change"]) < 1e-9
    assert f["verdict"] == "confirmed"


def test_partial_rotation_linear_error_is_first_order_in_the_angle():
    f = finding("partial-rotation")
    (a, b) = f["table"]
    # turning by t, the linear model misses the rotation's second-order term: relative to the O(t)
    # displacement its difference from StVK is O(t), so doubling a small angle doubles it
    slope = math.log(b["linear_vs_stvk"] / a["linear_vs_stvk"]) / math.log(b["angle_deg"] / a["angle_deg"])
    assert abs(slope - 1.0) < 0.05
    assert b["linear-tm_rel_l2"] > b["stvk-tm_rel_l2"]
    # at the small size's 8 degrees the linear model's own error (6% of the displacement, first order in
    # the angle) adds to the mesh's, which StVK shares (3%): over StVK's but not five times it, so the
    # rule says nuanced; the full size's 180 degrees decides the claim
    assert 1.0 < b["linear-tm_rel_l2"] / b["stvk-tm_rel_l2"] < 5.0
    assert f["plots"] and f["verdict"] == "nuanced"


def test_tube_fibres_along_the_axis_follow_beam_theory():
    f = finding("tubes")
    iso, axial, around = f["table"]
    ro, ri, length, young, nu = 0.01, 0.006, 0.06, 5.0e4, 0.45
    inertia = math.pi / 4 * (ro**4 - ri**4)
    area = math.pi * (ro**2 - ri**2)
    shear = young / (2 * (1 + nu))
    kappa = 0.53  # Timoshenko's shear coefficient of a tube with ri / ro = 0.6 (Cowper 1966)
    force = common.SMALL.tube_force

    def tip(e_axial):
        return force * length**3 / (3 * e_axial * inertia) + force * length / (kappa * shear * area)

    # Fibres along the axis stiffen bending by young_fiber / young and leave the shear term alone.
    # Beam theory ignores the clamp's restrained Poisson contraction and the top's load spreading:
    # 15% is its accuracy on this short (L / D = 3) tube.
    expected = tip(e3_tubes.FIBRE_RATIO * young) / tip(young)
    assert abs(axial["ref_ratio"] / expected - 1.0) < 0.15
    assert 1e3 * tip(young) == pytest.approx(iso["ref_tip_mm"], rel=0.15)
    # fibres around the tube resist its walls' hoop strain (the bent walls' Poisson contraction, the
    # section's ovalisation), not the axial strain that carries bending: stiffer, by less than axial ones
    assert axial["ref_ratio"] < around["ref_ratio"] < 1.0
    for m in ("linear-tm", "stvk-tm"):
        assert axial[f"{m}_ratio"] == pytest.approx(axial["ref_ratio"], rel=0.1)


def test_liver_linear_and_nonlinear_agree_under_a_small_force():
    f = finding("liver")
    (row,) = f["table"]
    # under a force that moves the lobe 0.1% of the organ's size the models are in the linear limit: the
    # linear and StVK answers differ by a fraction of that strain
    assert row["ref_max_of_size"] < 0.01
    assert row["linear_vs_stvk"] < row["ref_max_of_size"]
    assert f["plots"]


def test_hybrid_limits_are_stvk_and_linear():
    f = finding("hybrid-threshold")
    rows, data = f["table"], f["data"]
    # threshold 0: every tetrahedron is StVK; past the largest displacement none is. The runs settle to
    # 1e-10 of the force scale, so their errors agree to far better than 1e-6.
    assert rows[0]["nonlinear_tets"] == 1.0 and rows[-1]["nonlinear_tets"] == 0.0
    assert rows[0]["rel_l2"] == pytest.approx(data["stvk-tm"]["rel_l2"], rel=1e-6)
    assert rows[-1]["rel_l2"] == pytest.approx(data["linear-tm"]["rel_l2"], rel=1e-6)
    assert rows[0]["departure_from_stvk"] < 1e-8
    assert rows[-1]["departure_from_stvk"] == pytest.approx(data["linear_departure_from_stvk"], rel=1e-6)
    fractions = [r["nonlinear_tets"] for r in rows]
    assert fractions == sorted(fractions, reverse=True)


def test_tensor_mass_is_the_p1_solution_on_every_mesh():
    f = finding("tensor-mass-vs-mass-spring")
    h0, _ = common.SMALL.remesh_h
    scene = common.seed_scene("beam-linear", f"-h{h0:g}", e2_partial_rotation._h_edit(h0))
    u, _ = common._settled(scene, "linear-tm", common.SMALL.reference)
    p1 = reference_result(scene, degree=1, estimate=False, own_mesh=True).displacement[0]
    # one linear system solved by dolfinx's LU and by damped dynamics settled to 1e-10 of the force
    # scale, over a conditioning of about 1e3
    assert rel_l2(u, p1) < 1e-6
    a, fine, _ = f["table"]
    assert fine["linear-tm_rel_l2"] < a["linear-tm_rel_l2"] / 1.5  # P1 converges on refinement
    assert fine["mass-spring_rel_l2"] > 0.8 * a["mass-spring_rel_l2"]  # the springs' error is their own


def test_critical_step_is_the_measured_stability_limit():
    f = finding("critical-stiffness")
    for r in f["table"]:
        scene = common.seed_scene(
            "spring-block", f"-E{r['young_pa']:g}", lambda d, e=r["young_pa"]: d["material"].update(young=e)
        )
        model = scene_model(scene, "mass-spring")
        free = model.loading.free.ravel() > 0
        k = model.rest_stiffness().toarray()[np.ix_(free, free)]
        minv = 1.0 / np.sqrt(np.repeat(model.mass, 3)[free])
        omega = math.sqrt(np.linalg.eigvalsh(minv[:, None] * k * minv[None, :])[-1])
        # symplectic Euler is stable up to 2 / omega_max: the bisection's bracket must hold it
        assert r["measured_dt_s"] <= 2.0 / omega * (1 + 1e-9)
        assert r["unstable_dt_s"] >= 2.0 / omega * (1 - 1e-9)
    # the springs scale with E, so the stable step scales as E^-1/2 exactly, bisection and all
    assert f["data"]["dt_exponent_in_E"] == pytest.approx(-0.5, abs=1e-6)


def test_rates_follow_the_frame_arithmetic():
    f = finding("rates")
    for r in f["table"]:
        if r["status"] != "ok":
            continue
        # a static scene holds a rate when one step fits in 80% of its frame
        assert r["holds_haptic"] == (r["step_us"] <= 0.8 * 1e3)
        assert r["holds_visual"] == (r["step_us"] <= 0.8 * 1e5)
        assert r["holds_visual"] or not r["holds_haptic"]


def test_speedups_linear_models_share_one_answer():
    f = finding("speed-ups")
    by = {r["model"]: r for r in f["table"]}
    # condensed and precomputed solve the settled linear tensor-mass's system exactly (docs section 7)
    for m in ("condensed", "precomputed"):
        assert by[m]["rel_l2"] == pytest.approx(by["linear-tm"]["rel_l2"], rel=1e-6)
    # stvk-tm's force is dolfinx's P1 StVK residual on the same mesh (test_models), so settled it
    # answers what the timed full FEM solve answers, to the two solvers' tolerances (1e-10, 1e-10)
    assert by["stvk-tm"]["rel_l2"] == pytest.approx(f["table"][0]["rel_l2"], rel=1e-6)


def test_seeds_json_lists_nine_findings(capsys):
    """Every finding carries what the issue asks for, and --json writes it without the pictures."""
    from verification.cli import main

    for k in seeds.EXPERIMENTS:
        finding(k)
    res = {"experiments": [_RUNS[k] for k in seeds.EXPERIMENTS], "meta": {"size": "small", "wall_s": 0.0}}
    data = json.loads(json.dumps(seeds.without_pictures(res), default=str))
    assert [f["number"] for f in data["experiments"]] == list(range(1, 10))
    for f in data["experiments"]:
        assert f["verdict"] in ("confirmed", "refuted", "nuanced", "undecided")
        for k in ("claim", "source", "figure", "decides", "rule", "reference", "table", "plots"):
            assert f[k], (f["key"], k)
        assert "ref_err_estimate" in f["reference"]
        assert all(isinstance(p, str) for p in f["plots"])
    assert main(["seeds", "--only", "no-such"]) == 2
    assert "not an experiment" in capsys.readouterr().err


def test_report_seeds_fails_on_a_bad_directory_before_running(tmp_path, capsys):
    """A report directory that cannot be made is one line, said before half an hour of runs."""
    from verification.cli import main

    taken = tmp_path / "a-file"
    taken.write_text("")
    assert main(["report", "--seeds", "--out", str(taken)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(taken) in err and "existing file" in err


def test_seeds_page_images_load_in_a_headless_browser(tmp_path):
    from verification.report.seeds_page import write_seeds_report

    for k in seeds.EXPERIMENTS:
        finding(k)
    res = {"experiments": [_RUNS[k] for k in seeds.EXPERIMENTS], "meta": {"size": "small", "wall_s": 0.0}}
    page = write_seeds_report(res, out=str(tmp_path / "seeds"))
    images, broken, err = images_in_browser(page, tmp_path)
    n_plots = sum(len(f["plots"]) for f in res["experiments"])
    assert (images, broken) == (n_plots, 0), err


def test_a_rates_row_whose_run_does_not_settle_says_so_with_its_step_time(monkeypatch, tmp_path):
    """hybrid-tm did not settle on the rates study's 7232-tetrahedron beam, and the whole seeds page
    failed with a KeyError: the unsettled run's metadata (its step timed from rest) did not name its
    integrator. Made here with a settling budget of 5 steps: the row says "did not settle", carries its
    step time and the rates it holds, and has no error."""
    from verification.studies.seeds import e8_rates

    monkeypatch.setenv("TISSUEBENCH_CACHE", str(tmp_path))  # the unsettled run is cached: a private cache
    monkeypatch.setattr(common, "SETTLE_STEPS", 5)
    scene = e8_rates.rates_scenes(common.SMALL)[0]
    row = e8_rates._rate_row(scene, "linear-tm", np.zeros((scene.mesh.n_vertices, 3)), common.SMALL, {})
    assert row["status"].startswith("did not settle") and row["rel_l2"] is None
    assert row["step_us"] > 0 and isinstance(row["holds_visual"], bool)
