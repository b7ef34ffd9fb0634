"""What the report's pages share: the style sheet, where pages go, and how a number is printed."""

from __future__ import annotations

import html
from pathlib import Path

from verification.scene import SceneError

REPORTS = Path("reports")


def fmt(v, spec=".3g"):
    if v is None:
        return "-"
    if isinstance(v, float):
        return format(v, spec)
    return html.escape(str(v))


CSS = """body{font-family:system-ui,sans-serif;max-width:1250px;margin:2em auto;padding:0 1em;color:#222}
table{border-collapse:collapse;font-size:12px;margin:1em 0}td,th{border:1px solid #ccc;padding:3px 6px;text-align:right;vertical-align:top}
th{background:#f0f2f5}td.bad,tr.bad td{color:#a00}img{max-width:760px;display:block}img.wide{max-width:100%}
pre{background:#f6f8fa;padding:1em;font-size:12px}code{font-size:12px}p.advice{background:#eef6ee;padding:.6em}"""


def make_report_dir(outdir: Path) -> Path:
    """Create a report's directory now, before any compute; a path that cannot be one is a SceneError."""
    if outdir.exists() and not outdir.is_dir():
        raise SceneError(f"{outdir}: the report directory is an existing file")
    try:
        outdir.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"{outdir}: cannot create the report directory ({exc.strerror})") from None
    return outdir
