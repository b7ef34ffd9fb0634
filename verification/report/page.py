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

from meshes.io import atomic_write_text
from verification.cache import git_commit, versions
from verification.report.common import CSS, REPORTS, make_report_dir
from verification.report.cutting import CUT_SCENE, cut_cells, cutting_section
from verification.report.sections import (
    DEFAULT_QUESTION,
    STABILITY_MODELS,
    STABILITY_SCENE,
    Question,
    convergence_section,
    first_screen,
    scene_section,
    section_fractions,
    stability_section,
)
from verification.runs.row import jsonable
from verification.scene_file import load_scene
from verification.studies.prefetch import advice_jobs, scene_jobs, settle_ahead, solve_references
from verification.studies.stability import FAILED_REFERENCES, reference_jobs, settle_cells
from verification.studies.sweep import default_fractions, sweep_csv

DEFAULT_SCENES = ["cantilever", "cantilever-pull", "cantilever-dynamic", "stiff-inclusion", "liver-press"]


def report_dir(scenes: list[str], out: str | None = None) -> tuple[str, Path]:
    """The report's name and directory, created now. Every scene is read first, so a bad one fails before
    any compute; a scene given as a path is named by its scene name, never by its path."""
    name = "default" if scenes == DEFAULT_SCENES else "-".join(load_scene(s).name for s in scenes)
    return name, make_report_dir(Path(out) if out else REPORTS / name)


def write_report(
    scenes: list[str] | None = None,
    out: str | None = None,
    fractions=None,
    studies: bool | None = None,
    question: Question = DEFAULT_QUESTION,
) -> Path:
    """Run everything the report shows and write it; returns the HTML file's path. The convergence and
    stability sections are part of the default report (``studies`` None) and optional otherwise. The
    advisor asks ``question`` of every scene."""
    scenes = scenes or DEFAULT_SCENES
    default = scenes == DEFAULT_SCENES
    studies = default if studies is None else studies
    name, outdir = report_dir(scenes, out)
    t0 = time.perf_counter()
    jobs = advice_jobs([load_scene(s) for s in scenes])  # every scene's section ends with advice
    if studies:
        jobs += reference_jobs(load_scene(STABILITY_SCENE)) + scene_jobs([load_scene(CUT_SCENE)])
    FAILED_REFERENCES.update(solve_references(jobs))  # the stability study does not solve these again
    # the sections' steps, the advisor's (its sweep runs the default ones) and the stability study's cells
    settle_ahead(
        [
            (scene, tuple(dict.fromkeys([*section_fractions(scene, fractions), *default_fractions(scene)])))
            for scene in map(load_scene, scenes)
        ],
        cells=[*settle_cells(load_scene(STABILITY_SCENE), STABILITY_MODELS), *cut_cells()] if studies else (),
    )
    sections, data = [], {"scenes": []}
    for s in scenes:
        sec, d = scene_section(s, fractions, question)
        sections.append(sec)
        data["scenes"].append(d)
    if studies:
        for fn, key in (
            (convergence_section, "convergence"),
            (stability_section, "stability"),
            (cutting_section, "cutting"),
        ):
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
    data["question"] = {"tol": question.tol, "rate_hz": question.rate, "haptic_rate_hz": question.haptic_rate}
    names = [d["scene"] for d in data["scenes"]]
    nav = "".join(f"<a href='#{html.escape(s)}'>{html.escape(s)}</a> " for s in names)
    page = f"""<!doctype html><html><head><meta charset="utf-8"><title>tissuebench report: {html.escape(name)}</title>
<style>{CSS}</style></head><body>
<h1>tissuebench report: {html.escape(name)}</h1>
<p>What each real-time model gives up for its speed on these scenes: the cheapest model that meets the tolerance at the
rate, scene by scene, then each scene in detail. Errors are relative to a dolfinx reference and shown with the interval
its own error estimate allows. Step times are medians of repeated compiled n-step calls after a warm-up, on this
machine.</p>
<p>Commit {html.escape(meta["commit"])}, {meta["date"]}, {html.escape(json.dumps(meta["versions"]))}; written in {meta["wall_s"]:.0f} s.
Data: <a href="data.json">data.json</a>, <a href="runs.csv">runs.csv</a>. Scenes: {nav}</p>
{first_screen(data["scenes"], question)}
{"".join(sections)}
</body></html>"""
    outdir.mkdir(parents=True, exist_ok=True)
    atomic_write_text(outdir / "data.json", json.dumps(data, indent=1, default=jsonable))
    csv = "scene," + sweep_csv(data["scenes"][0]["sweep"]).splitlines()[0] + "\n"
    for d in data["scenes"]:
        csv += "".join(f"{d['scene']},{line}\n" for line in sweep_csv(d["sweep"]).splitlines()[1:])
    atomic_write_text(outdir / "runs.csv", csv)
    return atomic_write_text(outdir / "index.html", page).resolve()
