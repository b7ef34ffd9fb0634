"""The report's sections: one per scene (its mesh, reference, sweep, error budget, advice and deformed
shapes), the convergence studies and the stability study. Every number comes from runs made for the
page or from the caches, which record the run that made them."""

from __future__ import annotations

import base64
import dataclasses
import html
from dataclasses import dataclass

import numpy as np

from meshes import TetMesh
from realtime.models import linear_tm, mass_spring, precomputed, stvk_tm
from verification.figures import img as _img
from verification.progress import log
from verification.report.common import fmt
from verification.report.contact import contact_html
from verification.report.plots import (
    budget_rows,
    budget_verdict,
    plot_budget,
    plot_convergence,
    plot_deformation,
    plot_error_vs_speed,
    plot_reaction,
)
from verification.report.scene_picture import scene_picture
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row
from verification.runs.simulate import run_model
from verification.scene_file import load_scene
from verification.studies.advise import advise, refined_times
from verification.studies.converge import converge_manufactured, converge_time
from verification.studies.frame import true_range, with_bar
from verification.studies.stability import stability
from verification.studies.sweep import default_fractions, re_adapted, sweep

#: The convergence plots' error axes: the manufactured solution's L2 (m) and H1-seminorm (dimensionless)
#: errors against the exact field on the unit cube, and the integrators' relative L2 distance from their
#: run at 0.025 dt_crit.
MANUFACTURED_ERROR = "error against the exact field (L2: m; H1 seminorm: 1)"
TIME_ERROR = "relative L2 error against dt_crit / 40 (fraction)"
#: A step beyond the critical one, run beside the sweep's so that the report shows each model's limit.
BEYOND_LIMIT = 1.1


@dataclass(frozen=True)
class Question:
    """The advisor's question on every scene of a report (``report --tol --rate --haptic-rate``): rel_l2
    at most ``tol`` (relative) at ``rate`` Hz, and with ``haptic_rate`` (Hz) a haptic loop whose tool
    force is within ``tol`` too. The default: 5% at a haptic device's 1 kHz update."""

    tol: float = 0.05
    rate: float = 1000.0
    haptic_rate: float | None = None

    def __str__(self) -> str:
        haptic = "" if self.haptic_rate is None else f", tool force within {self.tol:g} at {self.haptic_rate:g} Hz"
        return f"rel_l2 &le; {self.tol:g} at {self.rate:g} Hz{haptic}"

    def of(self, scene) -> Question:
        """The question as it applies to ``scene``: without its haptic part where no tool gives a device a
        force to hold (a scene hung under gravity is judged at the rate alone, not refused)."""
        return self if scene.problem.held_by_tools else dataclasses.replace(self, haptic_rate=None)

    @staticmethod
    def answered(advice: dict) -> Question:
        """The question an ``advise`` answer was given."""
        return Question(advice["tol"], advice["rate"], (advice.get("haptic") or {}).get("rate"))


#: The report's question when none is asked.
DEFAULT_QUESTION = Question()


#: The stability study of the default report: the cantilever, two models (the others' columns
#: cost minutes each at nu = 0.4999; ``tissuebench stability cantilever`` runs them all).
STABILITY_SCENE = "cantilever"


STABILITY_MODELS = (linear_tm.NAME, stvk_tm.NAME)


PICTURE_MODELS = (linear_tm.NAME, stvk_tm.NAME, mass_spring.NAME, precomputed.NAME)


def _solver(options: dict) -> str:
    """The reference's linear solver in words, from the PETSc options its metadata records."""
    pc = options.get("pc_type", "?")
    if options.get("ksp_type", "preonly") == "preonly":
        kind = {"cholesky": "LDL^T", "lu": "LU"}.get(pc, pc)
        return f"{kind} by {options.get('pc_factor_mat_solver_type', 'PETSc')}"
    return f"{options['ksp_type'].upper()} preconditioned by {pc.upper()}"


def _sweep_table(rows: list[Row]) -> str:
    head = (
        "<tr><th>model</th><th>integrator</th><th>dt (s)</th><th>dt / dt_crit</th><th>rel_l2</th>"
        "<th>surface_rel_l2</th><th>max_err (m)</th><th>reaction_rel_err</th><th>volume_err</th>"
        "<th>step (us)</th><th>spread (us)</th><th>rate (Hz)</th><th>Pareto</th></tr>"
    )
    out = [head]
    for r in rows:
        ratio = fmt(r.dt / r.dt_crit, ".2f") if r.dt_crit else r.integrator
        if r.largest_stable:
            ratio += " (largest stable)"
        if r.status != "ok":
            what = (
                f"diverged at step {r.step} (critical dt {fmt(r.dt_crit)} s)"
                if r.status == "diverged"
                else html.escape(f"{r.status}: {r.message or ''}")
            )
            out.append(
                f"<tr class='bad'><td>{r.model}</td><td>{r.integrator}</td><td>{fmt(r.dt)}</td>"
                f"<td>{ratio}</td><td colspan='9'>{what}</td></tr>"
            )
            continue
        span = true_range(r.rel_l2, r.ref_err_estimate)
        acc = f" <em>({span})</em>" if span else ""
        acc += "".join(f" <em>(ran without {html.escape(t)})</em>" for t in r.unrepresented or [])
        acc += f" <em>{html.escape(re_adapted(r).strip())}</em>" if r.adaptation else ""
        out.append(
            f"<tr><td>{r.model}</td><td>{r.integrator}</td><td>{fmt(r.dt)}</td><td>{ratio}</td>"
            f"<td>{fmt(r.rel_l2)}{acc}</td><td>{fmt(r.surface_rel_l2)}</td><td>{fmt(r.max_err)}</td>"
            f"<td>{fmt(r.reaction_rel_err)}</td><td>{fmt(r.volume_err)}</td><td>{fmt(r.step_us, '.1f')}</td>"
            f"<td>{fmt(r.step_us_min, '.1f')} - {fmt(r.step_us_max, '.1f')}</td><td>{fmt(r.rate_hz, '.0f')}</td>"
            f"<td>{'yes' if r.pareto else ''}</td></tr>"
        )
    return "<table>" + "".join(out) + "</table>"


def _advice_html(a: dict, q: Question) -> str:
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
        f"<p class='advice'>For {q}: <b>{a['model']}</b> "
        f"({step}){mesh}: rel_l2 {html.escape(with_bar(a['value'], (a.get('reference') or {}).get('bar')))}; "
        f"{html.escape(a['frame']['why'])}. "
        f"{html.escape(a['why'][0].upper() + a['why'][1:])}.{ru} Check it: <code>{html.escape(a['command'])}</code></p>"
        + rej
    )


def section_fractions(scene, fractions=None) -> list[float]:
    """The fractions of the critical step a scene's section sweeps: ``fractions``, or the sweep's
    default for the scene and BEYOND_LIMIT."""
    return list(fractions) if fractions else [*default_fractions(scene), BEYOND_LIMIT]


def scene_section(name: str, fractions=None, question: Question = DEFAULT_QUESTION) -> tuple[str, dict]:
    """A scene's section and its data; ``fractions`` of the critical step (default: the sweep's for the
    scene, and BEYOND_LIMIT to show the limit); the advisor asked ``question``."""
    scene = load_scene(name)
    fractions = section_fractions(scene, fractions)
    mesh = scene.mesh
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    log(f"report: sweep {scene.name}")
    sw = sweep(scene, fractions=fractions)
    rows = sw["rows"]
    question = question.of(scene)
    adv = advise(scene, tol=question.tol, rate=question.rate, haptic_rate=question.haptic_rate)
    pictures, reactions = _pictures(scene, ref, rows)
    contact, contact_data = contact_html(scene, ref, rows)
    q = mesh.quality()
    budgets = budget_rows(rows)
    section = f"""
<section id="{html.escape(scene.name)}">
<h2>{html.escape(scene.name)} ({scene.time.mode})</h2>
<p>{html.escape(scene.description)}</p>
<h3>Advisor</h3>
{_advice_html(adv, question)}
{_mesh_html(scene, q)}
{_reference_html(ref)}
<h3>Error against speed</h3>
{_img(plot_error_vs_speed(rows, ref.meta.get("ref_err_estimate"), f"{scene.name}: error against speed"), f"error against step time for {scene.name}")}
{_sweep_table([r for r in rows if r.status == "ok"])}
{_diverged_html(rows)}
<h3>Error budget</h3>
<p>Each model's error split into the mesh's part (the P1 finite-element solution of the same law on the same
mesh against the converged reference), the model's part (the model against that P1 solution) and, on dynamic
scenes, the time step's (the model against itself at an eighth of its step).</p>
{_budget_html(scene, budgets)}
{_reaction_html(scene, ref, reactions)}
{contact}
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
        "contact": contact_data,
        "budget": {
            "rows": [{"model": r.model, "dt": r.dt, **r.error_budget} for r in budgets],
            "verdict": budget_verdict(budgets),
        },
    }


def _pictures(scene, ref, rows: list[Row]) -> tuple[list[str], dict]:
    """For each of PICTURE_MODELS, its run at its largest stable step deformed beside the reference at
    the instant of largest displacement, and its tool force over time (T, 3) N."""
    pictures, reactions = [], {}
    for model in PICTURE_MODELS:
        good = [r for r in rows if r.model == model and r.status == "ok"]
        if not good:
            continue
        r = max(good, key=lambda r: r.dt or 0.0)
        # the row's own run (by its fraction, as the sweep ran it: a static one is then settled already)
        fraction = r.fraction
        res = run_model(
            scene,
            model,
            dt=None if fraction else r.dt,
            dt_fraction=fraction,
            integrator=r.integrator if r.dt else "symplectic-euler",
        )
        k = int(np.argmax(np.abs(ref.displacement).max(axis=(1, 2))))
        at = "quasi-static" if r.dt is None else f"dt = {r.dt:.3g} s"
        when = f", t = {ref.times[k]:.3g} s" if scene.time.mode == "dynamic" else ""
        title = f"{scene.name}: {model} ({at}{when}), rel_l2 = {r.rel_l2:.3g}"
        # a cut scene's results live on the union of its states' vertices, on the mesh cut open
        # (``runs.staged.stitched``): every state is drawn on that mesh, whose lips coincide before the cut
        mesh = TetMesh(res.points, res.tets) if scene.events else scene.mesh
        if scene.events:
            title += f"\nthe state {res.meta['states'][k]['label']}"
        pictures.append(plot_deformation(mesh, ref.displacement[k], res.displacement[k], model, title))
        reactions[model] = res.reaction
    return pictures, reactions


def _mesh_html(scene, q: dict) -> str:
    """The scene file (folded) and its mesh's size and quality."""
    mesh = scene.mesh
    return f"""<details><summary>scene file {html.escape(str(scene.path.name))}</summary><pre>{html.escape(scene.path.read_text())}</pre></details>
<h3>Mesh</h3>
<p>{q["n_vertices"]} vertices, {q["n_tets"]} tetrahedra, sha256 <code>{mesh.sha256()[:16]}</code>; dihedral angles
{q["min_dihedral_deg"]:.1f} to {q["max_dihedral_deg"]:.1f} degrees, aspect ratio up to {q["max_aspect_ratio"]:.2f},
edges {q["min_edge_m"] * 1e3:.2f} to {q["max_edge_m"] * 1e3:.2f} mm.{_repairs(mesh)}</p>
{_img(base64.b64encode(scene_picture(scene)).decode(), f"{scene.name} from three sides", wide=True)}"""


def _reference_html(ref) -> str:
    """How the reference was solved, its own error estimate, and each level's solve."""
    est = ref.meta.get("ref_err_estimate")
    levels = "".join(
        f"<li>{'level ' + str(s['level']) if 'level' in s else ''} {s.get('n_dofs', '')} dofs, {s['solver']} "
        f"({s.get('iterations')} iterations), {s.get('wall_s', 0):.1f} s</li>"
        for s in ref.meta.get("solves", [])
    )
    return f"""<h3>Reference</h3>
<p>dolfinx, law <b>{ref.meta["law"]}</b>, P{ref.meta["degree"]} at refinement {ref.meta["refine"]},
linear solves {html.escape(_solver(ref.meta.get("petsc_options") or {}))};
own error estimate <b>{fmt(est)}</b> ({html.escape(ref.meta.get("estimate", ""))}).
Solved at commit {html.escape(str(ref.meta.get("commit")))}, {html.escape(str(ref.meta.get("date")))}.</p>
<ul>{levels}</ul>"""


def _budget_html(scene, budgets: list[Row]) -> str:
    """The error budget's plot and its verdict in words."""
    plot = (
        _img(plot_budget(budgets, f"{scene.name}: whose error is it?"), f"error budget of {scene.name}")
        if budgets
        else ""
    )
    return plot + f"<p>{html.escape(budget_verdict(budgets))}</p>"


def _reaction_html(scene, ref, reactions: dict) -> str:
    """On a dynamic scene with a tool: the tool's force over time, the reference's and the models'."""
    if scene.time.mode != "dynamic" or not scene.problem.tools:
        return ""
    plot = plot_reaction(ref.times, ref.reaction, reactions, f"{scene.name}: force on the tool")
    return "<h3>The tool's force over time</h3>" + _img(plot, "tool force")


def _diverged_html(rows: list[Row]) -> str:
    """The runs that blew up (the steps beyond each model's limit are run on purpose), folded, and those
    that did not settle."""
    bad = [r for r in rows if r.status == "diverged"]
    unsettled = [r for r in rows if r.status not in ("ok", "diverged")]
    out = ""
    if bad:
        out += (
            f"<details><summary>{len(bad)} runs beyond their stable step (run on purpose, to show each model's "
            f"limit)</summary>{_sweep_table(bad)}</details>"
        )
    if unsettled:
        out += (
            f"<details><summary>{len(unsettled)} runs that did not settle</summary>{_sweep_table(unsettled)}</details>"
        )
    return out


def _repairs(mesh) -> str:
    """What reading the mesh file repaired, as a sentence (empty for a clean mesh)."""
    return f" Read from its file with repairs: {html.escape('; '.join(mesh.notes))}." if mesh.notes else ""


def convergence_section() -> tuple[str, dict]:
    log("report: convergence")
    man = converge_manufactured(load_scene("manufactured"))
    tim = converge_time(load_scene("cantilever-dynamic"), models=(linear_tm.NAME,))
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
{_img(plot_convergence(man, "reference, manufactured solution", "h (m)", MANUFACTURED_ERROR), "reference convergence")}
{_img(plot_convergence(tim, "linear-tm, time step", "dt (s)", TIME_ERROR), "time convergence")}
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
<section id="stability">
<h2>Stability at the extremes: {STABILITY_SCENE}</h2>
<p>Models {", ".join(STABILITY_MODELS)} (all models: <code>tissuebench stability {STABILITY_SCENE}</code>).
Tolerance on rel_l2: {res["tol"]}; "(Nx)" is the error against the model's own error on the unchanged scene.</p>
<ul>{summary}</ul>
<details><summary>every case and model</summary><table>{head}{"".join(body)}</table></details>
</section>"""
    return text, res


def first_screen(scenes: list[dict], q: Question = DEFAULT_QUESTION) -> str:
    """The page's opening table, scene by scene: the advisor's pick for the question ``q``, its
    error with the interval the reference's own error bar allows (the true relative error lies within
    the measured one plus or minus the bar, by the triangle inequality), its rate and the verdict."""
    rows = []
    for d in scenes:
        a, est = d["advice"], d["reference"].get("ref_err_estimate")
        link = f"<a href='#{html.escape(d['scene'])}'>{html.escape(d['scene'])}</a>"
        if not a.get("model"):
            rows.append(
                f"<tr class='bad'><td>{link}</td><td colspan='4' style='text-align:left'>{html.escape(a['why'])}</td></tr>"
            )
            continue
        value = a["value"]
        interval = "reference unverified" if est is None else f"{max(value - est, 0.0):.3g} to {value + est:.3g}"
        step = "quasi-static" if a["dt"] is None else f"{a['integrator']}, dt = {a['dt']:.3g} s"
        mesh = f", mesh refined {refined_times(a['refine'])}" if a["refine"] else ""
        surely = "" if est is None else " whatever the reference's own error (the whole interval)"
        verdict = f"qualifies: {Question.answered(a)}{surely}"
        rows.append(
            f"<tr><td>{link}</td><td><b>{html.escape(a['model'])}</b> ({html.escape(step)}{mesh})</td>"
            f"<td>{value:.3g} ({interval})</td><td>{a['rate_hz']:.0f} Hz</td><td style='text-align:left'>{verdict}</td></tr>"
        )
    head = (
        f"<tr><th>scene</th><th>cheapest model for {q}{' (where a tool gives it a force)' if q.haptic_rate else ''}</th>"
        "<th>its rel_l2 (interval from the reference's bar)</th><th>its step rate</th><th>verdict</th></tr>"
    )
    return f"<table class='first'>{head}{''.join(rows)}</table>"
