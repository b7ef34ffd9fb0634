"""CI accuracy gates: a gates.toml of (scene, model, integrator, time step, metric, bound) with the
baseline each bound was set from (value, commit, mesh hash, solver options, date).

``tissuebench gate`` runs them, prints a table and exits 1 if any measured value exceeds its bound;
``--quick`` runs the gates marked quick (the test suite does); ``--update-baselines`` records the
measured values and their provenance in the file (the bounds stay as they are: a bound is a decision,
a baseline a measurement).
"""

from __future__ import annotations

import math
import time
import tomllib
from pathlib import Path

from realtime import INTEGRATORS, MODELS

from .results import atomic_write_text
from .runner import REFERENCE_DEFAULTS, git_commit
from .scene import SceneError, load_scene
from .studies import cached_compare

DEFAULT_CONFIG = Path(__file__).parent / "gates.toml"
METRICS = ("rel_l2", "surface_rel_l2", "max_err", "reaction_rel_err", "volume_err")
KEYS = ("scene", "model", "integrator", "fraction", "metric", "bound", "quick", "note", "baseline")


def load_gates(path: Path) -> list[dict]:
    try:
        data = tomllib.loads(Path(path).read_text())
    except (OSError, tomllib.TOMLDecodeError) as exc:
        raise SceneError(f"{path}: cannot read the gates ({exc})") from None
    gates = data.get("gate")
    if not isinstance(gates, list) or not gates:
        raise SceneError(f"{path}: gate: needs at least one [[gate]] table")
    for i, g in enumerate(gates):
        for k in g:
            if k not in KEYS:
                raise SceneError(f"{path}: gate[{i}].{k}: unknown key (allowed: {', '.join(KEYS)})")
        for k in ("scene", "model", "metric", "bound"):
            if k not in g:
                raise SceneError(f"{path}: gate[{i}].{k}: missing key")
        where = f"{path}: gate[{i}]"
        for k, allowed in (
            ("metric", METRICS),
            ("model", tuple(MODELS)),
            ("integrator", tuple(INTEGRATORS)),
        ):
            if k in g and g[k] not in allowed:
                raise SceneError(f"{where}.{k}: {g[k]!r} is not one of {', '.join(allowed)}")
        for k in ("bound", "fraction"):
            v = g.get(k, 1.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise SceneError(f"{where}.{k}: must be a finite number > 0, got {v!r}")
        for k, kind in (("scene", str), ("note", str), ("quick", bool), ("baseline", dict)):
            if k in g and not isinstance(g[k], kind):
                raise SceneError(f"{where}.{k}: must be a {kind.__name__}, got {g[k]!r}")
        load_scene(g["scene"])  # a scene that does not exist or does not load fails here, before any run
    return gates


def run_gates(path: Path = DEFAULT_CONFIG, quick: bool = False, use_cache: bool = True) -> list[dict]:
    rows = []
    for i, g in enumerate(load_gates(path)):
        if quick and not g.get("quick", False):
            continue
        scene = load_scene(g["scene"])
        r = cached_compare(
            scene, g["model"], g.get("integrator", "symplectic-euler"), None, g.get("fraction"), use_cache=use_cache
        )
        value = r.get(g["metric"]) if r["status"] == "ok" else None
        passed = value is not None and value <= g["bound"]
        rows.append(
            {
                "index": i,
                "scene": g["scene"],
                "model": g["model"],
                "metric": g["metric"],
                "bound": g["bound"],
                "value": value,
                "status": r["status"],
                "passed": passed,
                "baseline": g.get("baseline"),
                "mesh_sha256": scene.mesh.sha256(),
                "dt": r.get("dt"),
                "integrator": r.get("integrator"),
            }
        )
    return rows


def format_gates(rows: list[dict]) -> str:
    out = [f"{'':<5} {'scene':<18} {'model':<16} {'metric':<16} {'measured':>10} {'bound':>10} {'baseline':>10}"]
    for r in rows:
        v = "diverged" if r["value"] is None else f"{r['value']:.4g}"
        b = "-" if not r["baseline"] else f"{r['baseline']['value']:.4g}"
        out.append(
            f"{'PASS' if r['passed'] else 'MISS':<5} {r['scene']:<18} {r['model']:<16} {r['metric']:<16} "
            f"{v:>10} {r['bound']:>10.4g} {b:>10}"
        )
    missed = sum(not r["passed"] for r in rows)
    out.append(f"{len(rows) - missed} passed, {missed} missed")
    return "\n".join(out)


def update_baselines(path: Path, rows: list[dict]) -> None:
    """Rewrite the file with each run gate's baseline = the measured value and its provenance."""
    gates = load_gates(path)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    for r in rows:
        gates[r["index"]]["baseline"] = {
            "value": r["value"],
            "commit": git_commit(),
            "mesh_sha256": r["mesh_sha256"],
            "date": stamp,
            "options": f"{r['integrator']} at dt = {r['dt']} s; reference P{REFERENCE_DEFAULTS['degree']} "
            f"refine {REFERENCE_DEFAULTS['refine']}, MUMPS LU",
        }
    lines = [
        "# CI accuracy gates: tissuebench gate [--quick] [--update-baselines]. A gate fails when the measured",
        "# metric exceeds its bound; the baseline records the value the bound was set against, and where it",
        "# came from. Bounds are decisions (edit them by hand); baselines are measurements (--update-baselines).",
        "",
    ]
    for g in gates:
        lines.append("[[gate]]")
        for k in ("scene", "model", "integrator", "fraction", "metric", "bound", "quick", "note"):
            if k in g:
                lines.append(f"{k} = {_toml(g[k])}")
        if g.get("baseline"):
            b = g["baseline"]
            lines.append("baseline = { " + ", ".join(f"{k} = {_toml(v)}" for k, v in b.items() if v is not None) + " }")
        lines.append("")
    atomic_write_text(path, "\n".join(lines))


def _toml(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, float)):
        return repr(v)
    return '"' + str(v).replace("\\", "\\\\").replace('"', '\\"') + '"'
