"""Experiment 9, speed-ups: what precomputation and condensation buy, and what they cost in accuracy."""

from __future__ import annotations

import time

import matplotlib.pyplot as plt

from realtime.models import SPECS, condensed, hybrid_tm, linear_tm, precomputed, stvk_tm
from verification.figures import png
from verification.metrics import rel_l2
from verification.progress import log
from verification.runs.reference import P1_OWN_MESH, reference_result
from verification.scene import Scene
from verification.studies.seeds.common import FULL, Size, _finding, _ref, _reference_info, _settled, seed_scene
from verification.studies.seeds.e2_partial_rotation import _h_edit

SPEEDUP_MODELS = (condensed.NAME, precomputed.NAME, hybrid_tm.NAME, linear_tm.NAME, stvk_tm.NAME)


def speedup_scene(size: Size) -> Scene:
    return seed_scene(size.speedup_scene, "" if size is FULL else f"-h{size.speedup_h:g}", _h_edit(size.speedup_h))


def decide(data: dict) -> str:
    """The rule on ``data``: the smallest per-update speed-up over the full solve of any model, the
    quasi-static models' smallest, and the slowest answer's speed-up (settled, for a time-stepping
    model)."""
    if data["slowest_update_speedup"] < 1:
        return "refuted"
    if data["quasi_static_speedup"] >= 100 and data["slowest_answer"]["speedup_answer"] >= 1:
        return "confirmed"
    return "nuanced"


def speedups(size: Size) -> dict:
    out = _finding(
        9,
        "speed-ups",
        "Speed-ups against full FEM",
        "001 (Liu 2002: condensation, precomputation; 000 slide 30: the hybrid model)",
        "Condensation, precomputation and the hybrid model make an update orders of magnitude cheaper than a "
        "full finite-element solve of the same scene, for an error each pays.",
        "confirmed when condensed and precomputed updates are at least 100 times faster than the full P1 "
        "dolfinx solve and every model's answer (settled, for time-stepping ones) is faster than it; nuanced "
        "when the per-step speed-up does not survive settling; refuted when an update is slower than the solve",
    )
    scene = speedup_scene(size)
    ref, est = _ref(scene, size)
    # the full FEM solve timed warm: the first call compiles dolfinx's forms, which a simulator would
    # have done once before its first frame
    for _ in range(2):
        t0 = time.perf_counter()
        fem = reference_result(scene, **P1_OWN_MESH, use_cache=False)
        fem_s = time.perf_counter() - t0
    fem_err = rel_l2(fem.displacement[0], ref)
    rows = [{"model": "full FEM (dolfinx P1, Newton)", "update_s": fem_s, "answer_s": fem_s, "rel_l2": fem_err}]
    for m in SPEEDUP_MODELS:
        u, meta = _settled(scene, m, size.reference, allow_unsettled=True)
        step_s = meta["step_us"] * 1e-6
        answer_s = None if u is None else (step_s if SPECS[m].quasi_static else meta["static"]["steps"] * step_s)
        rows.append(
            {
                "model": m,
                "update_s": step_s,
                "answer_s": answer_s,
                "speedup_update": fem_s / step_s,
                "speedup_answer": 0.0 if answer_s is None else fem_s / answer_s,
                "rel_l2": None if u is None else rel_l2(u, ref),
                "settled": meta.get("unsettled", "yes"),
            }
        )
        log(f"seeds 9: {m}: {fem_s / step_s:.3g}x per update, settled: {rows[-1]['settled']}")
    out["table"] = rows
    by = {r["model"]: r for r in rows[1:]}
    quasi = min(by[condensed.NAME]["speedup_update"], by[precomputed.NAME]["speedup_update"])
    slowest_answer = min(rows[1:], key=lambda r: r["speedup_answer"])
    out["data"] = {
        "fem_s": fem_s,
        "quasi_static_speedup": quasi,
        "slowest_update_speedup": min(r["speedup_update"] for r in rows[1:]),
        "slowest_answer": slowest_answer,
    }
    out["verdict"] = decide(out["data"])
    slow = slowest_answer
    out["decides"] = f"condensed and precomputed update {quasi:.0f}x faster than the {fem_s:.2f} s solve; " + (
        f"{slow['model']} never settles ({slow['settled']})"
        if slow["answer_s"] is None
        else f"{slow['model']} settles {slow['speedup_answer']:.2g}x as fast as it"
    )

    def one(r):
        if r["answer_s"] is None:
            return f"{r['model']} x{r['speedup_update']:.3g} per update, never settles"
        return f"{r['model']} x{r['speedup_update']:.3g} per update (x{r['speedup_answer']:.2g} to settle), {r['rel_l2']:.1%}"

    out["figure"] = "; ".join(one(r) for r in rows[1:]) + f"; full P1 FEM {fem_s:.2f} s, {fem_err:.1%}"
    out["reference"] = _reference_info([est])
    fig, ax = plt.subplots(figsize=(6.4, 3.6))
    for r in rows[1:]:
        if r["rel_l2"] is None:  # never settled: no error to place it at
            continue
        ax.loglog(r["speedup_update"], max(r["rel_l2"], 1e-6), "o", label=f"{r['model']}, one update")
        if not SPECS[r["model"]].quasi_static:
            ax.loglog(r["speedup_answer"], max(r["rel_l2"], 1e-6), "x", color=ax.lines[-1].get_color())
    ax.axvline(1.0, color="k", ls=":", lw=0.8)
    ax.set_xlabel("speed-up against the full dolfinx solve (x: settled answer)")
    ax.set_ylabel("rel_l2 against the reference")
    ax.legend(fontsize=7)
    ax.set_title(f"{scene.name}: what each speed-up costs", fontsize=9)
    out["plots"].append({"alt": "speed-up against error for each model", "png": png(fig)})
    return out
