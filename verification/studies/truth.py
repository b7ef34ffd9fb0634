"""A truth sharp enough for the question (docs/architecture.md section 9): the advisor's reference,
refined until its bar leaves room for a verdict at the tolerance asked, within a budget, or said to be
too coarse, with what a sharper one would take."""

from __future__ import annotations

from verification.progress import log
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.scene import Scene
from verification.studies.proposal import refined_times

#: A truth sharp enough for the question: the reference's bar at most this share of the tolerance. A
#: candidate's true error lies within its measured one plus or minus the bar (``frame.judgement``), so
#: with a bar of 0.3 tol every candidate measured below 0.7 tol qualifies and every one above 1.3 tol
#: fails; only those in between are undecided. With SOFA's liver at 5% (a bar of 2.5%) every error
#: measured between 2.5% and 7.5% is undecided, and only one below 2.5% can qualify.
SHARP = 0.3
#: The refinements the advisor may add to its reference (each multiplies the reference's elements by 8)
#: to make it sharp (SHARP), and the longest the sharper reference may take to solve, s, predicted from
#: the one solved (``reference_cost``). Past either, the advice says it cannot decide the undecided
#: candidates and what a sharper truth would take.
TIGHTEN_LEVELS = 1
TIGHTEN_BUDGET_S = 120.0
#: How a reference's solve time grows with its dofs (``reference_cost``).
GROWTH = 2.0
#: P3's dofs over P2's on one mesh (3.01 on the unit cube's, 3.08 on the cantilever's refined once).
P3_DOFS = 3.1


def reference_cost(meta: dict) -> dict | None:
    """What the reference one refinement finer (``refine`` + 1, its estimate included) would cost,
    predicted from a solved one's ``meta`` (its levels' dofs and wall times): dofs 8 times the finest
    level's, and a solve time growing as dofs^2, the work of a sparse direct factorisation in 3D (nested
    dissection). Small solves grow slower (SOFA's liver's P2 levels, 8 808 -> 58 605 dofs, 0.4 -> 4.5 s:
    dofs^1.28), but a fit there promised the next level (424 503 dofs) in 78 s, and one factorisation of
    it took 25 s, its Newton solve minutes: the prediction is the budget's guard, so it takes the
    asymptotic growth. The finer reference solves the finest level again and the next. None when the
    meta says no levels' costs (a cached reference of an older version)."""
    solves = [x for x in meta.get("solves") or [] if x.get("n_dofs") and x.get("wall_s")]
    if not solves:
        return None
    if meta.get("estimator") == "p3":  # P2 and P3 on the mesh refined once more: both solves, 8 times the dofs
        dofs, wall = sum(x["n_dofs"] for x in solves), sum(x["wall_s"] for x in solves)
        return {"n_dofs": 8 * dofs, "seconds": wall * 8.0**GROWTH, "exponent": GROWTH}
    last = solves[-1]
    return {"n_dofs": 8 * last["n_dofs"], "seconds": last["wall_s"] * (1.0 + 8.0**GROWTH), "exponent": GROWTH}


def p3_cost(meta: dict) -> dict | None:
    """What the same reference with the ``p3`` estimate would cost (``reference.driver``): the returned P2
    level solved again and P3 on its mesh (P3_DOFS times its dofs, its time growing as dofs^GROWTH).
    None for a dynamic reference (the estimate is static), one that has it already, or no costs."""
    solves = [x for x in meta.get("solves") or [] if x.get("n_dofs") and x.get("wall_s")]
    if not solves or meta.get("mode") == "dynamic" or meta.get("estimator") != "difference" or meta.get("degree") != 2:
        return None
    last = solves[-1]
    return {"n_dofs": round(P3_DOFS * last["n_dofs"]), "seconds": last["wall_s"] * (1.0 + P3_DOFS**GROWTH)}


def _bars(meta: dict, needs: list[tuple[str, str, float]]) -> list[tuple[str, float | None, float]]:
    """Each bar the question needs, as (what it is on, its value or None, the tolerance it serves)."""
    return [(name, meta.get(key), t) for name, key, t in needs]


def _blocking(bars: list[tuple[str, float | None, float]]) -> list[tuple[str, float | None, float]]:
    """The bars that leave the question undecidable: unknown, or over SHARP of their tolerance."""
    return [b for b in bars if b[1] is None or b[1] > SHARP * b[2]]


def _why(bars: list, over: list, tightened: int, p3: bool, nxt: dict | None) -> str:
    """What the truth says of itself: each bar within its share of the tolerance and how it was made so,
    or each that blocks (unknown, or over) and what a sharper truth would take."""
    more = f" (refined {refined_times(tightened)} more for it)" if tightened else ""
    more += " (checked against P3 on its mesh)" if p3 else ""
    if not over:
        shown = (f"the reference's bar on {n} {b:.3g} is within {SHARP:g} of its tolerance {t:g}" for n, b, t in bars)
        return "; ".join(shown) + more
    parts = [
        f"the reference's bar on {n} is unknown (it has no error estimate)"
        if b is None
        else f"the reference's bar on {n} {b:.3g} is over {SHARP:g} of its tolerance {t:g}"
        + (f" even refined {refined_times(tightened)} more" if tightened else "")
        + (" and checked against P3" if p3 else "")
        for n, b, t in over
    ]
    why = "; ".join(parts)
    if nxt is not None:
        why += (
            f"; a sharper one (P2 refined once more, {nxt['n_dofs']} dofs) is predicted to take {nxt['seconds']:.0f} s"
        )
        why += (
            f", over the advisor's {TIGHTEN_BUDGET_S:.0f} s"
            if nxt["seconds"] > TIGHTEN_BUDGET_S
            else f"; the advisor refines its truth {refined_times(TIGHTEN_LEVELS)} at most"
        )
    return why + ": candidates whose interval contains the tolerance are undecided"


def sharp_reference(scene: Scene, tol: float, metric: str, haptic: dict | None = None) -> tuple[dict, dict]:
    """The reference the advice judges with (``reference_result`` options) and what it says of itself:
    REFERENCE_DEFAULTS, made sharper while a bar the question needs is over SHARP of its tolerance: first
    its bar checked against P3 on the same mesh (``estimate = "p3"``, static scenes) where that is
    predicted within TIGHTEN_BUDGET_S (``p3_cost``), then refined by up to TIGHTEN_LEVELS while the finer
    one is predicted within it (``reference_cost``). The question needs the bar on ``metric`` against
    ``tol`` and, with a haptic loop (``haptic``: {"rate", "force_tol"}), the bar on the tool force against
    ``force_tol``: a force tolerance under an untightened force bar could never be met. A bar the
    reference does not have is unknown, and refining does not make one: the truth is then not sharp, and
    ``why`` names it.

    Returns (options, {"bar": the bar on ``metric``, "force_bar": on the tool force (None without
    ``haptic``), "refine", "sharp", "tightened", "estimate": "p3" where it was checked against P3,
    "next": the cost of one more refinement or None, "blocking": the names of the bars that stay over,
    "why"})."""
    opts = dict(REFERENCE_DEFAULTS)
    shape_key = "ref_reaction_err_estimate" if metric == "reaction_rel_err" else "ref_err_estimate"
    needs = [(metric, shape_key, tol)]
    if haptic:
        needs.append(("the tool force", "ref_reaction_err_estimate", haptic["force_tol"]))
    ref = reference_result(scene, **opts)
    bars, tightened, nxt = _bars(ref.meta, needs), 0, None
    while (over := _blocking(bars)) and all(b[1] is not None for b in over):
        shown = ", ".join(f"its bar on {n} {b:.3g} is over {SHARP:g} x {t:g}" for n, b, t in over)
        sharper = p3_cost(ref.meta)
        if sharper is not None and sharper["seconds"] <= TIGHTEN_BUDGET_S:
            # first the bar made sharp on the same mesh (1.1 to 2.2 times the error, where the difference
            # of two refinements is 1.7 to 9.3: docs/effectivity.md), before eight times the elements
            opts = {**opts, "estimate": "p3"}
            log(
                f"advise {scene.name}: {shown}; checking it against P3 on its mesh ({sharper['n_dofs']} dofs, "
                f"about {sharper['seconds']:.0f} s)"
            )
            ref = reference_result(scene, **opts)
            bars = _bars(ref.meta, needs)
            continue
        nxt = reference_cost(ref.meta)
        if tightened >= TIGHTEN_LEVELS or nxt is None or nxt["seconds"] > TIGHTEN_BUDGET_S:
            break
        opts = {**opts, "refine": opts["refine"] + 1}
        log(
            f"advise {scene.name}: {shown}; solving it refined {refined_times(opts['refine'])} more "
            f"({nxt['n_dofs']} dofs, about {nxt['seconds']:.0f} s)"
        )
        ref, tightened, nxt = reference_result(scene, **opts), tightened + 1, None
        bars = _bars(ref.meta, needs)
    over = _blocking(bars)
    why = _why(bars, over, tightened, opts.get("estimate") == "p3", nxt)
    return opts, {
        "bar": bars[0][1],
        "force_bar": bars[1][1] if haptic else None,
        "refine": opts["refine"],
        "sharp": not over,
        "tightened": tightened,
        "estimate": opts.get("estimate"),
        "next": nxt,
        "blocking": [n for n, _, _ in over],
        "why": why,
    }
