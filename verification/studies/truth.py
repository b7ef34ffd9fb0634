"""A truth sharp enough for the question (docs/verification.md): the advisor's reference, made
as sharp as its undecided candidates need (adapted where its error lives on a static scene; on a dynamic
one its bar read by P3 and dt / 2 on the mesh it returns, then refined once more) within a budget, or said
to be too coarse, with how far it came and why."""

from __future__ import annotations

from reference.errors import ReferenceSolveError
from verification.progress import log
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.scene import Scene, point_held
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
#: A static truth is made sharp where its error lives (``reference.adaptive``): the longest it may take,
#: s, and the most levels. The adapted levels on the cantilever each added 1.4 to 2.6 times the cells and
#: cut the bar 1.5 to 3 times (0.018 to 0.00064 in 60 s, 112 000 P2 dofs, 2 cores).
ADAPT_BUDGET_S = 180.0
ADAPT_LEVELS = 8
#: The share of a straddling candidate's distance to the tolerance that the truth's bar is asked to
#: reach (``needed_bar``): its error is measured again against the sharper truth and moves with it.
MARGIN = 0.8


def _dynamic_p3(scene, opts: dict, ref, needs: list, bars: list, budget_s: float) -> tuple:
    """A dynamic truth's bar read again by P3 and dt / 2 on the mesh it returns (``reference.driver``'s
    ``p3``: the same trajectory, its bar 2.3 to 2.6 times its error on the dynamic beam where the
    default's was 4.4 to 5.7, docs/effectivity.md) when that is predicted within ``budget_s``. Kept where it lowers every bar
    that blocks; else, or where the P3 run finds no answer (Newton on an inverted element), the default
    stays. Returns (options, reference, bars, how)."""
    cost = p3_cost(ref.meta)
    if cost is None or cost["seconds"] > budget_s:
        return opts, ref, bars, ""
    shown = ", ".join(f"its bar on {n} {b:.3g} is over {w:.3g}" for n, b, _, w in _blocking(bars))
    log(
        f"advise {scene.name}: {shown}; reading it again by P3 and dt / 2 on its own mesh "
        f"({cost['n_dofs']} P3 dofs, about {cost['seconds']:.0f} s)"
    )
    p3_opts = {**opts, "estimate": "p3"}
    try:
        p3_ref = reference_result(scene, **p3_opts)
    except ReferenceSolveError as exc:  # the check failed where the truth it checks converged: keep the default
        log(f"advise {scene.name}: the P3 check found no answer ({' '.join(str(exc).split())}); keeping its bar")
        return opts, ref, bars, ""
    p3_bars = _bars(p3_ref.meta, needs)
    lower = all(
        b is not None and b <= a for (_, a, _, _), (_, b, _, _) in zip(bars, p3_bars, strict=True) if a is not None
    )
    if not lower:
        return opts, ref, bars, ""
    return p3_opts, p3_ref, p3_bars, " (its bar read by P3 and dt / 2 on its own mesh)"


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


#: P3's dofs over P2's on the same tetrahedral mesh (measured 3.08 on the cantilever, 33 405 / 10 839).
P3_DOFS = 3.1


def p3_cost(meta: dict) -> dict | None:
    """What a dynamic reference's ``p3`` bar would cost, predicted from its default solve's ``meta``
    (solves: u_R at dt, u_R+1 at dt, u_R at dt / 2): the returned run u_R+1 again, P3 beside it (P3_DOFS
    times its dofs, at GROWTH) and P2 there at dt / 2 (twice the steps). None without those costs."""
    solves = [x for x in meta.get("solves") or [] if x.get("n_dofs") and x.get("wall_s")]
    if len(solves) != 3 or meta.get("estimator") == "p3":
        return None
    n, wall = solves[1]["n_dofs"], solves[1]["wall_s"]
    return {"n_dofs": int(P3_DOFS * n), "seconds": wall * (1.0 + P3_DOFS**GROWTH + 2.0), "exponent": GROWTH}


def _bars(meta: dict, needs: list[tuple]) -> list[tuple[str, float | None, float, float]]:
    """Each bar the question needs, as (what it is on, its value or None, the tolerance it serves, the
    value it is asked to reach)."""
    return [(name, meta.get(key), t, want) for name, key, t, want in needs]


def _blocking(bars: list[tuple]) -> list[tuple]:
    """The bars that leave the question undecidable: unknown, or over what they are asked to reach."""
    return [b for b in bars if b[1] is None or b[1] > b[3]]


def _asked(t: float, want: float) -> str:
    """What a bar serving tolerance ``t`` was asked to reach, ``want``: "SHARP of its tolerance t", or "the
    w the undecided candidates need" where they asked for less."""
    if want >= SHARP * t:
        return f"{SHARP:g} of its tolerance {t:g}"
    return f"the {want:.3g} the undecided candidates need (tolerance {t:g})"


def _why(bars: list, over: list, how: str, nxt: dict | None, budget_s: float = TIGHTEN_BUDGET_S) -> str:
    """What the truth says of itself: each bar within what the question asks and how it was made so
    (``how``), or each that blocks (unknown, or over) and what a sharper truth would take."""
    if not over:
        shown = (f"the reference's bar on {n} {b:.3g} is within {_asked(t, w)}" for n, b, t, w in bars)
        return "; ".join(shown) + how
    parts = [
        f"the reference's bar on {n} is unknown (it has no error estimate)"
        if b is None
        else f"the reference's bar on {n} {b:.3g} is over {_asked(t, w)}" + how
        for n, b, t, w in over
    ]
    why = "; ".join(parts)
    if nxt is not None:
        why += (
            f"; a sharper one (P2 refined once more, {nxt['n_dofs']} dofs) is predicted to take {nxt['seconds']:.0f} s"
        )
        why += (
            f", over the advisor's {budget_s:.0f} s (--truth-budget)"
            if nxt["seconds"] > budget_s
            else f"; the advisor refines its truth {refined_times(TIGHTEN_LEVELS)} at most"
        )
    return why + ": candidates whose interval contains the tolerance are undecided"


def _adapted(scene: Scene, opts: dict, ref, needs: list, budget_s: float) -> tuple[dict, object, str]:
    """A static P2 truth adapted where its error lives until each needed bar is within what it is asked
    (``reference.adaptive``, within ``budget_s`` s): its options, the reference and how it was made, where
    its bars are known and the one on the metric is under the reference's ``ref`` had; else ``opts``,
    ``ref`` and why the adapted one was not taken."""
    adapt = {"target": needs[0][3], "budget_s": budget_s, "max_levels": ADAPT_LEVELS}
    if len(needs) > 1:
        adapt["force_target"] = needs[1][3]
    log(
        f"advise {scene.name}: adapting the reference where its error lives until its bar is at most "
        f"{adapt['target']:.3g} (at most {budget_s:.0f} s)"
    )
    sharper_opts = {**opts, "estimate": "adaptive", "adapt": adapt}
    sharper = reference_result(scene, **sharper_opts)
    info = sharper.meta.get("adaptive") or {}
    levels = info.get("levels") or [{}]
    bars, old = _bars(sharper.meta, needs), _bars(ref.meta, needs)
    if all(b[1] is not None for b in bars) and bars[0][1] <= old[0][1]:
        how = (
            f" (adapted {refined_times(info.get('returned', 0))} where its error lives: "
            f"{levels[-1].get('n_dofs')} P2 dofs, checked by P3 on the same mesh)"
        )
        return sharper_opts, sharper, how
    bar = bars[0][1]
    shown = "unknown" if bar is None else f"{bar:.3g}"
    return opts, ref, f" (adapted where its error lives, its bar was {shown}: {info.get('stop')})"


def sharp_reference(
    scene: Scene,
    tol: float,
    metric: str,
    haptic: dict | None = None,
    target: float | None = None,
    tighten: bool = True,
    budget_s: float | None = None,
) -> tuple[dict, dict]:
    """The reference the advice judges with (``reference_result`` options) and what it says of itself:
    REFERENCE_DEFAULTS, made sharper while a bar the question needs is over what it is asked to reach:
    the bar on ``metric`` ``target`` (default SHARP ``tol``; the advisor asks for what its undecided
    candidates need, ``needed_bar``) and, with a haptic loop (``haptic``: {"rate", "force_tol"}), the bar
    on the tool force SHARP ``force_tol``: a force tolerance under an untightened force bar could never
    be met. A static P2 truth is adapted where its error lives (``_adapted``); a dynamic one has its bar
    read by P3 and dt / 2 (``_dynamic_p3``), then is refined by up to TIGHTEN_LEVELS, each while
    predicted within TIGHTEN_BUDGET_S (``p3_cost``, ``reference_cost``).
    A scene held or pressed at points or along edges (``scene.point_held``) is never made sharper: its
    truth has no limit, and the advice says so instead of spending its budget on it.
    A bar the reference does not have is unknown, and refining does not make one: the truth is then not
    sharp, and ``why`` names it. ``tighten`` False: REFERENCE_DEFAULTS as it is, and what it says of itself.
    ``budget_s``: the seconds a sharper truth may take (``advise --truth-budget``; default ADAPT_BUDGET_S
    adapting, TIGHTEN_BUDGET_S refining).

    Returns (options, {"bar": the bar on ``metric``, "force_bar": on the tool force (None without
    ``haptic``), "refine", "sharp", "tightened": uniform refinements added, "estimate": "adaptive" where
    it was adapted, "next": the cost of one more refinement or None, "blocking": the names of the bars
    that stay over, "why"})."""
    opts = dict(REFERENCE_DEFAULTS)
    shape_key = "ref_reaction_err_estimate" if metric == "reaction_rel_err" else "ref_err_estimate"
    needs = [(metric, shape_key, tol, SHARP * tol if target is None else min(target, SHARP * tol))]
    if haptic:
        needs.append(("the tool force", "ref_reaction_err_estimate", haptic["force_tol"], SHARP * haptic["force_tol"]))
    ref = reference_result(scene, **opts)
    bars, tightened, nxt, how = _bars(ref.meta, needs), 0, None, ""
    static = scene.time.mode != "dynamic" and opts["degree"] == 2
    held_at_points = point_held(scene)
    if held_at_points:  # no truth converges there: refining only spends the budget to show it
        tighten, how = False, f" (not made sharper: {held_at_points[0]})"
    if tighten and static and (over := _blocking(bars)) and all(b[1] is not None for b in over):
        opts, ref, how = _adapted(scene, opts, ref, needs, ADAPT_BUDGET_S if budget_s is None else budget_s)
        bars = _bars(ref.meta, needs)
    refining = TIGHTEN_BUDGET_S if budget_s is None else budget_s
    if (
        tighten
        and not static
        and opts["degree"] == 2
        and (over := _blocking(bars))
        and all(b[1] is not None for b in over)
    ):
        opts, ref, bars, how = _dynamic_p3(scene, opts, ref, needs, bars, refining)
    while tighten and not static and (over := _blocking(bars)) and all(b[1] is not None for b in over):
        nxt = reference_cost(ref.meta)
        if tightened >= TIGHTEN_LEVELS or nxt is None or nxt["seconds"] > refining:
            break
        shown = ", ".join(f"its bar on {n} {b:.3g} is over {w:.3g}" for n, b, _, w in over)
        opts = {**opts, "refine": opts["refine"] + 1}
        log(
            f"advise {scene.name}: {shown}; solving it refined {refined_times(opts['refine'])} more "
            f"({nxt['n_dofs']} dofs, about {nxt['seconds']:.0f} s)"
        )
        ref, tightened, nxt = reference_result(scene, **opts), tightened + 1, None
        bars = _bars(ref.meta, needs)
        how = f" (refined {refined_times(tightened)} more for it)"
    over = _blocking(bars)
    return opts, {
        "bar": bars[0][1],
        "force_bar": bars[1][1] if haptic else None,
        "refine": opts["refine"],
        "sharp": not over,
        "tightened": tightened,
        "estimate": opts.get("estimate"),
        "next": nxt,
        "blocking": [b[0] for b in over],
        "why": _why(bars, over, how, nxt, refining),
    }
