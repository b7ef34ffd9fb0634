"""Figures as embedded PNG, the helpers every page shares (the report's and the seeds experiments'):
a figure as base64 PNG and as an <img>, deformed surfaces projected on a plane, a legend beside the
axes. Every axis names its quantity and unit; legends sit beside the axes, never over the data."""

from __future__ import annotations

import base64
import html
import io

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from matplotlib.collections import LineCollection, PolyCollection  # noqa: E402


def png(fig) -> str:
    """The figure as base64 PNG text; the figure is closed."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def img(data: str, alt: str, wide: bool = False) -> str:
    """An <img> element holding base64 PNG ``data``."""
    return f'<img{" class=wide" if wide else ""} alt="{html.escape(alt)}" src="data:image/png;base64,{data}">'


def projected_shapes(ax, points: np.ndarray, triangles: np.ndarray, shapes: list[tuple], axes=(0, 2)) -> None:
    """Draw deformed surfaces projected on the plane of two coordinate ``axes`` (0 x, 1 y, 2 z).

    points (N, 3) float64 m, rest positions; triangles (B, 3) int, the boundary. Each shape is
    (u (N, 3) m, label, style, colour), style "solid" (faces painted back to front along the dropped
    axis) or "wire" (the triangles' edges). Coordinates are plotted in mm.
    """
    depth_axis = ({0, 1, 2} - set(axes)).pop()
    for u, label, style, colour in shapes:
        x = (points + u) * 1e3
        tri = x[triangles][:, :, list(axes)]
        if style == "solid":
            order = np.argsort(x[triangles][:, :, depth_axis].mean(axis=1))
            ax.add_collection(
                PolyCollection(tri[order], facecolors=colour, edgecolors="k", linewidths=0.1, alpha=0.9, label=label)
            )
        else:
            segs = np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]])
            ax.add_collection(LineCollection(segs, colors=colour, linewidths=0.3, label=label))
    ax.autoscale()
    ax.set_aspect("equal")
    ax.set_xlabel(f"{'xyz'[axes[0]]} (mm)")
    ax.set_ylabel(f"{'xyz'[axes[1]]} (mm)")


def legend_beside(ax) -> None:
    """The legend to the right of the axes, where it hides no data."""
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0.0)
