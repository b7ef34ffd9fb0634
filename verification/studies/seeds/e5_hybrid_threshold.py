"""Experiment 5, the hybrid threshold: how much of StVK's accuracy a hybrid keeps, and at what rate."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from realtime.models import hybrid_tm, linear_tm, stvk_tm
from realtime.models.hybrid_tm import nonlinear_fraction
from verification.figures import png
from verification.metrics import rel_l2
from verification.progress import log
from verification.scene import Scene
from verification.studies.seeds.common import KEEPS_NONLINEAR, Size, _finding, _ref, _reference_info, _settled
from verification.studies.seeds.e4_liver import liver_scene


def decide(data: dict) -> str:
    """The rule on ``data``: the rate at the largest threshold over the rate at zero (rate_gain), the
    fastest accurate threshold's (accurate_gain, None where none keeps the non-linear answer) and
    whether the rate never fell by more than 10% as the threshold grew (monotone)."""
    if data["rate_gain"] <= 1.0:
        return "refuted"
    if data["accurate_gain"] is None:  # measured: no threshold keeps the non-linear answer
        return "nuanced"
    return "confirmed" if data["accurate_gain"] >= 1.5 and data["monotone"] else "nuanced"


def hybrid_rates(size: Size) -> dict:
    out = _finding(
        5,
        "hybrid-threshold",
        "The hybrid model's update rate against its threshold",
        "000, slide 30 (Picinbono et al. 2003)",
        "Using non-linear elasticity only where displacements exceed a threshold raises the update rate "
        "of the liver model as the threshold grows (slide 30's table on 6342 tetrahedra, 1394 vertices).",
        "confirmed when the fastest threshold whose answer keeps the non-linear one (its departure from "
        f"StVK tensor-mass at most {KEEPS_NONLINEAR:.0%} of the all-linear model's) runs at least 1.5 times "
        "the rate at threshold zero, and the rate never falls by more than 10% (timing noise) as the "
        "threshold grows: the hybrid buys speed without giving up the non-linear answer; refuted when even "
        "the largest threshold is not faster than zero; nuanced otherwise (the rate rises, but only as the "
        "answer turns linear)",
    )
    scene = liver_scene(size.hybrid_scene, size)
    ref, est = _ref(scene, size)
    umax = float(np.linalg.norm(ref, axis=1).max())
    pairs = [_threshold_row(scene, frac * umax, frac, ref, size) for frac in size.hybrid_fractions]
    rows, hybrid_answers = [row for row, _ in pairs], [u for _, u in pairs]
    bounds, answers = {}, {}
    for m in (stvk_tm.NAME, linear_tm.NAME):
        answers[m], meta = _settled(scene, m, size.reference)
        bounds[m] = {"step_us": meta["step_us"], "rate_hz": 1e6 / meta["step_us"], "rel_l2": rel_l2(answers[m], ref)}
    linear_departure = rel_l2(answers[linear_tm.NAME], answers[stvk_tm.NAME])
    for r, u in zip(rows, hybrid_answers, strict=True):
        r["departure_from_stvk"] = None if u is None else rel_l2(u, answers[stvk_tm.NAME])
    out["table"] = rows
    rates = [r["rate_hz"] for r in rows]
    gain = rates[-1] / rates[0]
    monotone = all(b > 0.9 * max(rates[: k + 1]) for k, b in enumerate(rates[1:]))
    near = [
        r
        for r in rows
        if r["departure_from_stvk"] is not None and r["departure_from_stvk"] <= KEEPS_NONLINEAR * linear_departure
    ]
    best = max(near, key=lambda r: r["rate_hz"]) if near else None
    mesh = scene.mesh
    out["data"] = {
        "mesh": {"n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets},
        "rate_gain": gain,
        "accurate_gain": (best["rate_hz"] / rates[0]) if best else None,
        "monotone": monotone,
        "fastest_keeping_nonlinear": best,
        "linear_departure_from_stvk": linear_departure,
        stvk_tm.NAME: bounds[stvk_tm.NAME],
        linear_tm.NAME: bounds[linear_tm.NAME],
    }
    out["verdict"] = decide(out["data"])
    out["decides"] = (
        f"the rate goes from {rates[0]:.0f} Hz (threshold 0) to {rates[-1]:.0f} Hz (all linear), x{gain:.2f}"
        + (
            f"; at {best['threshold_mm']:.2f} mm it runs at {best['rate_hz']:.0f} Hz, "
            f"{best['departure_from_stvk']:.2%} from StVK (all linear: {linear_departure:.2%})"
            if best
            else ""
        )
    )

    def one(r):
        if r["rel_l2"] is None:
            return f"{r['threshold_mm']:.2g} mm {r['rate_hz']:.0f} Hz (did not settle)"
        return (
            f"{r['threshold_mm']:.2g} mm {r['rate_hz']:.0f} Hz (error {r['rel_l2']:.1%}, "
            f"{r['departure_from_stvk']:.2%} from StVK)"
        )

    out["figure"] = f"{mesh.n_tets} tetrahedra, {mesh.n_vertices} vertices: " + ", ".join(one(r) for r in rows)
    out["reference"] = _reference_info([est])
    out["plots"].append(
        {"alt": "hybrid model's rate and error against its threshold", "png": _plot(rows, rates, bounds, scene)}
    )
    return out


def _plot(rows: list[dict], rates: list[float], bounds: dict, scene: Scene) -> str:
    """The hybrid model's rate and its departure from StVK against its threshold, the bounds' rates
    beside."""
    fig, ax = plt.subplots(figsize=(6.4, 3.4))
    xs = [r["threshold_of_max"] for r in rows]
    ax.plot(xs, rates, "o-", color="#1f77b4", label="hybrid-tm rate")
    ax.axhline(bounds[stvk_tm.NAME]["rate_hz"], color="#1f77b4", ls=":", lw=0.8, label="stvk-tm rate")
    ax.axhline(bounds[linear_tm.NAME]["rate_hz"], color="#1f77b4", ls="--", lw=0.8, label="linear-tm rate")
    ax.set_xlabel("threshold / largest displacement")
    ax.set_ylabel("updates per second (Hz)", color="#1f77b4")
    ax2 = ax.twinx()
    ax2.plot(
        xs, [np.nan if r["rel_l2"] is None else 100 * r["departure_from_stvk"] for r in rows], "s-", color="#d62728"
    )
    ax2.set_ylabel("departure from stvk-tm (%)", color="#d62728")
    ax.legend(fontsize=7, loc="upper left")
    ax.set_title(f"hybrid model on {scene.name} ({scene.mesh.n_tets} tetrahedra)", fontsize=9)
    return png(fig)


def _threshold_row(scene: Scene, threshold: float, frac: float, ref, size: Size) -> tuple[dict, object]:
    """hybrid-tm at ``threshold`` (m, ``frac`` of the largest reference displacement): its row (step time,
    rate, error, the share of tetrahedra non-linear at the reference's answer) and its settled answer
    (N, 3) m, None where it did not settle. ``ref``: the reference displacement (N, 3) m."""
    u, meta = _settled(scene, hybrid_tm.NAME, size.reference, {"threshold": threshold}, allow_unsettled=True)
    row = {
        "threshold_mm": 1e3 * threshold,
        "threshold_of_max": frac,
        "nonlinear_tets": nonlinear_fraction(scene.mesh.tets, ref, threshold),
        "step_us": meta["step_us"],
        "rate_hz": 1e6 / meta["step_us"],
        "rel_l2": None if u is None else rel_l2(u, ref),
        "settled": meta.get("unsettled", "yes"),
    }
    log(f"seeds 5: threshold {1e3 * threshold:.2f} mm: {row['step_us']:.0f} us, settled: {row['settled']}")
    return row, u
