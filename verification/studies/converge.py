"""Convergence studies: the reference's observed orders on a manufactured solution, nested mesh
refinement of a static scene (each model and the reference against one truth on the finest level),
and time-step halving of a dynamic scene."""

from __future__ import annotations

import numpy as np

from realtime.models import linear_tm, stvk_tm
from verification.progress import Bar
from verification.scene import Scene, SceneError


def converge_manufactured(scene: Scene) -> dict:
    """Observed orders of the reference on the scene's manufactured solution, P1 and P2."""
    from reference.manufactured import manufactured_errors

    spec = scene.manufactured
    out = {"scene": scene.name, "kind": "manufactured", "law": scene.material.law, "series": []}
    for degree in spec["degrees"]:
        sizes = spec["sizes"][str(degree)]
        runs = [manufactured_errors(scene.material.law, degree, n, scene.material) for n in sizes]
        h = np.array([r["h"] for r in runs])
        for norm, theory in (("l2", degree + 1), ("h1", degree)):
            e = np.array([r[norm] for r in runs])
            out["series"].append(
                {
                    "label": f"P{degree} {norm.upper()}",
                    "h": h.tolist(),
                    "error": e.tolist(),
                    "order": float(np.polyfit(np.log(h), np.log(e), 1)[0]),
                    "theory": theory,
                }
            )
    return out


def converge_space(scene: Scene, models=(linear_tm.NAME, stvk_tm.NAME), levels: int = 3) -> dict:
    """Nested mesh refinement: the scene's mesh and its uniform refinements (h, h/2, h/4, ...; the coarse
    vertices are vertices of every finer level), each model's error at each level's vertices against
    one P2 reference on the finest level, solved once, and the reference's own self-convergence (P1
    and P2 at each level against it). The geometry never changes, curved or not: refinement splits the
    coarse mesh's own tetrahedra. Orders are fitted against h. The reference solves come first, one
    process per core (``prefetch.static_displacements``), then the model runs. A scene with events (a
    cut) is studied in its last state, the body the events leave, which the result names."""
    from verification.events import states
    from verification.runs.simulate import run_model
    from verification.studies.prefetch import static_displacements

    if scene.time.mode != "static":
        raise SceneError(f"{scene.path}: converge --in space studies static scenes")
    if scene.level:
        raise SceneError(f"{scene.path}: converge --in space refines the scene's own mesh; leave out --refine")
    state = None
    if scene.events:  # each state's truth is its own body's: refine the state's mesh, not the meshed body
        last = states(scene)[-1]
        state, scene = last.label, last.scene
    scenes = [scene]
    for _ in range(levels - 1):
        scenes.append(scenes[-1].refined())
    meshes = [s.mesh for s in scenes]
    h0 = scene.mesh.mean_edge()
    hs = [h0 / 2**k for k in range(levels)]
    progress = Bar(1 + levels * (len(models) + 2), f"converge {scene.name}")
    base = dict(mesh=scene.mesh, material=scene.body_material(), problem=scene.problem, estimate=False)
    # the truth (P2 on the finest level, at its vertices) and P1 and P2 at each level but that one
    jobs = [dict(base, degree=2, refine=levels - 1, points=meshes[-1].points)]
    jobs += [dict(base, degree=d, refine=k, points=meshes[k].points) for k in range(levels) for d in (1, 2)]
    del jobs[-1]  # P2 on the finest level is the truth itself
    solved = static_displacements(
        jobs, done=lambda job: progress.step(f"level {job['refine']} reference P{job['degree']}")
    )
    fine, own = solved[0], iter(solved[1:])
    progress.step("the truth is P2 on the finest level")
    series = {m: [] for m in list(models) + ["reference P1", "reference P2"]}
    for k, mesh in enumerate(meshes):
        truth = fine[: mesh.n_vertices]  # nested: level k's vertices come first at every finer level
        scale = np.linalg.norm(truth)
        level = scenes[k]
        for m in models:
            u = run_model(level, m).displacement[-1]
            series[m].append(float(np.linalg.norm(u - truth) / scale))
            progress.step(f"level {k} {m}")
        for deg in (1, 2):
            if k == levels - 1 and deg == 2:
                series["reference P2"].append(None)  # the truth itself
            else:
                series[f"reference P{deg}"].append(float(np.linalg.norm(next(own) - truth) / scale))
    out = {"scene": scene.name, "kind": "space", "h": hs, "series": [], **({"state": state} if state else {})}
    for label, errs in series.items():
        pts = [(h, e) for h, e in zip(hs, errs, strict=True) if e]
        order = (
            float(np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0]) if len(pts) >= 2 else None
        )
        theory = {"reference P1": 2, "reference P2": 3}.get(label)  # L2 of displacements at the vertices
        out["series"].append(
            {"label": label, "h": [p[0] for p in pts], "error": [p[1] for p in pts], "order": order, "theory": theory}
        )
    return out


def converge_time(
    scene: Scene, models=(linear_tm.NAME,), integrators=("symplectic-euler", "central-difference")
) -> dict:
    """dt halving on a dynamic scene: each (model, integrator)'s trajectory at 0.4, 0.2, 0.1 x dt_crit
    against its own run at 0.025 x dt_crit; the observed order of the integrator."""
    from verification.runs.simulate import run_model

    if scene.time.mode != "dynamic":
        raise SceneError(f"{scene.path}: converge --in time needs a dynamic scene (time.mode = dynamic)")
    out = {"scene": scene.name, "kind": "time", "series": []}
    for m in models:
        for integ in integrators:
            fine = run_model(scene, m, dt_fraction=0.025, integrator=integ)
            dts, errs = [], []
            for f in (0.4, 0.2, 0.1):
                r = run_model(scene, m, dt_fraction=f, integrator=integ)
                dts.append(r.meta["dt"])
                errs.append(
                    float(np.linalg.norm(r.displacement - fine.displacement) / np.linalg.norm(fine.displacement))
                )
            out["series"].append(
                {
                    "label": f"{m} {integ}",
                    "h": dts,
                    "error": errs,
                    "order": float(np.polyfit(np.log(dts), np.log(errs), 1)[0]),
                    "theory": {"symplectic-euler": 1, "central-difference": 2, "implicit-euler": 1}[integ],
                }
            )
    return out


def format_converge(res: dict) -> str:
    unit = "dt (s)" if res["kind"] == "time" else "h"
    out = [
        f"converge {res['scene']} ({res['kind']})" + (f": the body after the {res['state']}" if "state" in res else "")
    ]
    for s in res["series"]:
        theory = f" (theory {s['theory']})" if s.get("theory") is not None else ""
        order = "-" if s["order"] is None else f"{s['order']:.2f}"
        errs = ", ".join(f"{e:.3g}" for e in s["error"])
        out.append(
            f"  {s['label']:<28} order {order}{theory}   errors {errs} at {unit} {', '.join(f'{h:.3g}' for h in s['h'])}"
        )
    return "\n".join(out)
