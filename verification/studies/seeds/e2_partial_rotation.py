"""Experiment 2, partial rotation: a twisted beam, where linear elasticity swells and StVK does not."""

from __future__ import annotations

import matplotlib.pyplot as plt

from realtime.models import linear_tm, stvk_tm
from verification.figures import png, projected_shapes
from verification.metrics import rel_l2
from verification.progress import log
from verification.scene import Scene
from verification.studies.seeds.common import (
    TENSOR_MASS,
    Size,
    _finding,
    _ref,
    _reference_info,
    _settled,
    _volume_change,
    seed_scene,
)


def _angle_edit(angle: float):
    def edit(data):
        data["load"][0]["rotation"]["angle"] = float(angle)

    return edit


def _h_edit(h: float, then=None):
    def edit(data):
        data["mesh"]["h"] = float(h)
        if then is not None:
            then(data)

    return edit


def twist_scenes(size: Size) -> list[Scene]:
    return [
        seed_scene("twist-cylinder", f"-{deg:g}deg", _h_edit(size.twist_h, _angle_edit(deg)))
        for deg in size.twist_angles
    ]


def decide(data: dict) -> str:
    """The rule on ``data``: the linear model's error over StVK's at the largest angle, and whether the
    linear error grows with the angle."""
    ratio = data["linear_over_stvk_at_largest"]
    if data["linear_error_grows"] and ratio > 5:
        return "confirmed"
    return "refuted" if ratio <= 1 else "nuanced"


def partial_rotation(size: Size) -> dict:
    out = _finding(
        2,
        "partial-rotation",
        "Partial rotation of a cylinder",
        "000, slides 19 and 26 (Picinbono et al. 2003)",
        "When one end of a cylinder is turned and the other held, the linear model deforms wrongly "
        "(its turned part inflates and shears), while the non-linear StVK model follows the true shape.",
        "confirmed when the linear model's error grows with the angle and is more than 5 times StVK's at "
        "the largest angle; refuted when it is not larger than StVK's",
    )
    rows, estimates, shapes = [], [], None
    for deg, scene in zip(size.twist_angles, twist_scenes(size), strict=True):
        ref, est = _ref(scene, size)
        estimates.append(est)
        mesh = scene.mesh
        row = {"angle_deg": deg, "ref_volume_change": _volume_change(mesh.points, mesh.tets, ref)}
        answers = {}
        for m in TENSOR_MASS:
            u, meta = _settled(scene, m, size.reference)
            answers[m] = u
            row[f"{m}_rel_l2"] = rel_l2(u, ref)
            row[f"{m}_volume_change"] = _volume_change(mesh.points, mesh.tets, u)
        row["linear_vs_stvk"] = rel_l2(answers[linear_tm.NAME], answers[stvk_tm.NAME])
        rows.append(row)
        shapes = (mesh, ref, answers, deg)
        log(f"seeds 2: {deg} degrees: linear {row['linear-tm_rel_l2']:.3f}, stvk {row['stvk-tm_rel_l2']:.3f}")
    out["table"] = rows
    lin = [r["linear-tm_rel_l2"] for r in rows]
    last = rows[-1]
    ratio = last["linear-tm_rel_l2"] / max(last["stvk-tm_rel_l2"], 1e-300)
    growing = all(b > a for a, b in zip(lin, lin[1:], strict=False))
    out["data"] = {"linear_over_stvk_at_largest": ratio, "linear_error_grows": growing}
    out["verdict"] = decide(out["data"])
    out["decides"] = (
        f"at {last['angle_deg']} degrees the linear model is {last['linear-tm_rel_l2']:.1%} off, "
        f"{ratio:.1f} times StVK's {last['stvk-tm_rel_l2']:.2%}"
    )
    out["figure"] = (
        f"linear error {', '.join(f'{e:.1%}' for e in lin)} at {', '.join(str(r['angle_deg']) for r in rows)} deg; "
        f"volume change at {last['angle_deg']}: linear {last['linear-tm_volume_change']:+.1%}, "
        f"reference {last['ref_volume_change']:+.1%}"
    )
    out["reference"] = _reference_info(estimates)
    mesh, ref, answers, deg = shapes
    fig, axs = plt.subplots(1, 3, figsize=(11, 3.6))
    for ax, axes, view in ((axs[0], (0, 2), "side"), (axs[1], (0, 1), "top")):
        projected_shapes(
            ax,
            mesh.points,
            mesh.boundary,
            [
                (answers[stvk_tm.NAME], "stvk-tm (solid)", "solid", "#9ecae1"),
                (answers[linear_tm.NAME], "linear-tm (wireframe)", "wire", "#d62728"),
            ],
            axes,
        )
        ax.set_title(f"{view} view, {deg} degrees", fontsize=9)
    axs[0].legend(fontsize=7, loc="lower left")
    for m, mk in zip(TENSOR_MASS, ("o-", "s-", "^-"), strict=True):
        axs[2].plot([r["angle_deg"] for r in rows], [r[f"{m}_rel_l2"] for r in rows], mk, ms=4, label=m)
    axs[2].set_xlabel("top turned by (degrees)")
    axs[2].set_ylabel("rel_l2 against the reference")
    axs[2].legend(fontsize=7)
    out["plots"].append(
        {"alt": "linear and StVK cylinders, side and top views, and error against angle", "png": png(fig)}
    )
    return out
