"""A run's frame budget (docs/verification.md): whether a simulator stepping the run's model
holds a frame rate on this machine with a share of each frame, what a frame costs, and what a refined
mesh would cost (``predict``); the verdict on a run against a tolerance at a rate; runs that agree
merged into one candidate."""

from __future__ import annotations

import math
import os
from pathlib import Path

from verification.metrics import error_interval
from verification.runs.row import Row

#: The share of a frame a candidate may use: the rest is margin for timing noise between this run and
#: the simulator's (the spread of repeated timings on a loaded 2-core machine reaches 10-20%).
FRAME_SHARE = 0.8


#: Two runs of one model whose errors differ by less than this, relatively, are the same answer.
SAME_ANSWER = 1e-6


def frame_budget(row: Row, rate: float, dynamic: bool, share: float = FRAME_SHARE, haptic: dict | None = None) -> dict:
    """``visual_budget``, and with ``haptic`` ({"rate": Hz, "force_tol": the tool force's tolerance}) the
    same budget at the haptic rate under "haptic" (with that rate and tolerance): a simulator that runs a
    haptic loop beside its display steps the model at the haptic rate, and ``judgement`` then judges the
    tool force there too."""
    out = visual_budget(row, rate, dynamic, share)
    if haptic:
        out["haptic"] = {**visual_budget(row, haptic["rate"], dynamic, share), **haptic}
    return out


def visual_budget(row: Row, rate: float, dynamic: bool, share: float = FRAME_SHARE) -> dict:
    """Whether a run (a ``compare`` row) holds ``rate`` frames per second on this machine, using at
    most ``share`` of each frame (FRAME_SHARE for every command, so that ``compare --rate`` and
    ``advise`` decide alike), and what reaching its answer costs.

    - A quasi-static model (precomputed, condensed) updates once per frame: the update must fit; so
      does a plug-in engine's step, which it times itself (a run without a time does not hold), unless
      its static answer says how many steps it took: those are costed as a settling's, below.
    - On a dynamic scene a time-stepping model must keep up with the wall clock: a frame of 1/rate s
      advances it by 1/rate s, ceil(1 / (rate dt)) steps, which must fit in the frame (a real-time
      factor of at least one, rounding included), and dt must not exceed the frame, or the state
      changes less often than the display.
    - On a static scene a frame runs as many steps as fit (at least one must), and the answer is
      reached after the run's ``settle_steps``: ``time_to_answer_s`` is the wall time to settle at that
      pace, what a user waits after a load change. Quasi-static models answer within their update.

    Returns holds (bool), steps_per_frame, work_us (of one frame), frame_us, time_to_answer_s (None
    on a dynamic scene, where the answer is the trajectory itself) and why (one line).
    """
    frame_us = 1e6 / rate
    budget_us = share * frame_us
    step_us = row.step_us
    out = {"frame_us": frame_us, "share": share, "step_us": step_us}
    if step_us is None:  # an engine in its own process that reports no time: nothing says it holds
        out.update(steps_per_frame=None, work_us=None, time_to_answer_s=None, holds=False)
        out["why"] = "the engine reports no step time"
        return out
    # quasi-static: one update per frame; a static answer of many steps without a time step (an engine
    # command's iterations) is costed by its steps, as a time-stepping model's settling is
    if row.dt is None and (dynamic or (row.settle_steps or 1) <= 1):
        holds = step_us <= budget_us
        out.update(
            steps_per_frame=1,
            work_us=step_us,
            time_to_answer_s=None if dynamic else step_us * 1e-6,
            holds=holds,
            why=f"one update of {step_us:.3g} us per frame of {frame_us:.3g} us",
        )
        return out
    if dynamic:
        dt_us = row.dt * 1e6
        n = max(1, math.ceil(frame_us / dt_us * (1.0 - 1e-12)))
        work = n * step_us
        # a step of one frame, printed to 6 digits in a command and read back, is still one frame
        holds = work <= budget_us and dt_us <= frame_us * (1.0 + 1e-6)
        why = f"{n} steps of {step_us:.3g} us keep up with the clock in {work:.3g} us of a {frame_us:.3g} us frame"
        if dt_us > frame_us * (1.0 + 1e-6):
            why = f"dt = {dt_us:.3g} us is longer than a frame of {frame_us:.3g} us: the state changes at {1e6 / dt_us:.0f} Hz"
        elif work > budget_us:
            why = (
                f"{n} steps of {step_us:.3g} us per simulated frame take {work:.3g} us, over "
                f"{share:.0%} of a {frame_us:.3g} us frame (real-time factor {frame_us / work:.2f})"
            )
        out.update(steps_per_frame=n, work_us=work, time_to_answer_s=None, holds=holds, why=why)
        return out
    n = int(budget_us // step_us)
    settle = row.settle_steps  # None: the run did not say how many steps it settled in
    answer_s = None if settle is None else settle * step_us * 1e-6
    if n < 1:
        out.update(
            steps_per_frame=0,
            work_us=step_us,
            time_to_answer_s=answer_s,
            holds=False,
            why=f"one step takes {step_us:.3g} us, over {share:.0%} of a {frame_us:.3g} us frame",
        )
        return out
    settles = (
        "its settling steps are unknown, so is its time to the answer"
        if settle is None
        else f"settles in {settle} steps, {answer_s:.3g} s ({math.ceil(settle / n)} frames)"
    )
    out.update(
        steps_per_frame=n,
        work_us=n * step_us,
        time_to_answer_s=answer_s,
        holds=True,
        why=f"{n} step{'s' if n > 1 else ''} of {step_us:.3g} us per frame; {settles}",
    )
    return out


def cost(row: Row, dynamic: bool) -> float:
    """What the advisor minimises: on a static scene the wall time to the answer, on a dynamic one the
    work per frame (the share of the machine a candidate takes). An unknown cost ranks after every known
    one (infinite), never as free."""
    b = row.frame
    value = b["work_us"] if dynamic else b["time_to_answer_s"]
    return math.inf if value is None else value


def merge_same_answers(rows: list[Row], metric: str, dynamic: bool) -> list[Row]:
    """One row per model and integrator among runs whose ``metric`` values agree within SAME_ANSWER
    (relative): a step that changes nothing is not a choice. The row kept is the cheapest (``cost``);
    it lists the steps merged into it (``merged_dt``). Rows that diverged are kept apart."""
    groups: list[list[Row]] = []
    for r in rows:
        if r.status != "ok":
            groups.append([r])
            continue
        for g in groups:
            h = g[0]
            if (
                h.status == "ok"
                and (h.model, h.integrator) == (r.model, r.integrator)
                and abs(getattr(h, metric) - getattr(r, metric))
                <= SAME_ANSWER * max(abs(getattr(h, metric)), abs(getattr(r, metric)), 1e-300)
            ):
                g.append(r)
                break
        else:
            groups.append([r])
    out = []
    for g in groups:
        best = min(g, key=lambda r: cost(r, dynamic)) if g[0].ok else g[0]
        out.append(best.replace(merged_dt=tuple(sorted(r.dt for r in g if r.dt is not None))))
    return out


def label(r: Row) -> str:
    if r.dt is None:
        return f"{r.model} ({r.integrator})"
    return f"{r.model} ({r.integrator}, dt {r.dt:.3g} s)"


def reference_bar(r: Row, metric: str) -> float | None:
    """The reference's bar on ``metric`` (relative, as the metric): its estimate on the tool force for
    reaction_rel_err, on the displacements for the others (over every vertex, surface_rel_l2's too);
    None where the reference is unverified."""
    if metric == "reaction_rel_err":
        return (r.reference or {}).get("ref_reaction_err_estimate")
    return r.ref_err_estimate


def row_interval(r: Row, metric: str) -> tuple[float, float] | None:
    """``error_interval`` of a row's ``metric`` with the reference's bar on it (``reference_bar``)."""
    return error_interval(getattr(r, metric), reference_bar(r, metric))


def true_range(value: float | None, bar: float | None, fmt: str = ".3g") -> str:
    """The interval ``error_interval`` leaves, as a user reads it ("true 0.109 to 0.263"); "" without."""
    span = error_interval(value, bar)
    return "" if span is None else f"true {span[0]:{fmt}} to {span[1]:{fmt}}"


def with_bar(value: float | None, bar: float | None, fmt: str = ".3g") -> str:
    """An error as a user reads it: the value and, where the reference has a bar, the interval the true
    error lies in ("0.186 (true 0.109 to 0.263)")."""
    if value is None:
        return "-"
    span = true_range(value, bar, fmt)
    return format(value, fmt) + (f" ({span})" if span else "")


def unknown_inputs(value: float | None, bar: float | None, metric: str) -> str:
    """What a verdict on ``metric`` lacks, in words ("the reference's bar on reaction_rel_err is unknown"),
    or "" when it has both numbers: a missing number is never read as zero."""
    missing = [f"{metric} was not measured"] if value is None else []
    missing += [f"the reference's bar on {metric} is unknown"] if bar is None else []
    return " and ".join(missing)


#: What a verdict on an error can be: within the tolerance whatever the reference's own error, over it
#: whatever, or neither (the tolerance lies inside the interval the reference's bar leaves).
QUALIFIES, FAILS, UNDECIDED = "qualifies", "fails", "undecided"


def _judged(r: Row, metric: str, tol: float) -> tuple[str, str]:
    """A candidate's verdict on one error and the frame it has, and a line saying why.

    The rule: its true error is within the measured one plus or minus the reference's bar
    (``error_interval``); it qualifies only when the whole interval is within ``tol`` (and its frame
    holds), fails when the interval is above it (or its frame does not hold), and is undecided when
    ``tol`` lies inside: the truth is not sharp enough to say. A missing number decides nothing: with
    no bar (an unverified reference) or no measured error, a candidate that does not fail on its frame
    is undecided, and the line names what is missing."""
    if r.status == "diverged":
        ratio = f", {r.dt / r.dt_crit:.2f} x its critical step" if r.dt_crit else ""
        return FAILS, f"{label(r)}: unstable, diverged at step {r.step}{ratio}"
    if r.status != "ok":
        return FAILS, f"{label(r)}: {r.status} ({r.message or ''})"
    value, bar = getattr(r, metric), reference_bar(r, metric)
    missing = unknown_inputs(value, bar, metric)
    lo, hi = error_interval(value, bar) or (-math.inf, math.inf)
    shown = f"{metric} {with_bar(value, bar)}"
    without = "".join(f"; ran without {term}" for term in r.unrepresented or [])
    bad = []
    if lo > tol:
        b = r.error_budget or {}
        parts = ", ".join(f"{k} {b[k]:.3g}" for k in ("mesh", "model", "time") if b.get(k) is not None)
        bad.append(f"{shown} > {tol:g}" + (f" ({parts})" if parts else ""))
    if not r.frame["holds"]:
        bad.append(r.frame["why"])
    if bad:
        return FAILS, f"{label(r)}: {'; '.join(bad)}{without}"
    if missing:
        return UNDECIDED, f"{label(r)}: {shown}: cannot decide, {missing}; {r.frame['why']}{without}"
    if hi > tol:
        return UNDECIDED, (
            f"{label(r)}: {shown}: the tolerance {tol:g} lies within the reference's bar {bar:.3g}, "
            f"undecided; {r.frame['why']}{without}"
        )
    return QUALIFIES, f"{label(r)}: {shown} <= {tol:g}; {r.frame['why']}{without}"


#: The verdicts from the best to the worst: two judged together give the worse.
_ORDER = (QUALIFIES, UNDECIDED, FAILS)


def judgement(r: Row, metric: str, tol: float) -> tuple[str, str]:
    """A candidate's verdict (QUALIFIES, FAILS or UNDECIDED) and a line saying why (``_judged``). Where its
    frame has a haptic budget (``frame_budget`` with ``haptic``), its tool force is judged too, at the
    haptic rate against its own tolerance, and the verdict is the worse of the two: a shape within the
    tolerance never hides a tool force out of it (91% off on a liver whose shape passed)."""
    state, line = _judged(r, metric, tol)
    haptic = (r.frame or {}).get("haptic") if r.status == "ok" else None
    if not haptic:
        return state, line
    at = {k: v for k, v in haptic.items() if k not in ("rate", "force_tol")}
    force, why = _judged(r.replace(frame=at), "reaction_rel_err", haptic["force_tol"])
    why = why.split(": ", 1)[1] if why.startswith(label(r)) else why
    return max(state, force, key=_ORDER.index), f"{line}; haptic loop at {haptic['rate']:g} Hz: {why}"


def verdict(r: Row, metric: str, tol: float) -> tuple[bool, str]:
    """Whether a candidate surely qualifies (``judgement``), and a line saying why or why not."""
    state, line = judgement(r, metric, tol)
    return state == QUALIFIES, line


def memory_bytes(model: str, n_vertices: int, n_surface: int) -> float:
    """What a model's dense precomputation takes, in bytes: its spec's ``memory`` (precomputed's responses,
    dofs x surface dofs; condensed's Schur complement with its Cholesky factor), 0 where that is
    negligible (the time-stepping models: sparse)."""
    from verification.engines import spec_of

    memory = spec_of(model).memory
    return 0.0 if memory is None else memory(3.0 * n_vertices, 3.0 * n_surface)


def available_memory() -> float:
    """Bytes of memory the advisor lets one run take: half of what the system has available."""
    try:
        for line in Path("/proc/meminfo").read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return 0.5 * float(line.split()[1]) * 1024
    except OSError:
        pass
    return 0.5 * os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")


def predict(r: Row, levels: int, dynamic: bool, rate: float, share: float = FRAME_SHARE) -> dict:
    """A level-0 row's frame budget on a mesh refined ``levels`` times: a step costs 8^levels times as
    much (the element loops), and an explicit step is 2^levels times shorter (dt_crit is proportional
    to h), so a static scene settles in 2^levels times the steps and a dynamic frame needs 2^levels
    times the steps. Implicit Euler's step (a sparse solve) is taken to grow like the elements too."""
    grow = 8.0**levels
    row = r.replace(step_us=r.step_us * grow)
    if r.dt is not None:
        explicit = r.integrator != "implicit-euler"
        row = row.replace(
            dt=r.dt / 2.0**levels if explicit else r.dt,
            settle_steps=None if r.settle_steps is None else r.settle_steps * (2**levels if explicit else 1),
        )
    return frame_budget(row, rate, dynamic, share)
