"""The engines page (``tissuebench engines SCENE... --report DIR``): per scene, every engine's solvers and the
built-in models on one error-against-step-time plot, each solver's largest stable step, whether its answer
depends on its iteration count, and its two distances (from P1 of the scene's law and from P1 of its own
law on the same mesh), with the device each ran on, the engines' versions and the machine.

Every number on it is a run of the study (``verification.studies.engines``) the command made or read from
the cache, which records the run that made it.
"""

from __future__ import annotations

import html
import json
import time
from pathlib import Path

from meshes.io import atomic_write_text
from verification.cache import git_commit, installed_versions, machine_id, versions
from verification.engines.adapters import ADAPTERS, engines_python
from verification.report.common import CSS, fmt
from verification.report.plots import plot_engines
from verification.runs.compare import cancelling
from verification.runs.row import jsonable
from verification.studies.engines import ITERATION_DT, run_line, stable_text

#: The distributions of the engines' venv the page names (PyPI's names).
ENGINE_DISTRIBUTIONS = ("newton", "warp-lang", "mujoco", "mujoco-warp")


def home_of(model: str) -> tuple[str, str]:
    """The adapter's name and its engine's home device ("cuda", "cpu") for one of its models."""
    for name, engine in ADAPTERS.items():
        if model in engine.solvers:
            return name, engine.home_device
    return "?", "cpu"


def ran_on(study: dict, model: str) -> str | None:
    """The device ``model``'s runs in ``study`` ran on: as its adapter said, else as they asked (an adapter
    runs on the device asked or refuses; on warp's CPU when none is asked); None where it has no run."""
    runs = [r for r in study["runs"] if r["model"] == model]
    for r in runs:
        if (r.get("engine") or {}).get("device"):
            return r["engine"]["device"]
    return (runs[0].get("options") or {}).get("device", "cpu") if runs else None


def off_home(studies: list[dict]) -> list[str]:
    """The models that ran off their engine's home device (a GPU engine on warp's CPU), each once."""
    out = {}
    for study in studies:
        for s in study["summary"]:
            device = ran_on(study, s["model"])
            home = home_of(s["model"])[1]
            if device is not None and not device.startswith(home):
                out[s["model"]] = f"{s['model']} ran on {device}, its engine is built for {home}"
    return list(out.values())


def _iterations(s: dict) -> str:
    it = s.get("iterations")
    if not it:
        return "-"
    d = it["depends"]
    why = d.get("why", "")
    if "distance" in d:
        why = f"answers of {d['between'][0]} and {d['between'][1]} iterations {d['distance']:.2g} apart"
        why += f" (floor {d['floor']:.2g})"
    return f"<b>{html.escape(d['verdict'])}</b>: {html.escape(why)}"


def _summary_table(study: dict) -> str:
    mesh = study.get("mesh_error")
    head = (
        "<tr><th>model</th><th>engine, as its adapter ran it</th><th>device</th><th>the scene's law mapped to</th>"
        "<th>best rel_l2 (its dt)</th><th>step, us</th><th>from P1 of the scene's law, same mesh</th>"
        "<th>from P1 of its own law, same mesh (its numerics)</th><th>largest stable step</th>"
        f"<th>answer by iterations at {ITERATION_DT:g} s</th></tr>"
    )
    body = []
    for s in study["summary"]:
        name = html.escape(s["model"])
        if s.get("not_applicable"):
            body.append(f"<tr><td>{name}</td><td colspan=9 style='text-align:left'>not applicable: "
                        f"{html.escape(s['not_applicable'])}</td></tr>")  # fmt: skip
            continue
        engine = s.get("engine") or {}
        device, home = ran_on(study, s["model"]), home_of(s["model"])[1]
        where = "-" if device is None else html.escape(device)
        if device is not None and not device.startswith(home):
            where += f" <b>(off its home device, {home})</b>"
        b = s.get("best")
        if b is None:
            best, step, own_part, own_law = "no run reached an answer", "-", "-", "-"
        else:
            best = f"{fmt(b['rel_l2'])} ({fmt(b['dt'])} s)"
            if cancelling(b["rel_l2"], mesh, b.get("model_part")):
                best += " <b>right for a wrong reason</b>: below the mesh's own error"
            step, own_part = fmt(b["step_us"], ".4g"), fmt(b.get("model_part"))
            law = b.get("own_law") or {}
            own_law = (
                "-"
                if not law
                else f"{fmt(law.get('rel_l2'))} ({html.escape(law['law'])})"
                + (f": {html.escape(law['why'])}" if law.get("why") else "")
            )
        body.append(
            f"<tr><td>{name}</td><td style='text-align:left'>{fmt(engine.get('engine'))}</td><td>{where}</td>"
            f"<td style='text-align:left'>{fmt(engine.get('law'))}</td><td>{best}</td><td>{step}</td>"
            f"<td>{own_part}</td><td>{own_law}</td><td>{stable_text(s)}</td><td style='text-align:left'>{_iterations(s)}</td></tr>"
        )
    return f"<table>{head}{''.join(body)}</table>"


def _builtin_table(study: dict) -> str:
    if not study.get("builtin"):
        return ""
    rows = []
    for b in study["builtin"]:
        stable = "quasi-static" if b["dt"] is None else fmt(b["largest_stable_dt"])
        rows.append(
            f"<tr><td>{html.escape(b['model'])}</td><td>{html.escape(b['status'])}</td><td>{fmt(b['rel_l2'])}</td>"
            f"<td>{fmt(b['dt'])}</td><td>{fmt(b['step_us'], '.4g')}</td><td>{fmt(b['model_part'])}</td><td>{stable}</td></tr>"
        )
    return (
        "<h3>The built-in models, in the same run</h3><p>Each at its default step (0.9 of its critical one, or its "
        "quasi-static update); its largest stable step by the same probe from rest.</p><table><tr><th>model</th>"
        "<th>status</th><th>rel_l2</th><th>dt, s</th><th>step, us</th><th>from P1 of the scene's law</th>"
        f"<th>largest stable step, s</th></tr>{''.join(rows)}</table>"
    )


def scene_html(study: dict) -> str:
    """One scene's section of the page."""
    name = html.escape(study["scene"])
    est, mesh = study.get("reference_estimate"), study.get("mesh_error")
    runs = "\n".join(html.escape(run_line(r)) for r in study["runs"])
    stopped = (
        f"<p class='bad'>{html.escape(study['stopped'])}: this section is partial.</p>" if study.get("stopped") else ""
    )
    return f"""<h2 id="{name}">{name}</h2>{stopped}
<p>The reference's own error estimate: {fmt(est)}. The mesh's own error (P1 of the scene's law on this mesh against
the reference, what every engine on this mesh pays): {fmt(mesh)}. An engine's error below the mesh's while its distance
from that P1 solution is over half of it is errors cancelling: right for a wrong reason.</p>
<img src="data:image/png;base64,{plot_engines(study)}" alt="{name}: error against step time, every engine and model">
{_summary_table(study)}
{_builtin_table(study)}
<details><summary>Every run of the study ({len(study["runs"])})</summary><pre>{runs}</pre></details>"""


def engines_page_html(studies: list[dict], meta: dict) -> str:
    """The whole page, from the studies and the run's ``meta`` (commit, date, machine, versions)."""
    names = [s["scene"] for s in studies]
    away = off_home(studies)
    device_note = (
        "<p class='advice'><b>Off their home device.</b> " + "; ".join(map(html.escape, away)) + ". Their answers are "
        "the same on any device; their step times here are those of warp's CPU kernels, not of the GPU their users "
        "run them on (give --device cuda:0 on a machine that has one).</p>"
        if away
        else ""
    )
    nav = " ".join(f"<a href='#{html.escape(n)}'>{html.escape(n)}</a>" for n in names)
    m = meta["machine"]
    return f"""<!doctype html><html><head><meta charset="utf-8"><title>tissuebench engines: {html.escape(", ".join(names))}</title>
<style>{CSS}</style></head><body>
<h1>tissuebench engines: {html.escape(", ".join(names))}</h1>
<p>The engines users pick, each through its adapter and each solver with its own knobs, against the dolfinx reference
of the scene, beside the built-in models (docs/engines.md). Two distances tell an engine's law from its numerics: from P1
of the scene's law on the same mesh (its law and its numerics), and from P1 of the law it implements (its numerics
alone). Step times are each engine's own, timed by its adapter on this machine.</p>
<p>Commit {html.escape(meta["commit"])}, {meta["date"]}; {html.escape(m["cpu"])}, {m["cores"]} cores ({html.escape(m["arch"])}).
Versions: {html.escape(json.dumps(meta["versions"]))}; the engines' venv: {html.escape(json.dumps(meta["engines"]))}.
Written in {meta["wall_s"]:.0f} s. Data: <a href="data.json">data.json</a>. Scenes: {nav}</p>
{device_note}
{"".join(scene_html(s) for s in studies)}
</body></html>"""


def write_engines_page(studies: list[dict], outdir: Path, wall_s: float = 0.0) -> Path:
    """Write ``outdir``/index.html and data.json (each through a temporary file and a rename); returns
    the page's path."""
    have = installed_versions(engines_python())
    meta = {
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()),
        "machine": machine_id(),
        "versions": versions(),
        "engines": {d: have.get(d) for d in ENGINE_DISTRIBUTIONS},
        "wall_s": wall_s,
    }
    atomic_write_text(outdir / "data.json", json.dumps({"studies": studies, "meta": meta}, indent=1, default=jsonable))
    return atomic_write_text(outdir / "index.html", engines_page_html(studies, meta)).resolve()
