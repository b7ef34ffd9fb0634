"""A run's frame budget (docs/architecture.md section 9): whether a simulator stepping the run's model
holds a frame rate on this machine with a share of each frame, what a frame costs, and what a refined
mesh would cost (``predict``); the verdict on a run against a tolerance at a rate; runs that agree
merged into one candidate."""

from __future__ import annotations

import math
import os
from pathlib import Path

from verification.runs.row import Row

#: The share of a frame a candidate may use: the rest is margin for timing noise between this run and
#: the simulator's (the spread of repeated timings on a loaded 2-core machine reaches 10-20%).
FRAME_SHARE = 0.8


#: Two runs of one model whose errors differ by less than this, relatively, are the same answer.
SAME_ANSWER = 1e-6


def frame_budget(row: Row, rate: float, dynamic: bool, share: float = FRAME_SHARE) -> dict:
    """Whether a run (a ``compare`` row) holds ``rate`` frames per second on this machine, using at
    most ``share`` of each frame (FRAME_SHARE for every command, so that ``compare --rate`` and
    ``advise`` decide alike), and what reaching its answer costs.

    - A quasi-static model (precomputed, condensed) updates once per frame: the update must fit; so
      does a plug-in engine's step, which it times itself (a run without a time does not hold).
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
    if row.dt is None:  # quasi-static: one update per frame
        holds = step_us <= budget_us
        out.update(
            steps_per_frame=1,
            work_us=step_us,
            time_to_answer_s=None if dynamic else step_us * 1e-6,
            holds=holds,
            why=f"one update of {step_us:.3g} us per frame of {frame_us:.3g} us",
        )
        return out
    dt_us = row.dt * 1e6
    if dynamic:
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
    settle = row.settle_steps or 1
    if n < 1:
        out.update(
            steps_per_frame=0,
            work_us=step_us,
            time_to_answer_s=settle * step_us * 1e-6,
            holds=False,
            why=f"one step takes {step_us:.3g} us, over {share:.0%} of a {frame_us:.3g} us frame",
        )
        return out
    out.update(
        steps_per_frame=n,
        work_us=n * step_us,
        time_to_answer_s=settle * step_us * 1e-6,
        holds=True,
        why=f"{n} step{'s' if n > 1 else ''} of {step_us:.3g} us per frame; settles in {settle} steps, "
        f"{settle * step_us * 1e-6:.3g} s ({math.ceil(settle / n)} frames)",
    )
    return out


def cost(row: Row, dynamic: bool) -> float:
    """What the advisor minimises: on a static scene the wall time to the answer, on a dynamic one the
    work per frame (the share of the machine a candidate takes)."""
    b = row.frame
    return b["work_us"] if dynamic else b["time_to_answer_s"]


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


def verdict(r: Row, metric: str, tol: float) -> tuple[bool, str]:
    """Whether a candidate qualifies, and a line saying why or why not."""
    if r.status == "diverged":
        ratio = f", {r.dt / r.dt_crit:.2f} x its critical step" if r.dt_crit else ""
        return False, f"{label(r)}: unstable, diverged at step {r.step}{ratio}"
    if r.status != "ok":
        return False, f"{label(r)}: {r.status} ({r.message or ''})"
    value = getattr(r, metric)
    bad = []
    if value is None or value > tol:
        b = r.error_budget or {}
        parts = ", ".join(f"{k} {b[k]:.3g}" for k in ("mesh", "model", "time") if b.get(k) is not None)
        bad.append(f"{metric} {value:.3g} > {tol:g}" + (f" ({parts})" if parts else ""))
    if not r.frame["holds"]:
        bad.append(r.frame["why"])
    without = "".join(f"; ran without {term}" for term in r.unrepresented or [])
    if bad:
        return False, f"{label(r)}: {'; '.join(bad)}{without}"
    return True, f"{label(r)}: {metric} {value:.3g} <= {tol:g}; {r.frame['why']}{without}"


def memory_bytes(model: str, n_vertices: int, n_surface: int) -> float:
    """What a model's dense precomputation takes, in bytes: precomputed's responses (free dofs x
    surface dofs) and condensed's Schur complement with its Cholesky factor (retained squared, twice);
    both solve their right-hand sides a block at a time. Time-stepping models: sparse, negligible."""
    n, s = 3.0 * n_vertices, 3.0 * n_surface  # dofs, surface dofs
    if model == "precomputed":
        return 8 * n * s
    if model == "condensed":
        return 8 * 2 * s * s
    return 0.0


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
            settle_steps=(r.settle_steps or 1) * (2**levels if explicit else 1),
        )
    return frame_budget(row, rate, dynamic, share)
