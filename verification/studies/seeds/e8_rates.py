"""Experiment 8, rates: which model holds the visual and haptic rates at which mesh size."""

from __future__ import annotations

import math

import matplotlib.pyplot as plt

from realtime.models import SPECS, condensed, corotational_tm, hybrid_tm, linear_tm, mass_spring, precomputed, stvk_tm
from verification.figures import png
from verification.metrics import rel_l2
from verification.progress import log
from verification.runs.row import Row
from verification.scene import Scene
from verification.studies.frame import FRAME_SHARE, available_memory, frame_budget, memory_bytes
from verification.studies.seeds.common import (
    SETTLE_STEPS,
    Size,
    _finding,
    _ref,
    _reference_info,
    _settled,
    seed_scene,
)

#: Seconds a quasi-static model's precomputation may take in the rates study (its cost grows about
#: 60-fold per refinement: 251 s for precomputed and 363 s for condensed on the 57856-tetrahedron beam).
PRECOMPUTE_BUDGET = 60.0


def _predicted_build(measured: list, n_vertices: int) -> float | None:
    """A precomputation's time, s, at ``n_vertices``, extrapolated from (vertices, seconds) measured on
    coarser meshes: the power law through the last two, or, from one, cubic growth (a dense block of
    surface columns solved against a sparse factor whose cost grows with the volume); None without any."""
    if not measured:
        return None
    (n1, t1) = measured[-1]
    p = 3.0 if len(measured) < 2 else math.log(t1 / measured[-2][1]) / math.log(n1 / measured[-2][0])
    return t1 * (n_vertices / n1) ** p


RATE_MODELS = (
    linear_tm.NAME,
    corotational_tm.NAME,
    stvk_tm.NAME,
    hybrid_tm.NAME,
    mass_spring.NAME,
    precomputed.NAME,
    condensed.NAME,
)

RATES = (("visual", 10.0), ("haptic", 1000.0))

#: The source's ideal model is fast and realistic; realistic here: within this relative error of the
#: truth (the tolerance the report's advice asks for).
REALISTIC = 0.05


def rates_scenes(size: Size) -> list[Scene]:
    return [seed_scene("rates-beam", refine=level) for level in size.rate_levels]


def rates_cells(size: Size) -> list[tuple[Scene, str, str, int]]:
    """The settlings the study makes (for ``prefetch.settle_ahead``): every time-stepping model on every
    beam that fits in memory, as ``_settled`` asks for them (symplectic Euler at the default step, at
    most SETTLE_STEPS). On the largest beam they took 13 minutes one after another in one process."""
    return [
        (scene, m, "symplectic-euler", SETTLE_STEPS)
        for scene in rates_scenes(size)
        for m in RATE_MODELS
        if not SPECS[m].quasi_static
        and memory_bytes(m, scene.mesh.n_vertices, len(scene.mesh.surface_vertices)) <= available_memory()
    ]


def rates(size: Size) -> dict:
    out = _finding(
        8,
        "rates",
        "Update rates",
        "001 (Liu 2002: visual >= 10 Hz, haptic >= 1000 Hz)",
        "An ideal deformable model is fast (10 updates per second for the eye, 1000 for a haptic device) "
        "and realistic: which model holds which rate, on how large a mesh, and at what error, on this machine.",
        f"confirmed when on every mesh some model holds both rates (using {FRAME_SHARE:.0%} of a frame) within "
        f"{REALISTIC:.0%} of the truth; refuted when no model holds the haptic rate even on the smallest mesh; "
        "nuanced otherwise (an ideal model up to some size only, or fast models that are not realistic)",
    )
    rows, estimates, built = [], [], {}
    for scene in rates_scenes(size):
        ref, est = _ref(scene, size)
        estimates.append(est)
        rows += [_rate_row(scene, m, ref, size, built) for m in RATE_MODELS]
    out["table"] = rows
    ok = [r for r in rows if "step_us" in r]  # timed: settled or not
    smallest = min(r["n_tets"] for r in rows)
    ideal = {n: [r["model"] for r in ok if r["n_tets"] == n and _ideal(r)] for n in sorted({r["n_tets"] for r in rows})}
    largest = {}
    for m in RATE_MODELS:
        for label, _ in RATES:
            held = [r for r in ok if r["model"] == m and r[f"holds_{label}"]]
            best = max(held, key=lambda r: r["n_tets"]) if held else None
            largest.setdefault(m, {})[label] = (
                None if best is None else {"n_tets": best["n_tets"], "rel_l2": best["rel_l2"], "status": best["status"]}
            )
    out["data"] = {
        "largest_mesh_held": largest,
        "ideal_by_mesh": {str(n): models for n, models in ideal.items()},
        "haptic_on_smallest": [r["model"] for r in ok if r["n_tets"] == smallest and r["holds_haptic"]],
    }
    out["verdict"] = decide(out["data"])

    def held(v):
        if v is None:
            return "none"
        err = "not settled" if v["rel_l2"] is None else f"error {v['rel_l2']:.1%}"
        return f"{v['n_tets']} tets ({err})"

    order = sorted(largest, key=lambda m: -(largest[m]["haptic"] or {"n_tets": 0})["n_tets"])
    ideal_line = "; ".join(f"{n} tets: {', '.join(ms) or 'none'}" for n, ms in ideal.items())
    out["decides"] = (
        f"both rates within {REALISTIC:.0%} of the truth: {ideal_line}; largest mesh held at 1 kHz: "
        + ", ".join(f"{m} {held(largest[m]['haptic'])}" for m in order)
    )
    out["figure"] = "; ".join(
        f"{m}: 10 Hz up to {held(v['visual'])}, 1 kHz up to {held(v['haptic'])}" for m, v in largest.items()
    )
    out["reference"] = _reference_info(estimates)
    out["plots"].append(
        {"alt": "time per update against mesh size with the visual and haptic frames", "png": _plot(ok)}
    )
    return out


def _ideal(row: dict) -> bool:
    """A row of the study holds both rates, settled, within REALISTIC of the truth."""
    return bool(
        row["status"] == "ok"
        and row["holds_visual"]
        and row["holds_haptic"]
        and row["rel_l2"] is not None
        and row["rel_l2"] <= REALISTIC
    )


def decide(data: dict) -> str:
    """The rule on ``data``: the models that are ideal (``_ideal``) on each mesh, by its tetrahedra, and
    those that hold the haptic rate on the smallest."""
    if not data["haptic_on_smallest"]:
        return "refuted"
    return "confirmed" if all(data["ideal_by_mesh"].values()) else "nuanced"


def _plot(ok: list[dict]) -> str:
    """Time per update against mesh size, with the visual and haptic frames."""
    fig, ax = plt.subplots(figsize=(6.6, 3.8))
    for m in RATE_MODELS:
        rs = [r for r in ok if r["model"] == m]
        if rs:
            ax.loglog([r["n_tets"] for r in rs], [r["step_us"] for r in rs], "o-", ms=4, label=m)
    for label, hz in RATES:
        ax.axhline(FRAME_SHARE * 1e6 / hz, color="k", ls=":", lw=0.8)
        ax.text(ax.get_xlim()[0], FRAME_SHARE * 1e6 / hz, f" {label} {hz:g} Hz", fontsize=7, va="bottom")
    ax.set_xlabel("tetrahedra")
    ax.set_ylabel("us per update")
    ax.legend(fontsize=7)
    ax.set_title("what fits in a frame on this machine", fontsize=9)
    return png(fig)


def _rate_row(scene: Scene, m: str, ref, size: Size, built: dict) -> dict:
    """One model on one beam: its step time, error and whether it holds each rate, or why it was not
    run (memory, or a precomputation ``built`` predicts too slow; each quasi-static build is recorded
    there). ``ref``: the reference displacement (N, 3) m at the beam's vertices."""
    mesh = scene.mesh
    row = {"model": m, "n_tets": mesh.n_tets, "n_vertices": mesh.n_vertices}
    need = memory_bytes(m, mesh.n_vertices, len(mesh.surface_vertices))
    if need > available_memory():
        row.update(status=f"needs {need / 1e9:.1f} GB, over half the free memory")
        return row
    predicted = _predicted_build(built.get(m, []), mesh.n_vertices)
    if predicted is not None and predicted > PRECOMPUTE_BUDGET:
        row.update(
            status=f"skipped: its precomputation would take about {predicted:.0f} s "
            f"(extrapolated from {len(built[m])} coarser meshes; the study allows {PRECOMPUTE_BUDGET:.0f} s)"
        )
        return row
    log(f"seeds 8: {m} on {mesh.n_tets} tetrahedra")
    u, meta = _settled(scene, m, size.reference, allow_unsettled=True)
    settled = u is not None
    if settled and SPECS[m].quasi_static:
        built.setdefault(m, []).append((mesh.n_vertices, meta["build_s"]))
    settle_steps = meta["static"]["steps"] if settled else 1
    run = Row(
        scene.name, m, meta["integrator"], "ok", dt=meta["dt"], step_us=meta["step_us"], settle_steps=settle_steps
    )
    row.update(
        status="ok" if settled else f"did not settle: {meta['unsettled']}",
        step_us=meta["step_us"],
        rel_l2=rel_l2(u, ref) if settled else None,
    )
    for label, hz in RATES:
        row[f"holds_{label}"] = frame_budget(run, hz, dynamic=False)["holds"]
    return row
