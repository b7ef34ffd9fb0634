"""Stability at the extremes (docs/promises.md): the largest stable step of every
explicit model, and what each model does as nu -> 0.5, over E, under a large twist or compression,
and with a sliver element."""

from __future__ import annotations

import dataclasses
import json

import numpy as np

from realtime import MODELS
from realtime.models import linear_tm, stvk_tm
from verification.engines import spec_of
from verification.progress import Bar
from verification.runs.store import cached_compare
from verification.scene import Scene, SceneError
from verification.studies.prefetch import settle_ahead, solve_references
from verification.studies.stable_step import largest_stable_fraction

EXTREME_POISSON = (0.3, 0.45, 0.49, 0.4999)
#: Steps a static relaxation may take in the stability study before the cell is "not settled".
STABILITY_BUDGET = 200_000
#: The stability study's references: P2 without the refined solve behind the error estimate (ten
#: variants of a scene, each a non-linear solve: the estimate would triple the cost).
#: References that could not be solved in this process, by scene hash (they are not cached on disk).
FAILED_REFERENCES: dict[str, str] = {}
STABILITY_REFERENCE = {"degree": 2, "refine": 0, "estimate": False, "newton_steps": 1, "min_increment": 1e-2}
EXTREME_YOUNG = (1e3, 1e5, 1e7)


def _far_face_tool(scene: Scene, kind: str):
    """A variant of a scene whose loads are replaced by one tool on the face of largest x: a 90 degree
    twist about the x axis ("rotation") or a push to half the length ("compression")."""
    from meshes.regions import BoxRegion
    from reference.problem import Displacement, Problem

    lo, hi = scene.mesh.bounding_box()
    eps = 1e-6 * float((hi - lo).max())
    region = BoxRegion((float(hi[0]) - eps, -1e9, -1e9), (1e9, 1e9, 1e9))
    centre = (float(hi[0]), float(0.5 * (lo[1] + hi[1])), float(0.5 * (lo[2] + hi[2])))
    if kind == "rotation":
        tool = Displacement(region=region, axis=(1.0, 0.0, 0.0), center=centre, angle=90.0, ramp=1.0)
    else:
        tool = Displacement(region=region, translation=(-0.5 * float(hi[0] - lo[0]), 0.0, 0.0), ramp=1.0)
    raw = json.loads(json.dumps(scene.raw))
    raw["load"] = [{"variant": kind}]
    return dataclasses.replace(
        scene, name=f"{scene.name}-{kind}", problem=Problem(scene.problem.fixed, (tool,)), raw=raw
    )


def _sliver_variant(scene: Scene):
    """The scene on its mesh with one interior vertex moved to make a sliver of its closest tetrahedron:
    the vertex is pushed to 2% of its height above the opposite face (aspect ratio ~50)."""
    from meshes import TetMesh

    mesh = scene.mesh
    interior = np.setdiff1d(np.arange(mesh.n_vertices), mesh.surface_vertices)
    pts = mesh.points.copy()
    if len(interior) == 0:
        return None
    v = int(interior[len(interior) // 2])
    tets = np.flatnonzero(np.any(mesh.tets == v, axis=1))
    best = None
    for t in tets:
        others = [int(w) for w in mesh.tets[t] if w != v]
        a, b, c = pts[others]
        n = np.cross(b - a, c - a)
        n /= np.linalg.norm(n)
        h = float(np.dot(pts[v] - a, n))
        target = pts[v] - 0.98 * h * n
        trial = pts.copy()
        trial[v] = target
        vol = np.linalg.det(
            np.stack([trial[mesh.tets[tets, k]] - trial[mesh.tets[tets, 0]] for k in (1, 2, 3)], axis=2)
        )
        if np.all(vol > 0):
            best = trial
            break
    if best is None:
        return None
    raw = json.loads(json.dumps(scene.raw))
    raw["mesh"] = {"sliver_of": scene.mesh.sha256()}
    sliver = TetMesh(best, mesh.tets, vertex_tags=mesh.vertex_tags, source=f"{mesh.source} with a sliver at vertex {v}")
    return dataclasses.replace(scene, name=f"{scene.name}-sliver", raw=raw, _mesh=sliver)


def _cell(scene: Scene, model: str, integrator: str, tol: float, baseline: float | None, use_cache: bool) -> dict:
    from realtime import NotConvergedError
    from reference.errors import ReferenceSolveError

    if scene.sha256() in FAILED_REFERENCES:  # a reference that failed once fails again: do not re-solve it
        return _alone(scene, model, integrator, f"no reference ({FAILED_REFERENCES[scene.sha256()]})")
    try:
        row = cached_compare(
            scene,
            model,
            integrator,
            None,
            None,
            None,
            ref_opts=STABILITY_REFERENCE,
            use_cache=use_cache,
            max_steps=STABILITY_BUDGET,
            budget=False,  # the extremes ask what a model does, not whose error is whose
        )
    except ReferenceSolveError as exc:
        FAILED_REFERENCES[scene.sha256()] = str(exc)
        return _alone(scene, model, integrator, f"no reference ({exc})")
    except NotConvergedError as exc:
        return {"status": "not settled", "detail": str(exc)}
    if row.status != "ok":
        return {
            "status": "diverged",
            "detail": f"at step {row.step} (dt {row.dt:.3g} s, critical {row.dt_crit:.3g} s)",
            "dt": row.dt,
            "dt_crit": row.dt_crit,
        }
    status = "ok" if row.rel_l2 <= tol else "inaccurate"
    ref = row.reference or {}
    out = {
        "status": status,
        "rel_l2": row.rel_l2,
        # the extremes are where a reference is least reliable: say what is known of it
        "reference": "verified" if ref.get("verified") else "reference unverified",
        "ref_err_estimate": ref.get("ref_err_estimate"),
        "ref_min_det_F": ref.get("min_det_F"),
        "dt": row.dt,
        "dt_crit": row.dt_crit,
        "step_us": row.step_us,
        "settle_steps": row.settle_steps,
        "settle_ms": row.settle_ms,
    }
    if baseline:
        out["vs_baseline"] = row.rel_l2 / baseline
    return out


def _alone(scene: Scene, model: str, integrator: str, why: str) -> dict:
    """A cell whose reference failed (buckling, StVK softening): the model's own fate, and how many of
    its elements ended inverted (settled, or where a run that did not settle stopped)."""
    from realtime import DivergenceError, NotConvergedError
    from realtime.geometry import signed_volumes
    from verification.runs.simulate import run_model

    def inverted(u: np.ndarray) -> int:
        return int(np.sum(signed_volumes(scene.mesh.points + u[: scene.mesh.n_vertices], scene.mesh.tets) <= 0.0))

    try:
        res = run_model(scene, model, integrator=integrator, max_steps=STABILITY_BUDGET)
    except DivergenceError as exc:
        return {"status": "diverged", "detail": f"{why}; the model diverged at step {exc.step}"}
    except NotConvergedError as exc:
        out = {"status": "not settled", "detail": f"{why}; the model did not settle in {STABILITY_BUDGET} steps"}
        if exc.u is not None:  # where it stopped: whether it had turned elements inside out on its way
            out["inverted"] = inverted(exc.u)
            out["detail"] += f", and stopped with {out['inverted']} inverted elements"
        return out
    n = inverted(res.displacement[-1])
    return {
        "status": "settled, no reference",
        "inverted": n,
        "detail": f"{why}; the model settled with {n} inverted elements",
    }


def _cases(scene: Scene) -> list[tuple[str, float, Scene]]:
    """The extremes: (case, value, variant of the scene)."""
    cases = []
    for nu in EXTREME_POISSON:
        cases.append(("poisson", nu, scene.with_material(poisson=nu)))
    for E in EXTREME_YOUNG:
        cases.append(("young", E, scene.with_material(young=E)))
    for kind in ("rotation", "compression"):
        cases.append((kind, 90.0 if kind == "rotation" else 0.5, _far_face_tool(scene, kind)))
    sliver = _sliver_variant(scene)
    if sliver is not None:
        cases.append(("sliver", sliver.mesh.quality()["max_aspect_ratio"], sliver))
    return cases


def _integrators(what: str, value: float, model: str) -> tuple[str, ...]:
    """The integrators a case's cell runs ``model`` with: implicit Euler too for linear-tm and stvk-tm
    at nu >= 0.49, where the explicit step shrinks with the stiffening volume."""
    implicit = what == "poisson" and value >= 0.49 and model in (linear_tm.NAME, stvk_tm.NAME)
    return ("symplectic-euler", "implicit-euler") if implicit else ("symplectic-euler",)


def settle_cells(scene: Scene, models, cases=None) -> list[tuple[Scene, str, str, int]]:
    """The settlings the stability study of ``scene`` makes (for ``prefetch.settle_ahead``): (scene or
    variant, model, integrator, STABILITY_BUDGET) for its baselines and each case's cells; the
    quasi-static models do not settle."""
    explicit = [m for m in models if not spec_of(m).quasi_static]
    cells = [(scene, m, "symplectic-euler", STABILITY_BUDGET) for m in explicit]
    for what, value, variant in _cases(scene) if cases is None else cases:
        cells += [(variant, m, i, STABILITY_BUDGET) for m in explicit for i in _integrators(what, value, m)]
    return cells


def reference_jobs(scene: Scene) -> list[tuple[Scene, dict]]:
    """The references the stability study of ``scene`` solves (for ``prefetch.solve_references``)."""
    return [(scene, STABILITY_REFERENCE)] + [(variant, STABILITY_REFERENCE) for _, _, variant in _cases(scene)]


def stability(scene: Scene, models=None, tol: float = 0.1, use_cache: bool = True) -> dict:
    """The largest stable explicit step of every model against its predicted critical step, and what
    each model does at the extremes: nu -> 0.4999 (explicit and implicit), E from 1 kPa to 10 MPa,
    a 90 degree twist, compression to half the length, a sliver element. A cell is ok, inaccurate
    (rel_l2 above tol), diverged (with the step) or not settled; where the reference itself cannot
    follow (buckling, StVK softening) it gives the model's own fate: settled (with its inverted
    elements), diverged or not settled."""
    if scene.time.mode != "static":
        raise SceneError(f"{scene.path}: stability studies a static scene (time.mode = static)")
    models = list(models or MODELS)
    explicit = [m for m in models if not spec_of(m).quasi_static]
    cases = _cases(scene)
    if use_cache:
        jobs = [job for job in reference_jobs(scene) if job[0].sha256() not in FAILED_REFERENCES]
        FAILED_REFERENCES.update(solve_references(jobs))
        settle_ahead([], cells=settle_cells(scene, models, cases))
    progress = Bar(len(explicit) + len(cases) * len(models), f"stability {scene.name}")
    limits = {}
    for m in explicit:
        limits[m] = largest_stable_fraction(scene, m, use_cache=use_cache)
        progress.step(f"{m} largest stable step")
    baselines = {}
    for m in models:
        base = _cell(scene, m, "symplectic-euler", tol, None, use_cache)
        baselines[m] = base.get("rel_l2")
    table = []
    for what, value, variant in cases:
        row = {"case": what, "value": value, "models": {}}
        for m in models:
            for integrator in _integrators(what, value, m):
                key = m if integrator == "symplectic-euler" else f"{m} (implicit)"
                row["models"][key] = _cell(variant, m, integrator, tol, baselines.get(m), use_cache)
            progress.step(f"{what}={value} {m}")
        table.append(row)
    return {
        "scene": scene.name,
        "tol": tol,
        "limits": limits,
        "baselines": baselines,
        "table": table,
        "summary": _stability_summary(limits, baselines, table),
    }


def _stability_summary(limits, baselines, table) -> list[str]:
    lines = []
    for m, lim in limits.items():
        if lim.get("stable") is not None:
            lines.append(
                f"{m}: stable up to {lim['stable']:.3g} x the predicted critical step "
                f"({lim['dt_crit']:.3g} s), unstable at {lim['unstable']:.3g} x"
                if lim.get("unstable")
                else f"{m}: stable at every step tried"
            )
    nearly = next((r for r in table if r["case"] == "poisson" and r["value"] == max(EXTREME_POISSON)), None)
    if nearly:
        locks = [m for m, c in nearly["models"].items() if c.get("vs_baseline", 0) > 2.0]
        fine = [m for m, c in nearly["models"].items() if c.get("status") == "ok"]
        lines.append(
            f"nu = {nearly['value']}: error more than doubles (locking) for {', '.join(locks) or 'none'}; "
            f"within tolerance: {', '.join(fine) or 'none'}"
        )
        for m in (linear_tm.NAME, stvk_tm.NAME):
            ex, im = nearly["models"].get(m, {}), nearly["models"].get(m + " (implicit)", {})
            if ex.get("settle_ms") and im.get("settle_ms"):
                lines.append(
                    f"nu = {nearly['value']}: {m} explicit settles in {ex['settle_steps']} steps of "
                    f"{ex['dt']:.2g} s ({ex['settle_ms']:.0f} ms), implicit in {im['settle_steps']} steps of "
                    f"{im['dt']:.2g} s ({im['settle_ms']:.0f} ms)"
                    + ("; needs the implicit integrator" if im["settle_ms"] < ex["settle_ms"] else "")
                )
            elif ex.get("status") in ("not settled", "diverged"):
                lines.append(f"nu = {nearly['value']}: {m} explicit {ex['status']}; implicit {im.get('status')}")
    return lines


def format_stability(res: dict) -> str:
    out = [f"stability {res['scene']} (tolerance on rel_l2: {res['tol']})"]
    out += ["  " + line for line in res["summary"]]
    for row in res["table"]:
        out.append(f"{row['case']} = {row['value']:.4g}:")
        for m, c in row["models"].items():
            extra = f" rel_l2 {c['rel_l2']:.3g}" if "rel_l2" in c else ""
            extra += f", dt_crit {c['dt_crit']:.3g} s" if c.get("dt_crit") else ""
            extra += f" ({c['vs_baseline']:.2g} x baseline)" if "vs_baseline" in c else ""
            extra += ", reference unverified" if c.get("reference") == "reference unverified" else ""
            extra += f" {c['detail']}" if "detail" in c else ""
            out.append(f"    {m:<28} {c['status']:<16}{extra}")
    return "\n".join(out)
