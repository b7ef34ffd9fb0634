"""The HTML report: one self-contained page (images embedded) plus its data as JSON and CSV.

Per scene: the scene file and its mesh's quality; the reference with its own error estimate; the
sweep of every model over time steps (fractions of each one's critical step and the largest stable
one) as a table and as error against microseconds per step with the Pareto front; the advisor's
answer; the reference and each model deformed side by side, the model coloured by its error; for
dynamic scenes the tool's force over time. Then the convergence studies (the reference's orders on
a manufactured solution, the integrators' orders in time) as log-log plots with reference slopes,
and the stability study. Every number comes from runs made for the page or from the caches, which
record the run that made them.
"""

from __future__ import annotations

import html
import json
import time
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from verification.cache import git_commit, versions
from verification.progress import log
from verification.report.plots import img as _img  # noqa: E402
from verification.report.plots import png as _png  # noqa: E402
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.results import atomic_write_text  # noqa: E402
from verification.runs.simulate import run_model  # noqa: E402
from verification.scene import SceneError, load_scene  # noqa: E402
from verification.studies.advise import advise, refined_times
from verification.studies.converge import converge_manufactured, converge_time  # noqa: E402
from verification.studies.prefetch import advice_jobs, settle_ahead, solve_references  # noqa: E402
from verification.studies.stability import FAILED_REFERENCES, reference_jobs, settle_cells, stability  # noqa: E402
from verification.studies.sweep import default_fractions, sweep, sweep_csv  # noqa: E402

DEFAULT_SCENES = ["cantilever", "cantilever-pull", "cantilever-dynamic", "stiff-inclusion"]
#: A step beyond the critical one, run beside the sweep's so that the report shows each model's limit.
BEYOND_LIMIT = 1.1
#: The advisor's question on every scene of the report: 5% error at a haptic 1 kHz.
ADVISE_TOL, ADVISE_RATE = 0.05, 1000.0
#: The stability study of the default report: the cantilever, two models (the others' columns
#: cost minutes each at nu = 0.4999; ``tissuebench stability cantilever`` runs them all).
STABILITY_SCENE, STABILITY_MODELS = "cantilever", ("linear-tm", "stvk-tm")
PICTURE_MODELS = ("linear-tm", "stvk-tm", "mass-spring", "precomputed")
REPORTS = Path("reports")


def plot_error_vs_speed(rows: list[dict], ref_est: float | None, title: str) -> str:
    """Log-log rel_l2 against step_us, one series per model, the Pareto front as a staircase."""
    fig, ax = plt.subplots(figsize=(7.2, 4.6))
    ok = [r for r in rows if r["status"] == "ok"]
    for model in sorted({r["model"] for r in ok}):
        pts = sorted((r for r in ok if r["model"] == model), key=lambda r: r["step_us"])
        ax.loglog([r["step_us"] for r in pts], [max(r["rel_l2"], 1e-16) for r in pts], "o", label=model, alpha=0.8)
        for r in pts:
            label = "q-s" if not r.get("dt_crit") else f"{r['dt'] / r['dt_crit']:.2g}"
            ax.annotate(
                label, (r["step_us"], max(r["rel_l2"], 1e-16)), textcoords="offset points", xytext=(4, 3), fontsize=7
            )
    front = sorted((r for r in ok if r.get("pareto")), key=lambda r: r["step_us"])
    if front:
        ax.step(
            [r["step_us"] for r in front],
            [r["rel_l2"] for r in front],
            where="post",
            color="k",
            lw=1,
            label="Pareto front",
        )
    errs = [max(r["rel_l2"], 1e-16) for r in ok]
    if ref_est:
        ax.axhline(ref_est, color="grey", ls="--", lw=1, label="reference error estimate")
        lo = min(errs + [ref_est]) / 10
        ax.axhspan(lo, 10 * ref_est, color="grey", alpha=0.12, label="at reference accuracy (< 10x)")
        ax.set_ylim(lo, max(errs + [10 * ref_est]) * 3)
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.3g"))
    ax.set_xlabel("median wall time of one step (us)")
    ax.set_ylabel("relative L2 displacement error")
    ax.set_title(title + "  (labels: dt / dt_crit; q-s: quasi-static)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7, loc="best")
    return _png(fig)


def budget_rows(rows: list[dict]) -> list[dict]:
    """One row per model with an error budget: its run at the largest step that stayed stable."""
    best = {}
    for r in rows:
        if r["status"] == "ok" and r.get("error_budget") and r["error_budget"].get("mesh") is not None:
            if r["model"] not in best or (r["dt"] or 0.0) > (best[r["model"]]["dt"] or 0.0):
                best[r["model"]] = r
    return [best[m] for m in sorted(best)]


def plot_budget(rows: list[dict], title: str) -> str:
    """Horizontal stacked bars: each model's error split into the mesh's, the model's and the time
    step's parts (relative L2), with the model's total error marked."""
    fig, ax = plt.subplots(figsize=(7.2, 0.45 * len(rows) + 1.4))
    left = np.zeros(len(rows))
    for part, colour in (("mesh", "#8c8c8c"), ("model", "#d95f02"), ("time", "#1b9e77")):
        width = np.array([r["error_budget"].get(part) or 0.0 for r in rows])
        ax.barh([r["model"] for r in rows], width, left=left, color=colour, label=part)
        left += width
    # the parts are distances between solutions: the total can be below their sum (errors that cancel)
    ax.plot([r["rel_l2"] for r in rows], range(len(rows)), "k|", markersize=22, mew=2, label="total error")
    ax.set_xlabel("relative L2 displacement error, by part")
    ax.set_title(title, fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    ax.grid(True, axis="x", alpha=0.3)
    return _png(fig)


def budget_verdict(rows: list[dict]) -> str:
    """One sentence: which part of the error dominates, with the numbers that say so."""
    if not rows:
        return "No error budget: the P1 solution on this mesh could not be computed."
    mesh = rows[0]["error_budget"]["mesh"]
    models = [r["error_budget"]["model"] for r in rows]
    times = [r["error_budget"]["time"] for r in rows if r["error_budget"].get("time") is not None]
    dominant = [r["error_budget"]["dominant"] for r in rows]
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
    fig.suptitle(title, fontsize=10)
    return _png(fig)


def plot_reaction(times, ref_reaction, runs: dict, title: str) -> str:
    """The tool's force (z) over time: what a haptic device would render."""
    fig, ax = plt.subplots(figsize=(7.2, 3.6))
    ax.plot(times, ref_reaction[:, 2], "k-", lw=2, label="reference")
    for model, r in runs.items():
        ax.plot(times, r[:, 2], lw=1, label=model)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("tool force, z (N)")
    ax.set_title(title, fontsize=9)
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7)
    return _png(fig)


def plot_convergence(res: dict, title: str, xlabel: str) -> str:
    """Log-log error against h (or dt) with dashed reference slopes at the theoretical orders."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for s in res["series"]:
        h, e = np.array(s["h"]), np.array(s["error"])
        line = ax.loglog(h, e, "o-", label=f"{s['label']}: {s['order']:.2f}")[0]
        if s.get("theory"):
            ax.loglog(h, e[-1] * (h / h[-1]) ** s["theory"], "--", color=line.get_color(), lw=0.8, alpha=0.7)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("error")
    ax.set_title(title + " (dashed: theoretical slopes)", fontsize=9)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=7)
    return _png(fig)


def _fmt(v, spec=".3g"):
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, spec)
    return html.escape(str(v))


def _solver(options: dict) -> str:
    """The reference's linear solver in words, from the PETSc options its metadata records."""
    pc = options.get("pc_type", "?")
    if options.get("ksp_type", "preonly") == "preonly":
        kind = {"cholesky": "LDL^T", "lu": "LU"}.get(pc, pc)
        return f"{kind} by {options.get('pc_factor_mat_solver_type', 'PETSc')}"
    return f"{options['ksp_type'].upper()} preconditioned by {pc.upper()}"


def _sweep_table(rows: list[dict]) -> str:
    head = (
        "<tr><th>model</th><th>integrator</th><th>dt (s)</th><th>dt / dt_crit</th><th>rel_l2</th>"
        "<th>surface_rel_l2</th><th>max_err (m)</th><th>reaction_rel_err</th><th>volume_err</th>"
        "<th>step (us)</th><th>spread (us)</th><th>rate (Hz)</th><th>Pareto</th></tr>"
    )
    out = [head]
    for r in rows:
        ratio = "quasi-static" if not r.get("dt_crit") else _fmt(r["dt"] / r["dt_crit"], ".2f")
        if r.get("largest_stable"):
            ratio += " (largest stable)"
        if r["status"] != "ok":
            out.append(
                f"<tr class='bad'><td>{r['model']}</td><td>{r['integrator']}</td><td>{_fmt(r['dt'])}</td>"
                f"<td>{ratio}</td><td colspan='9'>diverged at step {r['step']} (critical dt "
                f"{_fmt(r['dt_crit'])} s)</td></tr>"
            )
            continue
        acc = " <em>(at reference accuracy)</em>" if r["at_reference_accuracy"] else ""
        acc += "".join(f" <em>(ran without {html.escape(t)})</em>" for t in r.get("unrepresented") or [])
        out.append(
            f"<tr><td>{r['model']}</td><td>{r['integrator']}</td><td>{_fmt(r['dt'])}</td><td>{ratio}</td>"
            f"<td>{_fmt(r['rel_l2'])}{acc}</td><td>{_fmt(r['surface_rel_l2'])}</td><td>{_fmt(r['max_err'])}</td>"
            f"<td>{_fmt(r['reaction_rel_err'])}</td><td>{_fmt(r['volume_err'])}</td><td>{_fmt(r['step_us'], '.1f')}</td>"
            f"<td>{_fmt(r['step_us_min'], '.1f')} - {_fmt(r['step_us_max'], '.1f')}</td><td>{_fmt(r['rate_hz'], '.0f')}</td>"
            f"<td>{'yes' if r.get('pareto') else ''}</td></tr>"
        )
    return "<table>" + "".join(out) + "</table>"


def _advice_html(a: dict) -> str:
    """The advisor's answer: the pick (on the mesh it names), its frame budget, why, the command that
    re-runs it, and every cheaper option with the reason it failed."""
    rej = "".join(f"<li>{html.escape(x)}</li>" for x in a.get("cheaper_failed") or a.get("rejected") or [])
    rej = f"<details><summary>cheaper options rejected</summary><ul>{rej}</ul></details>" if rej else ""
    if not a.get("model"):
        why = a["why"]  # it already says that no model meets the bound
        return f"<p class='advice'>{html.escape(why[0].upper() + why[1:])}</p>" + rej
    step = a["integrator"] if a["dt"] is None else f"{a['integrator']}, dt = {a['dt']:.3g} s"
    m = a["mesh"]
    mesh = (
        f" on the mesh refined {refined_times(a['refine'])} ({m['n_vertices']} vertices, mean edge "
        f"{m['mean_edge_m'] * 1e3:.3g} mm)"
        if a["refine"]
        else ""
    )
    runner = a.get("runner_up")
    ru = f" Runner-up: <b>{runner['model']}</b> (rel_l2 {runner['value']:.3g})." if runner else ""
    return (
        f"<p class='advice'>For rel_l2 &le; {ADVISE_TOL} at {ADVISE_RATE:.0f} Hz: <b>{a['model']}</b> "
        f"({step}){mesh}: rel_l2 {a['value']:.3g}; {html.escape(a['frame']['why'])}. "
        f"{html.escape(a['why'][0].upper() + a['why'][1:])}.{ru} Check it: <code>{html.escape(a['command'])}</code></p>"
        + rej
    )


def section_fractions(scene, fractions=None) -> list[float]:
    """The fractions of the critical step a scene's section sweeps: ``fractions``, or the sweep's
    default for the scene and BEYOND_LIMIT."""
    return list(fractions) if fractions else [*default_fractions(scene), BEYOND_LIMIT]


def scene_section(name: str, fractions=None) -> tuple[str, dict]:
    """A scene's section and its data; ``fractions`` of the critical step (default: the sweep's for the
    scene, and BEYOND_LIMIT to show the limit)."""
    scene = load_scene(name)
    fractions = section_fractions(scene, fractions)
    mesh = scene.mesh
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    est = ref.meta.get("ref_err_estimate")
    log(f"report: sweep {scene.name}")
    sw = sweep(scene, fractions=fractions)
    rows = sw["rows"]
    adv = advise(scene, tol=ADVISE_TOL, rate=ADVISE_RATE)
    pictures, reactions = [], {}
    for model in PICTURE_MODELS:
        good = [r for r in rows if r["model"] == model and r["status"] == "ok"]
        if not good:
            continue
        r = max(good, key=lambda r: r["dt"] or 0.0)
        # the row's own run (by its fraction, as the sweep ran it: a static one is then settled already)
        fraction = r.get("fraction")
        res = run_model(
            scene,
            model,
            dt=None if fraction else r["dt"],
            dt_fraction=fraction,
            integrator=r["integrator"] if r["dt"] else "symplectic-euler",
        )
        k = int(np.argmax(np.abs(ref.displacement).max(axis=(1, 2))))
        at = "quasi-static" if r["dt"] is None else f"dt = {r['dt']:.3g} s"
        when = f", t = {ref.times[k]:.3g} s" if scene.time.mode == "dynamic" else ""
        pictures.append(
            plot_deformation(
                mesh,
                ref.displacement[k],
                res.displacement[k],
                model,
                f"{scene.name}: {model} ({at}{when}), rel_l2 = {r['rel_l2']:.3g}",
            )
        )
        reactions[model] = res.reaction
    q = mesh.quality()
    plot = plot_error_vs_speed(rows, est, f"{scene.name}: error against speed")
    budgets = budget_rows(rows)
    budget_html = (
        _img(plot_budget(budgets, f"{scene.name}: whose error is it?"), f"error budget of {scene.name}")
        if budgets
        else ""
    ) + f"<p>{html.escape(budget_verdict(budgets))}</p>"
    extra = ""
    if scene.time.mode == "dynamic" and scene.problem.tools:
        extra = "<h3>The tool's force over time</h3>" + _img(
            plot_reaction(ref.times, ref.reaction, reactions, f"{scene.name}: force on the tool"), "tool force"
        )
    ref_lines = "".join(
        f"<li>{'level ' + str(s['level']) if 'level' in s else ''} {s.get('n_dofs', '')} dofs, {s['solver']} "
        f"({s.get('iterations')} iterations), {s.get('wall_s', 0):.1f} s</li>"
        for s in ref.meta.get("solves", [])
    )
    section = f"""
<section id="{html.escape(scene.name)}">
<h2>{html.escape(scene.name)} ({scene.time.mode})</h2>
<p>{html.escape(scene.description)}</p>
<details><summary>scene file {html.escape(str(scene.path.name))}</summary><pre>{html.escape(scene.path.read_text())}</pre></details>
<h3>Mesh</h3>
<p>{q["n_vertices"]} vertices, {q["n_tets"]} tetrahedra, sha256 <code>{mesh.sha256()[:16]}</code>; dihedral angles
{q["min_dihedral_deg"]:.1f} to {q["max_dihedral_deg"]:.1f} degrees, aspect ratio up to {q["max_aspect_ratio"]:.2f},
edges {q["min_edge_m"] * 1e3:.2f} to {q["max_edge_m"] * 1e3:.2f} mm.{_repairs(mesh)}</p>
<h3>Reference</h3>
<p>dolfinx, law <b>{ref.meta["law"]}</b>, P{ref.meta["degree"]} at refinement {ref.meta["refine"]},
linear solves {html.escape(_solver(ref.meta.get("petsc_options") or {}))};
own error estimate <b>{_fmt(est)}</b> ({html.escape(ref.meta.get("estimate", ""))}).
Solved at commit {html.escape(str(ref.meta.get("commit")))}, {html.escape(str(ref.meta.get("date")))}.</p>
<ul>{ref_lines}</ul>
<h3>Error against speed</h3>
{_img(plot, f"error against step time for {scene.name}")}
{_sweep_table(rows)}
<h3>Error budget</h3>
<p>Each model's error split into the mesh's part (the P1 finite-element solution of the same law on the same
mesh against the converged reference), the model's part (the model against that P1 solution) and, on dynamic
scenes, the time step's (the model against itself at an eighth of its step).</p>
{budget_html}
<h3>Advisor</h3>
{_advice_html(adv)}
{extra}
<h3>Deformed shapes</h3>
{"".join(_img(p, f"deformed {scene.name}", wide=True) for p in pictures)}
</section>"""
    return section, {
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": mesh.sha256(),
        "mesh_quality": q,
        "reference": ref.meta,
        "sweep": sw,
        "advice": adv,
        "budget": {
            "rows": [{"model": r["model"], "dt": r["dt"], **r["error_budget"]} for r in budgets],
            "verdict": budget_verdict(budgets),
        },
    }


def _repairs(mesh) -> str:
    """What reading the mesh file repaired, as a sentence (empty for a clean mesh)."""
    return f" Read from its file with repairs: {html.escape('; '.join(mesh.notes))}." if mesh.notes else ""


def convergence_section() -> tuple[str, dict]:
    log("report: convergence")
    man = converge_manufactured(load_scene("manufactured"))
    tim = converge_time(load_scene("cantilever-dynamic"), models=("linear-tm",))
    rows = "".join(
        f"<tr><td>{s['label']}</td><td>{s['order']:.2f}</td><td>{s['theory']}</td>"
        f"<td>{', '.join(f'{e:.3g}' for e in s['error'])}</td></tr>"
        for s in man["series"] + tim["series"]
    )
    text = f"""
<section>
<h2>Convergence</h2>
<p>The reference on a manufactured StVK solution of the unit cube (errors in L2 and the H1 seminorm against the exact
field), and the explicit integrators' trajectories on <code>cantilever-dynamic</code> against their own run at
0.025 dt_crit. Fitted orders beside the theoretical ones.</p>
<table><tr><th>series</th><th>observed order</th><th>theory</th><th>errors</th></tr>{rows}</table>
{_img(plot_convergence(man, "reference, manufactured solution", "h"), "reference convergence")}
{_img(plot_convergence(tim, "linear-tm, time step", "dt (s)"), "time convergence")}
</section>"""
    return text, {"manufactured": man, "time": tim}


def stability_section() -> tuple[str, dict]:
    log("report: stability")
    res = stability(load_scene(STABILITY_SCENE), models=STABILITY_MODELS)
    models = list(res["table"][0]["models"]) if res["table"] else []
    for row in res["table"]:
        for m in row["models"]:
            if m not in models:
                models.append(m)
    head = "<tr><th>case</th>" + "".join(f"<th>{html.escape(m)}</th>" for m in models) + "</tr>"
    body = []
    for row in res["table"]:
        cells = []
        for m in models:
            c = row["models"].get(m)
            if c is None:
                cells.append("<td></td>")
                continue
            txt = c["status"]
            if "rel_l2" in c:
                txt += f"<br>rel_l2 {c['rel_l2']:.3g}"
            if "vs_baseline" in c:
                txt += f" ({c['vs_baseline']:.2g}x)"
            if c.get("settle_ms"):
                txt += f"<br>settles in {c['settle_ms']:.0f} ms"
            if "detail" in c:
                txt += f"<br><small>{html.escape(c['detail'][:160])}</small>"
            cls = " class='bad'" if c["status"] not in ("ok",) else ""
            cells.append(f"<td{cls}>{txt}</td>")
        body.append(f"<tr id='{row['case']}'><td>{row['case']} = {row['value']:.4g}</td>{''.join(cells)}</tr>")
    summary = "".join(f"<li>{html.escape(x)}</li>" for x in res["summary"])
    text = f"""
<section>
<h2>Stability at the extremes: {STABILITY_SCENE}</h2>
<p>Models {", ".join(STABILITY_MODELS)} (all models: <code>tissuebench stability {STABILITY_SCENE}</code>).
Tolerance on rel_l2: {res["tol"]}; "(Nx)" is the error against the model's own error on the unchanged scene.</p>
<ul>{summary}</ul>
<table>{head}{"".join(body)}</table>
</section>"""
    return text, res


CSS = """body{font-family:system-ui,sans-serif;max-width:1250px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 6px;text-align:right;vertical-align:top}
th{background:#f0f2f5}td.bad,tr.bad td{color:#a00}img{max-width:760px;display:block}img.wide{max-width:100%}
pre{background:#f6f8fa;padding:1em;font-size:12px}code{font-size:12px}p.advice{background:#eef6ee;padding:.6em}"""


def report_dir(scenes: list[str], out: str | None = None) -> tuple[str, Path]:
    """The report's name and directory, created now. Every scene is read first, so a bad one fails before
    any compute; a scene given as a path is named by its scene name, never by its path."""
    name = "default" if scenes == DEFAULT_SCENES else "-".join(load_scene(s).name for s in scenes)
    return name, make_report_dir(Path(out) if out else REPORTS / name)


def make_report_dir(outdir: Path) -> Path:
    """Create a report's directory now, before any compute; a path that cannot be one is a SceneError."""
    if outdir.exists() and not outdir.is_dir():
        raise SceneError(f"{outdir}: the report directory is an existing file")
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{outdir}: cannot create the report directory ({exc.strerror})") from None
    return outdir


def write_report(
    scenes: list[str] | None = None,
    out: str | None = None,
    fractions=None,
    studies: bool | None = None,
) -> Path:
    """Run everything the report shows and write it; returns the HTML file's path. The convergence and
    stability sections are part of the default report (``studies`` None) and optional otherwise."""
    scenes = scenes or DEFAULT_SCENES
    default = scenes == DEFAULT_SCENES
    studies = default if studies is None else studies
    name, outdir = report_dir(scenes, out)
    t0 = time.perf_counter()
    jobs = advice_jobs([load_scene(s) for s in scenes])  # every scene's section ends with advice
    if studies:
        jobs += reference_jobs(load_scene(STABILITY_SCENE))
    FAILED_REFERENCES.update(solve_references(jobs))  # the stability study does not solve these again
    # the sections' steps, the advisor's (its sweep runs the default ones) and the stability study's cells
    settle_ahead(
        [
            (scene, tuple(dict.fromkeys([*section_fractions(scene, fractions), *default_fractions(scene)])))
            for scene in map(load_scene, scenes)
        ],
        cells=settle_cells(load_scene(STABILITY_SCENE), STABILITY_MODELS) if studies else (),
    )
    sections, data = [], {"scenes": []}
    for s in scenes:
        sec, d = scene_section(s, fractions)
        sections.append(sec)
        data["scenes"].append(d)
    if studies:
        for fn, key in ((convergence_section, "convergence"), (stability_section, "stability")):
            sec, d = fn()
            sections.append(sec)
            data[key] = d
    meta = {
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "versions": versions(),
        "wall_s": time.perf_counter() - t0,
    }
    data["meta"] = meta
    names = [d["scene"] for d in data["scenes"]]
    nav = "".join(f"<a href='#{html.escape(s)}'>{html.escape(s)}</a> " for s in names)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>tissuebench report: {html.escape(name)}</title>
<style>{CSS}</style></head><body>
<h1>tissuebench report: {html.escape(name)}</h1>
<p>What each real-time model gives up for its speed on these scenes. Errors are relative to a dolfinx reference and shown
beside its own error estimate; an error below ten times that estimate is "at reference accuracy", not a number to trust.
Step times are medians of repeated compiled n-step calls after a warm-up, on this machine.</p>
<p>Commit {html.escape(meta["commit"])}, {meta["date"]}, {html.escape(json.dumps(meta["versions"]))}; written in {meta["wall_s"]:.0f} s.
Data: <a href="data.json">data.json</a>, <a href="runs.csv">runs.csv</a>. Scenes: {nav}</p>
{"".join(sections)}
</body></html>"""
    outdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(outdir / "data.json", json.dumps(data, indent=1, default=str))
    csv = "scene," + sweep_csv(data["scenes"][0]["sweep"]).splitlines()[0] + "\n"
    for d in data["scenes"]:
        csv += "".join(f"{d['scene']},{line}\n" for line in sweep_csv(d["sweep"]).splitlines()[1:])
    atomic_write_text(outdir / "runs.csv", csv)
    return atomic_write_text(outdir / "index.html", page).resolve()


def _rows_html(rows: list[dict]) -> str:
    """A list of flat dicts as a table, one column per key in first-seen order."""
    if not rows:
        return ""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(_fmt(r.get(k)))}</td>" for k in keys) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def seeds_html(res: dict) -> str:
    """The seeds study (``verification.studies.seeds.run_seeds``) as a section: the table of verdicts, then each
    experiment with its claim, the rule that decided, the numbers and the plots."""
    verdicts = "".join(
        f"<tr class='{html.escape(f['verdict'])}'><td>{f['number']}</td><td><a href='#seed-{html.escape(f['key'])}'>"
        f"{html.escape(f['title'])}</a></td><td>{html.escape(f['source'])}</td><td style='text-align:left'>"
        f"{html.escape(f['claim'])}</td><td><b>{html.escape(f['verdict'])}</b></td><td style='text-align:left'>"
        f"{html.escape(f['decides'])}</td><td>{html.escape(_reference_bar(f['reference']))}</td></tr>"
        for f in res["experiments"]
    )
    parts = [
        "<h2 id='seeds'>The source documents, measured</h2>",
        "<table><tr><th>#</th><th>experiment</th><th>source</th><th>claim</th><th>verdict</th>"
        f"<th>the number that decides</th><th>truth</th></tr>{verdicts}</table>",
    ]
    for f in res["experiments"]:
        left = f"<p><b>Left out:</b> {html.escape(f['left_out'])}</p>" if f.get("left_out") else ""
        parts.append(
            f"<h3 id='seed-{html.escape(f['key'])}'>{f['number']}. {html.escape(f['title'])} "
            f"({html.escape(f['source'])}): {html.escape(f['verdict'])}</h3>"
            f"<p><b>Claim:</b> {html.escape(f['claim'])}</p><p><b>Rule:</b> {html.escape(f['rule'])}</p>"
            f"<p><b>Measured:</b> {html.escape(f['figure'])}</p><p class=advice><b>Decides:</b> "
            f"{html.escape(f['decides'])}</p>{left}"
            + "".join(_img(p["png"], p["alt"], wide=True) for p in f["plots"])
            + _rows_html(f["table"])
            + f"<p>Truth: {html.escape(_reference_bar(f['reference']))}; ran in {f.get('wall_s', 0):.0f} s.</p>"
        )
    return "".join(parts)


def _reference_bar(ref: dict) -> str:
    est = ref.get("ref_err_estimate")
    if est is None:
        return ref["kind"] + ("" if ref.get("verified") else ", unverified")
    return f"{ref['kind']}, error estimate {est:.1e}"


def seeds_report_dir(out: str | None = None) -> Path:
    """The seeds page's directory, ``reports/seeds`` or ``out``, created now."""
    return make_report_dir(Path(out) if out else REPORTS / "seeds")


def write_seeds_report(res: dict, out: str | None = None) -> Path:
    """The seeds study as its own page, ``reports/seeds/index.html`` (or ``out``), with its data."""
    from verification.studies.seeds import without_pictures

    outdir = seeds_report_dir(out)
    meta = {
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "versions": versions(),
        "size": res["meta"]["size"],
        "wall_s": res["meta"]["wall_s"],
    }
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>tissuebench: the source documents, measured</title>
<style>{CSS}</style></head><body>
<h1>tissuebench: the source documents, measured</h1>
<p>Each claim of the two documents the project started from (Xu's slides on Picinbono, Delingette and Ayache; Liu's
MMVR 2002 tutorial), reproduced on this machine against the dolfinx reference or a closed form. Every verdict is
computed from the run by the rule printed beside it.</p>
<p>Commit {html.escape(meta["commit"])}, {meta["date"]}, {html.escape(json.dumps(meta["versions"]))};
runs of size "{html.escape(meta["size"])}", {meta["wall_s"]:.0f} s. Data: <a href="data.json">data.json</a>.</p>
{seeds_html(res)}
</body></html>"""
    atomic_write_text(outdir / "data.json", json.dumps({**without_pictures(res), "meta": meta}, indent=1, default=str))
    return atomic_write_text(outdir / "index.html", page).resolve()
