"""What every static reference's levels share: one level's solve (``solve_level``), the relative
difference its bars are made of (``relative``), and the ``p3`` bar's safety factor (``reference.driver``'s
module docstring says why it is 2)."""

from __future__ import annotations

import numpy as np

#: The ``p3`` estimate's safety factor (``reference.driver``; ``reference.adaptive`` uses it at every level).
P3_SAFETY = 2.0


def solve_level(ep, coarse, infos: list, newton: dict, petsc_options) -> dict:
    """One level's static solve: the linear law's one solve, or Newton (from ``coarse``'s solution at
    full load where there is one); a check level gives up sooner than the level it checks, after 10
    times that level's time."""
    if ep.linear:
        return ep.solve(petsc_options=petsc_options)
    if coarse is not None:
        ep.start_from(coarse)
    limit = {} if not infos else {"time_limit": max(120.0, 10.0 * infos[-1]["wall_s"])}
    return ep.solve(**newton, start_at_full_load=coarse is not None, petsc_options=petsc_options, **limit)


def relative(coarse: np.ndarray, fine: np.ndarray) -> float | None:
    """|coarse - fine| / |fine| over every entry (the tools' forces at every output time); None where the
    finer one is zero (a scene without a tool has no force to estimate: 0 / 0)."""
    den = float(np.linalg.norm(fine))
    return float(np.linalg.norm(coarse - fine)) / den if den > 0 else None
