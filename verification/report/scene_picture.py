"""A picture of a scene before anything is solved (``tissuebench check --picture FILE.png``, and the
report's "Mesh" section): the body from above, the front and the side, with its axes and extent in
metres, each held region and each load's region coloured and labelled as the scene file names them
(fixed[0], load[0]), a tool's motion and gravity drawn as arrows, and the faces a cut opens.

The body is its boundary triangles projected onto each view's plane, translucent, so that its
silhouette and its thickness show; the regions are their vertices, drawn over it. It answers what
users otherwise answer with a script on the export: which way is up, where the back is, whether the
tool sits where the scene means it to, and whether the file was in millimetres.
"""

from __future__ import annotations

import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import PolyCollection  # noqa: E402

#: The three views: (title, horizontal axis, vertical axis), axes by index (0 x, 1 y, 2 z).
VIEWS = (("from above (x, y)", 0, 1), ("from the front (x, z)", 0, 2), ("from the side (y, z)", 1, 2))
#: Held regions' colours, then loads' (a qualitative palette; a region keeps its colour in every view).
HELD_COLOURS = ("#1f77b4", "#17becf", "#9467bd", "#7f7f7f")
LOAD_COLOURS = ("#d62728", "#ff7f0e", "#e377c2", "#bcbd22", "#8c564b")
CUT_COLOUR = "#2ca02c"
#: The arrows' length, as a fraction of the body's largest extent.
ARROW = 0.15


def _regions(scene) -> list[dict]:
    """Each fixed and load region to draw: its label, colour, marker, vertices (V,) and the direction
    of its motion or force (3,) (None: a held region)."""
    from reference.problem import Displacement
    from verification.events import cut_faces

    mesh, out = scene.mesh, []
    for i, fx in enumerate(scene.problem.fixed):
        v = fx.region.vertices(mesh)
        comps = "" if len(fx.components) == 3 else f" ({''.join(fx.components)} only)"
        out.append(
            {
                "label": f"fixed[{i}]: {len(v)} vertices held{comps}",
                "colour": HELD_COLOURS[i % len(HELD_COLOURS)],
                "marker": "s",
                "vertices": v,
                "direction": None,
            }
        )
    for i, ld in enumerate(scene.problem.loads):
        if not hasattr(ld, "region"):
            continue
        v = ld.region.vertices(mesh)
        if isinstance(ld, Displacement):
            d = None if ld.translation is None else np.asarray(ld.translation, dtype=float)
            what = (
                f"tool, moves {np.round(d * 1e3, 3).tolist()} mm"
                if d is not None
                else f"tool, turns {ld.angle:g} deg about {list(ld.axis)}"
            )
        else:
            d = np.asarray(ld.value, dtype=float)
            what = f"{type(ld).__name__.lower()} {np.round(d, 4).tolist()}"
        out.append(
            {
                "label": f"load[{i}]: {what}, {len(v)} vertices",
                "colour": LOAD_COLOURS[i % len(LOAD_COLOURS)],
                "marker": "o",
                "vertices": v,
                "direction": d,
            }
        )
    for e in scene.events:
        if e.kind == "cut":
            faces = cut_faces(mesh.points, mesh.tets, e)
            out.append(
                {
                    "label": f"cut at t = {e.time:g} s: {len(faces)} faces opened",
                    "colour": CUT_COLOUR,
                    "marker": "^",
                    "vertices": np.unique(faces),
                    "direction": None,
                    "faces": faces,
                }
            )
    return out


def _view(ax, scene, regions: list[dict], title: str, a: int, b: int, span: float) -> None:
    """One view: the boundary projected onto axes (a, b), the regions' vertices and their arrows."""
    mesh = scene.mesh
    p = mesh.points
    tri = p[mesh.boundary][:, :, [a, b]]
    ax.add_collection(
        PolyCollection(tri, facecolor=(0.55, 0.6, 0.7, 0.06), edgecolor=(0.3, 0.3, 0.35, 0.25), linewidths=0.3)
    )
    for r in regions:
        if "faces" in r:
            ax.add_collection(
                PolyCollection(
                    p[r["faces"]][:, :, [a, b]], facecolor=CUT_COLOUR + "55", edgecolor=CUT_COLOUR, linewidths=0.5
                )
            )
        x = p[r["vertices"]]
        if len(x):  # its name beside it, so that the views read without the legend
            ax.annotate(
                r["label"].split(":")[0],
                (x[:, a].max(), x[:, b].max()),
                fontsize=7,
                color=r["colour"],
                xytext=(3, 3),
                textcoords="offset points",
                zorder=5,
            )
        ax.scatter(x[:, a], x[:, b], s=22, c=r["colour"], marker=r["marker"], edgecolors="k", linewidths=0.4, zorder=3)
        d = r["direction"]
        if d is not None and len(x) and np.linalg.norm(d[[a, b]]) > 1e-12 * np.linalg.norm(d):
            c = x.mean(axis=0)
            arrow = ARROW * span * d[[a, b]] / np.linalg.norm(d)
            ax.annotate(
                "",
                xy=(c[a] + arrow[0], c[b] + arrow[1]),
                xytext=(c[a], c[b]),
                arrowprops={"arrowstyle": "-|>", "color": r["colour"], "lw": 1.8},
                zorder=4,
            )
    g = scene.problem.gravity()
    if np.linalg.norm(g[[a, b]]) > 1e-12 * max(np.linalg.norm(g), 1e-300):
        lo = p.min(axis=0)
        arrow = ARROW * span * g[[a, b]] / np.linalg.norm(g)
        start = (lo[a] + 0.05 * span - min(arrow[0], 0.0), lo[b] + 0.05 * span - min(arrow[1], 0.0))
        ax.annotate(
            "",
            xy=(start[0] + arrow[0], start[1] + arrow[1]),
            xytext=start,
            arrowprops={"arrowstyle": "-|>", "color": "k", "lw": 1.2},
        )
        ax.text(start[0], start[1], " gravity", fontsize=7, va="bottom" if arrow[1] < 0 else "top")
    names = "xyz"
    ax.set_xlabel(f"{names[a]} (m)")
    ax.set_ylabel(f"{names[b]} (m)")
    ax.set_title(title, fontsize=9)
    ax.set_aspect("equal")
    ax.autoscale_view()
    ax.margins(0.08)
    ax.tick_params(labelsize=7)
    ax.grid(True, linewidth=0.3, alpha=0.5)


def scene_picture(scene) -> bytes:
    """The scene seen from three sides (module docstring), as PNG bytes."""
    mesh = scene.mesh
    lo, hi = mesh.bounding_box()
    extent = hi - lo
    span = float(extent.max())
    regions = _regions(scene)
    fig, axes = plt.subplots(1, 3, figsize=(14, 4.6))
    for ax, (title, a, b) in zip(axes, VIEWS, strict=True):
        _view(ax, scene, regions, title, a, b, span)
    size = " x ".join(f"{e:.3g}" for e in extent)
    fig.suptitle(
        f"{scene.name}: {size} m (x, y, z), from {np.round(lo, 4).tolist()} to {np.round(hi, 4).tolist()} m; "
        f"{mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra",
        fontsize=10,
    )
    handles = [
        plt.Line2D([], [], marker=r["marker"], color=r["colour"], markeredgecolor="k", linestyle="", label=r["label"])
        for r in regions
    ]
    if handles:
        fig.legend(handles=handles, loc="lower center", ncol=min(len(handles), 3), fontsize=8, frameon=False)
    fig.tight_layout(rect=(0, 0.08 if handles else 0, 1, 0.94))
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110)
    plt.close(fig)
    return buf.getvalue()
