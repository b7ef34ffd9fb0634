"""Every seeds experiment's rule can come out otherwise: each ``decide`` is given constructed numbers (a
hypothetical model, mesh or timing) and returns each of its verdicts. A rule that cannot is an
identity, not a test of the claim. The numbers of today's full run are in reports/seeds; here, each
rule on its own, in milliseconds."""

import pytest

from verification.studies.seeds import (
    e1_global_rotation,
    e2_partial_rotation,
    e3_tubes,
    e4_liver,
    e5_hybrid_threshold,
    e6_remeshing,
    e7_critical_stiffness,
    e8_rates,
    e9_speedups,
)


def _e1(stores=1.0, dv=1.0, others=1e-14):
    return {
        "linear_energy_of_closed_form": stores,
        "linear_volume_change_at": {"value": dv},
        "nonlinear_largest": others,
    }


@pytest.mark.parametrize(
    "data, verdict",
    [
        (_e1(), "confirmed"),  # the linear cube stores the closed form's energy and grows by sin^2 90 = 100%
        (_e1(stores=0.0, dv=0.0), "refuted"),  # a linear model that were rotation-invariant
        (_e1(others=0.05), "refuted"),  # a corotational model that stored 5% of the energy
        (_e1(dv=0.05), "nuanced"),  # energy stored, but the released body barely grows
    ],
)
def test_global_rotation_rule(data, verdict):
    assert e1_global_rotation.decide(data) == verdict


@pytest.mark.parametrize(
    "ratio, grows, verdict",
    [(20.0, True, "confirmed"), (0.9, True, "refuted"), (3.0, True, "nuanced"), (20.0, False, "nuanced")],
)
def test_partial_rotation_rule(ratio, grows, verdict):
    """A linear model as accurate as StVK at 180 degrees (ratio 0.9) would refute the claim."""
    assert e2_partial_rotation.decide({"linear_over_stvk_at_largest": ratio, "linear_error_grows": grows}) == verdict


@pytest.mark.parametrize(
    "change, miss, estimate, verdict",
    [
        (0.4, 0.02, 1e-3, "confirmed"),
        (0.005, 0.02, 1e-3, "refuted"),  # fibres that move the tip by 0.5%, five times the truth's bar
        (0.4, 0.3, 1e-3, "nuanced"),  # stvk-tm 30% off the fibres' effect
        (0.005, 0.02, None, "undecided"),  # no estimate: a 0.5% change is not measurable against nothing
    ],
)
def test_tubes_rule(change, miss, estimate, verdict):
    data = {"largest_change": change, "stvk_tm_largest_miss": miss, "ref_err_estimate": estimate}
    assert e3_tubes.decide(data) == verdict


@pytest.mark.parametrize(
    "differ, ratio, verdict", [(True, 3.0, "confirmed"), (False, 3.0, "refuted"), (True, 1.2, "nuanced")]
)
def test_liver_rule(differ, ratio, verdict):
    assert e4_liver.decide({"models_differ": differ, "smallest_linear_over_stvk": ratio}) == verdict


@pytest.mark.parametrize(
    "gain, accurate, monotone, verdict",
    [
        (2.0, 1.8, True, "confirmed"),  # a threshold that keeps StVK's answer at 1.8 times the rate
        (2.0, 1.02, True, "nuanced"),  # the gain comes only as the answer turns linear
        (2.0, None, True, "nuanced"),  # no threshold keeps the non-linear answer
        (0.95, 0.95, True, "refuted"),  # a hybrid whose flag test costs what StVK saves
        (2.0, 1.8, False, "nuanced"),
    ],
)
def test_hybrid_threshold_rule(gain, accurate, monotone, verdict):
    data = {"rate_gain": gain, "accurate_gain": accurate, "monotone": monotone}
    assert e5_hybrid_threshold.decide(data) == verdict


def _e6(speed=1.2, tm=0.5, ms=0.95, topo_tm=0.01, topo_ms=0.05):
    return {
        "mass_spring_over_linear_tm_step": speed,
        "linear_tm_error_ratio_on_refinement": tm,
        "mass_spring_error_ratio_on_refinement": ms,
        "tip_change_on_remeshing": {"linear-tm": topo_tm, "mass-spring": topo_ms},
    }


@pytest.mark.parametrize(
    "data, verdict",
    [
        (_e6(), "confirmed"),
        (_e6(topo_ms=0.012), "nuanced"),  # springs as insensitive to the remeshing as tensor-mass
        (_e6(speed=0.5, tm=0.9, ms=0.5, topo_ms=0.01), "refuted"),  # springs twice as fast, and converging
    ],
)
def test_tensor_mass_vs_mass_spring_rule(data, verdict):
    assert e6_remeshing.decide(data) == verdict


@pytest.mark.parametrize(
    "slope_h, slope_e, spread, verdict",
    [
        (1.02, -0.5, (0.7, 0.9), "confirmed"),
        (0.6, -0.5, (0.7, 0.9), "refuted"),  # a step that shrinks as h^0.6: the formula's h-dependence fails
        (1.02, -0.5, (0.2, 0.9), "nuanced"),  # the formula 5 times off
        (None, -0.5, (0.7, 0.9), "nuanced"),  # h not varied: the claim's h half not measured
        (1.02, -0.4, (0.7, 0.9), "nuanced"),  # E exponent off: the bisection is unreliable
    ],
)
def test_critical_stiffness_rule(slope_h, slope_e, spread, verdict):
    data = {"dt_exponent_in_h": slope_h, "dt_exponent_in_E": slope_e, "measured_over_formula": list(spread)}
    assert e7_critical_stiffness.decide(data) == verdict


@pytest.mark.parametrize(
    "ideal, haptic, verdict",
    [
        ({"904": ["condensed"], "7232": ["condensed"], "57856": ["condensed"]}, ["linear-tm"], "confirmed"),
        ({"904": ["condensed"], "7232": ["condensed"], "57856": []}, ["linear-tm"], "nuanced"),
        ({"904": [], "7232": [], "57856": []}, [], "refuted"),  # nothing at 1 kHz on 904 tetrahedra
    ],
)
def test_rates_rule(ideal, haptic, verdict):
    assert e8_rates.decide({"ideal_by_mesh": ideal, "haptic_on_smallest": haptic}) == verdict


def test_a_fast_model_out_of_tolerance_is_not_ideal():
    """The rates study's ideal model is realistic too: holding both rates at 8% error is not enough."""
    row = {"status": "ok", "holds_visual": True, "holds_haptic": True, "rel_l2": 0.08}
    assert not e8_rates._ideal(row)
    assert e8_rates._ideal({**row, "rel_l2": 0.01})


@pytest.mark.parametrize(
    "slowest_update, quasi, answer, verdict",
    [(50.0, 2000.0, 3.0, "confirmed"), (0.5, 2000.0, 3.0, "refuted"), (50.0, 2000.0, 0.2, "nuanced")],
)
def test_speed_ups_rule(slowest_update, quasi, answer, verdict):
    """An update slower than the full solve refutes; a settling slower than it leaves the claim nuanced."""
    data = {
        "slowest_update_speedup": slowest_update,
        "quasi_static_speedup": quasi,
        "slowest_answer": {"speedup_answer": answer},
    }
    assert e9_speedups.decide(data) == verdict
