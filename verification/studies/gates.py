"""CI accuracy gates, gold regressions as in MOOSE's and FEBio's test suites: a gates.toml of (scene,
model, integrator, time step, metric, bound) with the baseline each was measured at (value, commit,
mesh hash, solver options, date).

``tissuebench gate`` runs them, prints a table and exits 1 when a gate fails, saying why: the measured
value exceeds its bound (the decision), or is within it while the reference's bar lets the true value
reach over it or is unknown (not decided: a pass the truth cannot confirm is no pass), or it moved from its baseline by more than ``drift`` (relative,
default DEFAULT_DRIFT: a change nobody decided on, better or worse), or the baseline no longer
describes what the gate measures (``stale``): the scene's mesh, the scene itself (its material,
loads, regions, time and mesh tags: the scene's hash) or the reference's solver options differ from
those the baseline recorded, or it recorded none of them. ``--quick`` runs the gates marked quick (the
test suite does); ``--update-baselines`` records the measured values and what they were measured on
(the bounds stay as they are: a bound is a decision, a baseline a measurement).
"""

from __future__ import annotations

import json
import math
import time
import tomllib
from pathlib import Path

from meshes.io import atomic_write_text
from realtime import INTEGRATORS, MODELS
from realtime.errors import InputError
from verification.cache import git_commit
from verification.engines import load_engine
from verification.metrics import METRICS
from verification.runs.row import Row
from verification.runs.store import cached_compare
from verification.scene import SceneError
from verification.scene_file import load_scene
from verification.studies.judge import judge

DEFAULT_CONFIG = Path(__file__).parent / "gates.toml"
KEYS = (
    "scene", "model", "integrator", "fraction", "metric", "bound", "drift", "quick", "note", "baseline", "engine",
    "result",
)  # fmt: skip
#: How far (relative) a measured value may move from its baseline before the gate fails.
DEFAULT_DRIFT = 0.1


def load_gates(path: Path) -> list[dict]:
    try:
        data = tomllib.loads(Path(path).read_text(encoding="utf-8-sig"))  # -sig: an editor's byte-order mark
    except (OSError, tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
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
        models = _models(g, where, Path(path))
        for k, allowed in (
            ("metric", METRICS),
            ("model", models),
            ("integrator", tuple(INTEGRATORS)),
        ):
            if k in g and g[k] not in allowed:
                raise SceneError(f"{where}.{k}: {g[k]!r} is not one of {', '.join(allowed)}")
        for k in ("bound", "fraction", "drift"):
            v = g.get(k, 1.0)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v <= 0:
                raise SceneError(f"{where}.{k}: must be a finite number > 0, got {v!r}")
        for k, kind in (("scene", str), ("note", str), ("quick", bool), ("baseline", dict), ("result", str)):
            if k in g and not isinstance(g[k], kind):
                raise SceneError(f"{where}.{k}: must be a {kind.__name__}, got {g[k]!r}")
        load_scene(g["scene"])  # a scene that does not exist or does not load fails here, before any run
    return gates


def run_gates(
    path: Path = DEFAULT_CONFIG, quick: bool = False, use_cache: bool = True, baselines: bool = True
) -> list[dict]:
    """Run the gates; each row says whether it passed and, if not, why. ``baselines`` False checks the
    bounds only (when the baselines are about to be measured again)."""
    rows = []
    for i, g in enumerate(load_gates(path)):
        if quick and not g.get("quick", False):
            continue
        scene = load_scene(g["scene"])
        r = _measured(scene, g, Path(path), use_cache)
        value = getattr(r, g["metric"]) if r.ok else None
        mesh_sha = scene.mesh.sha256()
        why = []
        if value is None:
            why.append(f"no value ({r.status})")
        elif value > g["bound"]:
            why.append(f"{value:.4g} exceeds the bound {g['bound']:.4g}")
        else:
            why += _undecided(r, g["metric"], value, g["bound"])
        base = g.get("baseline") or {}
        if baselines and value is not None and base.get("value") is not None:
            drift = g.get("drift", DEFAULT_DRIFT)
            moved = abs(value - base["value"]) / max(abs(base["value"]), 1e-300)
            if moved > drift:
                why.append(
                    f"moved {100 * moved:.1f}% from its baseline {base['value']:.4g} ({base.get('commit', '?')}), "
                    f"more than the {100 * drift:g}% allowed"
                )
        if baselines and base:
            why += stale(base, mesh_sha, scene.sha256(), _solver(r.reference))
        passed = not why
        rows.append(
            {
                "index": i,
                "scene": g["scene"],
                "model": g["model"],
                "metric": g["metric"],
                "bound": g["bound"],
                "value": value,
                "status": r.status,
                "passed": passed,
                "why": "; ".join(why),
                "baseline": g.get("baseline"),
                "mesh_sha256": mesh_sha,
                "scene_sha256": scene.sha256(),
                "dt": r.dt,
                "integrator": r.integrator,
                "reference": r.reference,
            }
        )
    return rows


def _undecided(r: Row, metric: str, value: float, bound: float) -> list[str]:
    """Why a value within its bound is still no pass: the true value lies within the value plus or minus
    the reference's bar on the metric (``frame.reference_bar``), and that interval reaches over the
    bound, or the bar is unknown (the reference unverified). A gate passes what the truth can decide."""
    from verification.studies.frame import reference_bar

    bar = reference_bar(r, metric)
    if bar is None:
        return [
            f"{value:.4g} is within the bound, but the reference's bar on {metric} is unknown (unverified): not decided"
        ]
    if value + bar > bound:
        return [
            f"{value:.4g} is within the bound {bound:.4g}, but the reference's bar {bar:.3g} lets the true value reach "
            f"{value + bar:.4g}: not decided (a sharper truth, or a bound it can decide)"
        ]
    return []


def _models(g: dict, where: str, path: Path) -> tuple[str, ...]:
    """The models a gate may name: the built-in ones, a plug-in ``engine``'s (loaded now), or, for a
    gate on a ``result`` file (relative to the gates file), any label."""
    if "result" in g:
        result = path.parent / g["result"]
        if not result.is_file():
            raise SceneError(f"{where}.result: no file {result}")
        return (g.get("model"),)
    if "engine" in g:
        try:
            return tuple(load_engine(g["engine"]).models)
        except InputError as exc:
            raise SceneError(f"{where}.engine: {exc}") from None
    return tuple(MODELS)


def _measured(scene, g: dict, path: Path, use_cache: bool) -> Row:
    """A gate's run: a result file judged (``studies.judge``), or a model (a plug-in's too) through the
    run cache."""
    if "result" in g:
        out = judge(scene, str(path.parent / g["result"]))
        fields = {k: out[k] for k in (*METRICS, "ref_err_estimate", "rel_l2_interval")}
        return Row(scene.name, g["model"], "result file", "ok", reference=out["reference"], **fields)
    return cached_compare(
        scene, g["model"], g.get("integrator", "symplectic-euler"), None, g.get("fraction"), use_cache=use_cache
    )


def _solver(ref: dict | None) -> str:
    """The reference's PETSc options of a run's row, as the canonical JSON a baseline records."""
    opts = (ref or {}).get("petsc_options")
    return json.dumps(opts, sort_keys=True) if opts else "?"


def stale(base: dict, mesh_sha: str, scene_sha: str, solver: str) -> list[str]:
    """Why a baseline no longer describes what its gate measures, one phrase a reason (none: it does).
    The rule: the baseline must name the mesh, the scene and the reference's solver options it was
    measured with, and each must be today's. A value measured on another problem or with another
    solver cannot tell drift from change, so the gate fails until --update-baselines re-measures it."""
    out = []
    if base.get("mesh_sha256") and base["mesh_sha256"] != mesh_sha:
        out.append(f"the mesh changed: hash {mesh_sha[:12]}, the baseline's {base['mesh_sha256'][:12]}")
    if not base.get("scene_sha256"):
        out.append("the baseline records no scene hash (material, loads, regions): re-measure with --update-baselines")
    elif base["scene_sha256"] != scene_sha:
        out.append(
            f"the scene changed (material, loads, regions, time or mesh tags): hash {scene_sha[:12]}, the baseline's "
            f"{base['scene_sha256'][:12]}; re-measure with --update-baselines"
        )
    if base.get("solver") and base["solver"] != solver:
        out.append(
            f"the reference's solver changed: {solver}, the baseline's {base['solver']}; re-measure with --update-baselines"
        )
    return out


def format_gates(rows: list[dict]) -> str:
    out = [f"{'':<5} {'scene':<18} {'model':<16} {'metric':<16} {'measured':>10} {'bound':>10} {'baseline':>10}"]
    for r in rows:
        v = "diverged" if r["value"] is None else f"{r['value']:.4g}"
        b = "-" if not r["baseline"] else f"{r['baseline']['value']:.4g}"
        out.append(
            f"{'PASS' if r['passed'] else 'FAIL':<5} {r['scene']:<18} {r['model']:<16} {r['metric']:<16} "
            f"{v:>10} {r['bound']:>10.4g} {b:>10}" + (f"  {r['why']}" if r["why"] else "")
        )
    failed = sum(not r["passed"] for r in rows)
    out.append(f"{len(rows) - failed} passed, {failed} failed")
    return "\n".join(out)


def update_baselines(path: Path, rows: list[dict]) -> None:
    """Rewrite the file with each run gate's baseline = the measured value and its provenance."""
    gates = load_gates(path)
    stamp = time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime())
    for r in rows:
        ref = r.get("reference") or {}
        gates[r["index"]]["baseline"] = {
            "value": r["value"],
            "commit": git_commit(),
            "mesh_sha256": r["mesh_sha256"],
            "scene_sha256": r["scene_sha256"],
            "solver": _solver(ref),
            "date": stamp,
            # the settings the runs used, read from their results
            "options": f"{r['integrator']} at dt = {r['dt']} s; reference {ref.get('law')} P{ref.get('degree')} "
            f"refine {ref.get('refine')} (returned level {ref.get('returned_level')})",
        }
    lines = [
        "# CI accuracy gates: tissuebench gate [--quick] [--update-baselines]. A gate fails when the measured",
        "# metric exceeds its bound or the reference's bar lets it reach over it, when it moves from its",
        f"# baseline by more than drift (relative, default {DEFAULT_DRIFT}), or when the scene's mesh is not the",
        "# baseline's. Bounds and drifts are decisions (edit",
        "# them by hand); baselines are measurements, with where they came from (--update-baselines).",
        "",
    ]
    for g in gates:
        lines.append("[[gate]]")
        for k in (
            "scene",
            "model",
            "engine",
            "result",
            "integrator",
            "fraction",
            "metric",
            "bound",
            "drift",
            "quick",
            "note",
        ):
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
