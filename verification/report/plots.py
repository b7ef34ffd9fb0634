"""The report's figures as embedded PNG (``verification.figures``): error against speed with the Pareto
front, the error budget, deformed shapes, the tool's force over time and convergence plots. Every axis names its quantity and unit; legends sit beside the axes, never over the data."""

from __future__ import annotations

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from verification.figures import legend_beside, png  # noqa: E402
from verification.runs.row import Row  # noqa: E402

#: The markers of the error-against-speed plot's series, in turn.
MARKERS = "os^Dv<>pPXh*"


def plot_error_vs_speed(rows: list[Row], ref_est: float | None, title: str, notes=()) -> str:
    """Log-log rel_l2 against step_us, one series per model (the plug-in engines' beside the built-in
    ones), the Pareto front as a staircase; ``notes``: legend lines for what has no point (a model with
    no answer)."""
    fig, ax = plt.subplots(figsize=(7.2, 4.6))
    ok = [r for r in rows if r.ok and r.step_us is not None]  # timed: a plug-in may report no step time
    colours = plt.get_cmap("tab20").colors
    for k, model in enumerate(sorted({r.model for r in ok})):  # colour and marker: no two series alike
        pts = sorted((r for r in ok if r.model == model), key=lambda r: r.step_us)
        ax.loglog([r.step_us for r in pts], [max(r.rel_l2, 1e-16) for r in pts], MARKERS[k % len(MARKERS)],
                  color=colours[(2 * k) % 20 + (k // 10) % 2], label=model, alpha=0.85)  # fmt: skip
        for r in pts:
            ax.annotate(
                _step_label(r), (r.step_us, max(r.rel_l2, 1e-16)), textcoords="offset points", xytext=(4, 3), fontsize=7
            )
    front = sorted((r for r in ok if r.pareto), key=lambda r: r.step_us)
    if front:
        ax.step(
            [r.step_us for r in front],
            [r.rel_l2 for r in front],
            where="post",
            color="k",
            lw=1,
            label="Pareto front",
        )
    errs = [max(r.rel_l2, 1e-16) for r in ok]
    if ref_est:
        ax.axhline(ref_est, color="grey", ls="--", lw=1, label="reference error estimate")
        lo = min(errs + [ref_est]) / 10
        ax.axhspan(lo, ref_est, color="grey", alpha=0.12, label="within the reference's bar: not told from zero")
        ax.set_ylim(lo, max(errs + [ref_est]) * 3)
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.3g"))
    ax.set_xlabel("median wall time of one step (us)")
    ax.set_ylabel("relative L2 displacement error (fraction)")
    ax.set_title(title + "  (labels: dt / dt_crit; q-s: quasi-static; ms: another engine's step)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    for note in notes:
        ax.plot([], [], " ", label=note)
    legend_beside(ax)
    return png(fig)


def _step_label(r: Row) -> str:
    """A point's label: dt / dt_crit for the built-in models, another engine's step in ms (and its
    iterations, where it has some), "q-s" for a quasi-static update, "own" for a step no one reported."""
    if r.dt_crit:
        return f"{r.dt / r.dt_crit:.2g}"
    if r.integrator == "quasi-static":
        return "q-s"
    if r.dt is None:
        return "own"
    its = (r.engine or {}).get("iterations")
    return f"{r.dt * 1e3:.2g} ms" + (f", {its} it" if its is not None else "")


def plot_engines(out: dict) -> str:
    """``tissuebench engines``' plot: every model of the study, each a series: the adapters' answers
    (their steps and iterations; not the stability probes, which answer nothing) and, with --builtin,
    the built-in models at their default step, beside the reference's error estimate. A model with no
    answer to draw (every run unsettled or diverged) is named in the legend with why, not left out."""
    fields = set(Row.__dataclass_fields__)
    rows = [Row.from_json({k: v for k, v in r.items() if k in fields}) for r in out["runs"] if r["knob"] != "stability"]
    rows += [
        Row(
            out["scene"],
            b["model"],
            "quasi-static" if b["dt"] is None else "built-in",
            b["status"],
            dt=b["dt"],
            rel_l2=b["rel_l2"],
            step_us=b["step_us"],
        )
        for b in out.get("builtin") or []
    ]
    drawn = {r.model for r in rows if r.ok and r.step_us is not None and r.rel_l2 is not None}
    missing = {}
    for r in rows:
        if r.model not in drawn:
            missing.setdefault(r.model, set()).add(r.status if not r.ok else "not timed")
    notes = [f"{m}: no answer to draw ({', '.join(sorted(why))})" for m, why in sorted(missing.items())]
    return plot_error_vs_speed(
        [r for r in rows if r.model in drawn], out.get("reference_estimate"), f"{out['scene']}: engines", notes
    )


def budget_rows(rows: list[Row]) -> list[Row]:
    """One row per model with an error budget: its run at the largest step that stayed stable."""
    best = {}
    for r in rows:
        if r.status == "ok" and r.error_budget and r.error_budget.get("mesh") is not None:
            if r.model not in best or (r.dt or 0.0) > (best[r.model].dt or 0.0):
                best[r.model] = r
    return [best[m] for m in sorted(best)]


def plot_budget(rows: list[Row], title: str) -> str:
    """Horizontal stacked bars: each model's error split into the mesh's, the model's and the time
    step's parts (relative L2), with the model's total error marked."""
    fig, ax = plt.subplots(figsize=(7.2, 0.45 * len(rows) + 1.4))
    left = np.zeros(len(rows))
    for part, colour in (("mesh", "#8c8c8c"), ("model", "#d95f02"), ("time", "#1b9e77")):
        width = np.array([r.error_budget.get(part) or 0.0 for r in rows])
        ax.barh([r.model for r in rows], width, left=left, color=colour, label=part)
        left += width
    # the parts are distances between solutions: the total can be below their sum (errors that cancel)
    ax.plot([r.rel_l2 for r in rows], range(len(rows)), "k|", markersize=22, mew=2, label="total error")
    ax.set_xlabel("relative L2 displacement error, by part (fraction)")
    ax.set_title(title, fontsize=9)
    legend_beside(ax)
    ax.grid(True, axis="x", alpha=0.3)
    return png(fig)


def budget_verdict(rows: list[Row]) -> str:
    """One sentence: which part of the error dominates, with the numbers that say so."""
    if not rows:
        return "No error budget: the P1 solution on this mesh could not be computed."
    mesh = rows[0].error_budget["mesh"]
    models = [r.error_budget["model"] for r in rows]
    times = [r.error_budget["time"] for r in rows if r.error_budget.get("time") is not None]
    dominant = [r.error_budget["dominant"] for r in rows]
    lead = max(set(dominant), key=dominant.count)
    text = (
        f"The P1 finite-element solution on this mesh is {100 * mesh:.1f}% off the converged reference; the models "
        f"differ from it by {100 * min(models):.2g}% to {100 * max(models):.2g}%"
        + (f", their time steps cost {100 * min(times):.2g}% to {100 * max(times):.2g}%" if times else "")
        + ". "
    )
    if lead == "mesh":
        return text + (
            f"The mesh dominates for {dominant.count('mesh')} of {len(rows)} models: a finer mesh, not another "
            "model, is what lowers their error, and a model that looks better than finite elements here is "
            "cancelling the mesh's error, not removing it."
        )
    if lead == "model":
        return text + "The models' own shortcuts dominate: here the choice of model matters more than the mesh."
    return text + "The time step dominates: a smaller step, or an implicit integrator, lowers the error most."


def plot_deformation(mesh, u_ref: np.ndarray, u_model: np.ndarray, model: str, title: str) -> str:
    """Deformed boundary: reference (left, grey) and model (right, coloured by |u - u*| in mm)."""
    faces = mesh.boundary
    err = np.linalg.norm(u_model - u_ref, axis=1) * 1e3
    lo, hi = mesh.bounding_box()
    span = float((hi - lo).max())
    fig = plt.figure(figsize=(11, 4.0))
    for k, (u, name) in enumerate(((u_ref, "reference"), (u_model, model))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        tri = (mesh.points + u)[faces]
        if k == 0:
            coll = Poly3DCollection(tri, facecolor=(0.75, 0.78, 0.85), edgecolor=(0.3, 0.3, 0.3, 0.3), linewidths=0.2)
        else:
            coll = Poly3DCollection(tri, cmap="viridis", edgecolor=(0.2, 0.2, 0.2, 0.2), linewidths=0.2)
            coll.set_array(err[faces].mean(axis=1))
            coll.set_clim(0.0, max(float(err.max()), 1e-12))
            fig.colorbar(coll, ax=ax, shrink=0.6, label="|u - u*| (mm)")
        ax.add_collection3d(coll)
        ax.add_collection3d(
            Poly3DCollection(
                mesh.points[faces], facecolor=(0, 0, 0, 0), edgecolor=(0.6, 0.1, 0.1, 0.15), linewidths=0.2
            )
        )
        c = 0.5 * (lo + hi)
        for setlim, i in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
            setlim(c[i] - 0.6 * span, c[i] + 0.6 * span)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=18, azim=-60)
        ax.set_title(f"{name} (rest shape in red)", fontsize=9)
        ax.tick_params(labelsize=6)
        for setlabel, axis in ((ax.set_xlabel, "x"), (ax.set_ylabel, "y"), (ax.set_zlabel, "z")):
            setlabel(f"{axis} (m)", fontsize=7)
    fig.suptitle(title, fontsize=10)
    return png(fig)


def plot_reaction(times, ref_reaction, runs: dict, title: str) -> str:
    """The tool's force (z) over time: what a haptic device would render."""
    fig, ax = plt.subplots(figsize=(7.2, 3.6))
    ax.plot(times, ref_reaction[:, 2], "k-", lw=2, label="reference")
    for model, r in runs.items():
        ax.plot(times, r[:, 2], lw=1, label=model)
    return _finished(fig, ax, "time (s)", "tool force, z (N)", title)


def _finished(fig, ax, xlabel: str, ylabel: str, title: str) -> str:
    """A one-axes figure's labels, title, grid and legend (beside it), as an embedded PNG."""
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    legend_beside(ax)
    return png(fig)


def plot_contact_curve(travel, truth, bars, runs: dict, title: str) -> str:
    """A rigid tool's force against its travel: the reference's points with their bars (None: no bar
    drawn), each model's line over the same stations. travel (S,) m; truth (S,) N; runs: model -> (S,) N."""
    fig, ax = plt.subplots(figsize=(7.2, 4.2))
    mm = np.asarray(travel) * 1e3
    known = [b is not None for b in bars]
    ax.errorbar(mm[known], np.asarray(truth)[known], yerr=[b for b in bars if b is not None], fmt="ko", capsize=3,
                lw=2, label="reference (bar)", zorder=3)  # fmt: skip
    if not all(known):
        ax.plot(mm[~np.asarray(known)], np.asarray(truth)[~np.asarray(known)], "ko", mfc="none", label="reference")
    for k, (model, forces) in enumerate(runs.items()):
        ax.plot(mm, forces, MARKERS[k % len(MARKERS)] + "-", lw=1, ms=4, label=model)
    return _finished(fig, ax, "tool travel (mm)", "tool's push along its travel (N)", title)


def plot_convergence(res: dict, title: str, xlabel: str, ylabel: str) -> str:
    """Log-log error against h (or dt) with dashed reference slopes at the theoretical orders."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for s in res["series"]:
        h, e = np.array(s["h"]), np.array(s["error"])
        line = ax.loglog(h, e, "o-", label=f"{s['label']}: {s['order']:.2f}")[0]
        if s.get("theory"):
            ax.loglog(h, e[-1] * (h / h[-1]) ** s["theory"], "--", color=line.get_color(), lw=0.8, alpha=0.7)
    ax.set_xlabel(xlabel)
    ax.set_ylabel(ylabel)
    ax.set_title(title + " (dashed: theoretical slopes)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    legend_beside(ax)
    return png(fig)
