"""The seeds page (``tissuebench report --seeds``): each experiment of the source documents with its claim, the
rule that decided it, the numbers and the plots, its verdicts in one table first."""

from __future__ import annotations

import html
import json
import time
from pathlib import Path

from meshes.io import atomic_write_text
from verification.cache import git_commit, versions
from verification.figures import img as _img
from verification.report.common import CSS, REPORTS, fmt, make_report_dir


def rows_html(rows: list[dict]) -> str:
    """A list of flat dicts as a table, one column per key in first-seen order."""
    if not rows:
        return ""
    keys = list(dict.fromkeys(k for r in rows for k in r))
    head = "".join(f"<th>{html.escape(k)}</th>" for k in keys)
    body = "".join("<tr>" + "".join(f"<td>{html.escape(fmt(r.get(k)))}</td>" for k in keys) + "</tr>" for r in rows)
    return f"<table><tr>{head}</tr>{body}</table>"


def seeds_html(res: dict) -> str:
    """The seeds study (``verification.studies.seeds.run_seeds``) as a section: the table of verdicts, then each
    experiment with its claim, the rule that decided, the numbers and the plots."""
    verdicts = "".join(
        f"<tr class='{html.escape(f['verdict'])}'><td>{f['number']}</td><td><a href='#seed-{html.escape(f['key'])}'>"
        f"{html.escape(f['title'])}</a></td><td>{html.escape(f['source'])}</td><td style='text-align:left'>"
        f"{html.escape(f['claim'])}</td><td><b>{html.escape(f['verdict'])}</b></td><td style='text-align:left'>"
        f"{html.escape(f['decides'])}</td><td>{html.escape(reference_bar(f['reference']))}</td></tr>"
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
            + rows_html(f["table"])
            + f"<p>Truth: {html.escape(reference_bar(f['reference']))}; ran in {f.get('wall_s', 0):.0f} s.</p>"
        )
    return "".join(parts)


def reference_bar(ref: dict) -> str:
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
