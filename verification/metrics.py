"""The metrics of docs/metrics.md, on displacements at the scene mesh's vertices."""

from __future__ import annotations

import numpy as np

from realtime.geometry import signed_volumes

#: The errors ``compute`` measures, in the order tables print them.
METRICS = ("rel_l2", "surface_rel_l2", "max_err", "reaction_rel_err", "volume_err")


def rel_l2(u: np.ndarray, ref: np.ndarray) -> float:
    """sqrt(sum |u - u*|^2) / sqrt(sum |u*|^2) over all entries of (T, N, 3) or (N, 3) arrays."""
    den = float(np.linalg.norm(ref))
    return float(np.linalg.norm(u - ref)) / den if den > 0 else float(np.linalg.norm(u - ref))


def error_interval(value: float | None, bar: float | None) -> tuple[float, float] | None:
    """Where a true relative error lies given the one measured against the reference, ``value``, and the
    reference's bar, ``bar`` (which bounds the reference's own relative error: reference.driver): by
    the triangle inequality, within value -/+ bar (to first order in the bar: the two are relative to
    norms that differ by at most the bar). None without either: a missing number leaves it unknown."""
    if value is None or bar is None:
        return None
    return max(value - bar, 0.0), value + bar


def volume_err(points: np.ndarray, tets: np.ndarray, u: np.ndarray, ref: np.ndarray) -> float:
    """max over t of |V(t) - V*(t)| / V0, volumes of the scene mesh moved by u and by u* (T, N, 3)."""
    v0 = signed_volumes(points, tets).sum()
    errs = [
        abs(signed_volumes(points + a, tets).sum() - signed_volumes(points + b, tets).sum()) / v0
        for a, b in zip(
            np.atleast_3d(u).reshape(-1, *points.shape), np.atleast_3d(ref).reshape(-1, *points.shape), strict=True
        )
    ]
    return float(max(errs))


def compute(points, tets, surface, u, ref, reaction=None, ref_reaction=None, ref_err_estimate=None) -> dict:
    """All accuracy metrics of a model run against the reference.

    Args:
        points: (N, 3) rest positions, m.  tets: (M, 4).  surface: (S,) surface vertex indices.
        u, ref: (T, N, 3) displacements of the model and the reference, m.
        reaction, ref_reaction: (T, 3) tool forces, N, or None when the scene has no tool.
        ref_err_estimate: the reference's own relative error, or None.

    ``rel_l2_interval`` is where the true rel_l2 lies given that bar (``error_interval``), None without it.
    """
    u = np.asarray(u).reshape(-1, *points.shape)
    ref = np.asarray(ref).reshape(-1, *points.shape)
    out = {
        "rel_l2": rel_l2(u, ref),
        "surface_rel_l2": rel_l2(u[:, surface], ref[:, surface]),
        "max_err": float(np.linalg.norm(u - ref, axis=2).max()),
        "volume_err": volume_err(points, tets, u, ref),
        "reaction_rel_err": None,
        "ref_err_estimate": ref_err_estimate,
    }
    if reaction is not None and ref_reaction is not None and np.linalg.norm(ref_reaction) > 0:
        out["reaction_rel_err"] = float(
            np.linalg.norm(np.asarray(reaction) - ref_reaction) / np.linalg.norm(ref_reaction)
        )
    out["rel_l2_interval"] = error_interval(out["rel_l2"], ref_err_estimate)
    return out
