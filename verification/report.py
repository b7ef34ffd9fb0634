"""The HTML report: one self-contained page (images embedded) plus its data as JSON and CSV.

For each scene: the scene file and its mesh's quality, the reference and its own error estimate, the
real-time models at several time steps (fractions of each one's critical step) with their errors
and step times, the error-versus-microseconds-per-step plot, and pictures of the reference and the
model deformed side by side, the model coloured by its error. Every number on the page comes from
runs made while writing it (or from the reference cache, which records the run that made it).
"""

from __future__ import annotations

import base64
import csv
import html
import io
import json
import time
from pathlib import Path

import matplotlib
import matplotlib.ticker

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from realtime import MODELS  # noqa: E402
from realtime.models import QUASI_STATIC  # noqa: E402

from .results import atomic_write_text  # noqa: E402
from .runner import REFERENCE_DEFAULTS, compare, git_commit, log, reference_result, versions  # noqa: E402
from .scene import load_scene  # noqa: E402

DEFAULT_SCENES = ["cantilever", "cantilever-pull"]
REPORTS = Path("reports")


def _png(fig) -> str:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    return base64.b64encode(buf.getvalue()).decode()


def plot_error_vs_speed(rows: list[dict], ref_est: float | None, title: str) -> str:
    """Log-log rel_l2 against step_us, one series per model, points labelled with dt / dt_crit."""
    fig, ax = plt.subplots(figsize=(6.4, 4.2))
    for model in sorted({r["model"] for r in rows}):
        pts = [r for r in rows if r["model"] == model and r["status"] == "ok"]
        if not pts:
            continue
        ax.loglog([r["step_us"] for r in pts], [max(r["rel_l2"], 1e-16) for r in pts], "o-", label=model)
        for r in pts:
            ax.annotate(
                f"{r['dt'] / r['dt_crit']:.2g} dt_c",
                (r["step_us"], max(r["rel_l2"], 1e-16)),
                textcoords="offset points",
                xytext=(5, 4),
                fontsize=8,
            )
    ok = [max(r["rel_l2"], 1e-16) for r in rows if r["status"] == "ok"]
    if ref_est:
        ax.axhline(ref_est, color="grey", ls="--", lw=1, label="reference error estimate")
        lo = min(ok + [ref_est]) / 10
        ax.axhspan(lo, 10 * ref_est, color="grey", alpha=0.12, label="at reference accuracy (< 10x)")
        ax.set_ylim(lo, max(ok + [10 * ref_est]) * 3)
    ax.xaxis.set_major_formatter(matplotlib.ticker.FormatStrFormatter("%.3g"))
    ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
    ax.set_xlabel("median wall time of one step (us)")
    ax.set_ylabel("relative L2 displacement error")
    ax.set_title(title)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    return _png(fig)


def plot_deformation(mesh, u_ref: np.ndarray, u_model: np.ndarray, model: str, title: str) -> str:
    """Deformed boundary: reference (left, grey) and model (right, coloured by |u - u*| in mm)."""
    faces = mesh.boundary
    err = np.linalg.norm(u_model - u_ref, axis=1) * 1e3
    lo, hi = mesh.bounding_box()
    span = float((hi - lo).max())
    fig = plt.figure(figsize=(11, 4.2))
    for k, (u, name) in enumerate(((u_ref, "reference"), (u_model, model))):
        ax = fig.add_subplot(1, 2, k + 1, projection="3d")
        x = mesh.points + u
        tri = x[faces]
        if k == 0:
            coll = Poly3DCollection(tri, facecolor=(0.75, 0.78, 0.85), edgecolor=(0.3, 0.3, 0.3, 0.3), linewidths=0.2)
        else:
            vals = err[faces].mean(axis=1)
            coll = Poly3DCollection(tri, cmap="viridis", edgecolor=(0.2, 0.2, 0.2, 0.2), linewidths=0.2)
            coll.set_array(vals)
            coll.set_clim(0.0, max(float(err.max()), 1e-12))
            fig.colorbar(coll, ax=ax, shrink=0.6, label="|u - u*| (mm)")
        ax.add_collection3d(coll)
        rest = mesh.points[faces]
        ax.add_collection3d(
            Poly3DCollection(rest, facecolor=(0, 0, 0, 0), edgecolor=(0.6, 0.1, 0.1, 0.15), linewidths=0.2)
        )
        c = 0.5 * (lo + hi)
        for setlim, i in ((ax.set_xlim, 0), (ax.set_ylim, 1), (ax.set_zlim, 2)):
            setlim(c[i] - 0.6 * span, c[i] + 0.6 * span)
        ax.set_box_aspect((1, 1, 1))
        ax.view_init(elev=18, azim=-60)
        ax.set_title(f"{name} (rest shape in red)", fontsize=9)
        ax.set_xlabel("x (m)", fontsize=7)
        ax.set_ylabel("y (m)", fontsize=7)
        ax.set_zlabel("z (m)", fontsize=7)
        ax.tick_params(labelsize=6)
    fig.suptitle(title, fontsize=10)
    return _png(fig)


def _fmt(v, spec=".3g"):
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, spec)
    return html.escape(str(v))


def scene_section(name: str, fractions: list[float]) -> tuple[str, dict]:
    scene = load_scene(name)
    mesh = scene.mesh
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    est = ref.meta.get("ref_err_estimate")
    rows = []
    for model in sorted(MODELS):
        for f in [None] if model in QUASI_STATIC else fractions:
            log(f"report: {scene.name} {model}" + ("" if f is None else f" dt = {f} dt_crit"))
            rows.append(compare(scene, model, dt_fraction=f, reference=ref))
    best = {}
    for r in rows:
        if r["status"] == "ok" and (r["model"] not in best or (r["dt"] or 0) > (best[r["model"]]["dt"] or 0)):
            best[r["model"]] = r
    pictures = []
    from .runner import run_model

    for model, r in sorted(best.items()):
        res = run_model(scene, model, dt=r["dt"])
        pictures.append(
            plot_deformation(
                mesh,
                ref.displacement[-1],
                res.displacement[-1],
                model,
                f"{scene.name}: {model} at dt = {r['dt']:.3g} s, rel_l2 = {r['rel_l2']:.3g}",
            )
        )
    q = mesh.quality()
    plot = plot_error_vs_speed(rows, est, f"{scene.name}: error against speed")
    table = [
        "<tr><th>model</th><th>dt (s)</th><th>dt / dt_crit</th><th>status</th><th>rel_l2</th><th>surface_rel_l2</th>"
        "<th>max_err (m)</th><th>reaction_rel_err</th><th>volume_err</th><th>step (us)</th><th>spread (us)</th>"
        "<th>rate (Hz)</th><th>settle (steps)</th></tr>"
    ]
    for r in rows:
        if r["status"] != "ok":
            table.append(
                f"<tr class='bad'><td>{r['model']}</td><td>{_fmt(r['dt'])}</td><td>{_fmt(r['dt'] / r['dt_crit'], '.2f')}</td>"
                f"<td colspan='10'>diverged at step {r['step']} (critical dt {_fmt(r['dt_crit'])} s)</td></tr>"
            )
            continue
        acc = " <em>(at reference accuracy)</em>" if r["at_reference_accuracy"] else ""
        ratio = "quasi-static" if r["dt"] is None else _fmt(r["dt"] / r["dt_crit"], ".2f")
        table.append(
            f"<tr><td>{r['model']}</td><td>{_fmt(r['dt'])}</td><td>{ratio}</td><td>ok</td>"
            f"<td>{_fmt(r['rel_l2'])}{acc}</td><td>{_fmt(r['surface_rel_l2'])}</td><td>{_fmt(r['max_err'])}</td>"
            f"<td>{_fmt(r['reaction_rel_err'])}</td><td>{_fmt(r['volume_err'])}</td><td>{_fmt(r['step_us'], '.1f')}</td>"
            f"<td>{_fmt(r['step_us_min'], '.1f')} - {_fmt(r['step_us_max'], '.1f')}</td><td>{_fmt(r['rate_hz'], '.0f')}</td>"
            f"<td>{r['settle_steps']}</td></tr>"
        )
    solves = ref.meta.get("solves", [])
    ref_lines = "".join(
        f"<li>level {s['level']}: {s['n_dofs']} dofs, {s['n_cells']} cells, {s['solver']} ({s.get('iterations')} iterations), "
        f"{s['wall_s']:.1f} s</li>"
        for s in solves
    )
    section = f"""
<section>
<h2>{html.escape(scene.name)}</h2>
<p>{html.escape(scene.description)}</p>
<details><summary>scene file {html.escape(str(scene.path.name))}</summary><pre>{html.escape(scene.path.read_text())}</pre></details>
<h3>Mesh</h3>
<p>{q["n_vertices"]} vertices, {q["n_tets"]} tetrahedra, sha256 <code>{mesh.sha256()[:16]}</code>; dihedral angles
{q["min_dihedral_deg"]:.1f} to {q["max_dihedral_deg"]:.1f} degrees, aspect ratio up to {q["max_aspect_ratio"]:.2f},
edges {q["min_edge_m"] * 1e3:.2f} to {q["max_edge_m"] * 1e3:.2f} mm.</p>
<h3>Reference</h3>
<p>dolfinx, law <b>{ref.meta["law"]}</b>, P{ref.meta["degree"]} at refinement {ref.meta["refine"]},
LU by {html.escape(str((ref.meta.get("petsc_options") or {}).get("pc_factor_mat_solver_type", "?")))};
own error estimate <b>{_fmt(est)}</b> ({html.escape(ref.meta.get("estimate", ""))}); reaction
{_fmt(float(np.linalg.norm(ref.reaction[-1])))} N. Solved at commit {html.escape(str(ref.meta.get("commit")))}, {html.escape(str(ref.meta.get("date")))}.</p>
<ul>{ref_lines}</ul>
<h3>Error against speed</h3>
<img alt="error against step time for {html.escape(scene.name)}" src="data:image/png;base64,{plot}">
<table>{"".join(table)}</table>
<h3>Deformed shapes</h3>
{"".join(f'<img class="wide" alt="deformed {html.escape(scene.name)}" src="data:image/png;base64,{p}">' for p in pictures)}
</section>"""
    data = {
        "scene": scene.name,
        "scene_sha256": scene.sha256(),
        "mesh_sha256": mesh.sha256(),
        "mesh_quality": q,
        "reference": ref.meta,
        "runs": rows,
    }
    return section, data


CSS = """body{font-family:system-ui,sans-serif;max-width:1200px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:13px;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 7px;text-align:right}
th{background:#f0f2f5}tr.bad td{color:#a00}img{max-width:640px;display:block}img.wide{max-width:100%}
pre{background:#f6f8fa;padding:1em;font-size:12px}code{font-size:12px}"""


def write_report(scenes: list[str] | None = None, out: str | None = None, fractions=(0.25, 0.5, 0.9, 1.1)) -> Path:
    """Run everything the report shows and write it; returns the HTML file's path."""
    scenes = scenes or DEFAULT_SCENES
    name = "default" if scenes == DEFAULT_SCENES else "-".join(scenes)
    outdir = Path(out) if out else REPORTS / name
    t0 = time.perf_counter()
    sections, data = [], []
    for s in scenes:
        sec, d = scene_section(s, list(fractions))
        sections.append(sec)
        data.append(d)
    meta = {
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "versions": versions(),
        "wall_s": time.perf_counter() - t0,
    }
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>tissuebench report: {html.escape(name)}</title>
<style>{CSS}</style></head><body>
<h1>tissuebench report: {html.escape(name)}</h1>
<p>What each real-time model gives up for its speed on these scenes. Errors are relative to a dolfinx reference and shown
beside its own error estimate; an error below ten times that estimate is "at reference accuracy", not a number to trust.
Step times are medians of repeated compiled n-step calls after a warm-up, on this machine.</p>
<p>Commit {html.escape(meta["commit"])}, {meta["date"]}, {html.escape(json.dumps(meta["versions"]))}; written in {meta["wall_s"]:.0f} s.
Data: <a href="data.json">data.json</a>, <a href="runs.csv">runs.csv</a>.</p>
{"".join(sections)}
</body></html>"""
    outdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(outdir / "data.json", json.dumps({"meta": meta, "scenes": data}, indent=1, default=str))
    buf = io.StringIO()
    cols = [
        "scene",
        "model",
        "integrator",
        "status",
        "dt",
        "dt_crit",
        "rel_l2",
        "surface_rel_l2",
        "max_err",
        "reaction_rel_err",
        "volume_err",
        "ref_err_estimate",
        "step_us",
        "step_us_min",
        "step_us_max",
        "rate_hz",
        "settle_steps",
    ]
    w = csv.DictWriter(buf, fieldnames=cols, extrasaction="ignore")
    w.writeheader()
    for d in data:
        for r in d["runs"]:
            w.writerow(r)
    atomic_write_text(outdir / "runs.csv", buf.getvalue())
    return atomic_write_text(outdir / "index.html", page).resolve()
