"""How close the reference's bar is to the error it bounds: its effectivity, bar / true error, on cases
that span what users bring (a smooth bend, a clamp's corner, a tool's rim, a near-incompressible block,
a cut, large rotation, a material jump, a manufactured solution).

Each case is a scene made coarse enough that a truth two levels finer than the returned solution is
affordable (P2 at refinement 3 for the returned refinement 1; the manufactured solution's exact field
instead; the suite's tests return refinement 0 against P2 at 2, a coarser and so harder test). The
reference returns P2 at refinement 1, and each estimator of ``ESTIMATORS`` bounds its relative error over
the scene's vertices (the norm of ``reference.driver``'s bar):

- ``difference``: |u_0 - u_1| / |u_1|, P2 at refinements 0 and 1, the reference's default bar. It bounds
  the error where refining at least halves it, and is 2^p - 1 times the error where P2 converges at
  order p (7 at p = 3);
- ``p3``: P3_SAFETY |u_1 - u_1^P3| / |u_1^P3|, the difference to P3 on the same mesh (the reference's
  ``estimate = "p3"``, which the advisor asks for first where a bar blocks). It is the error
  itself, within the P3 solution's own error: within (1 -/+ r) of it, r = e(P3) / e(P2) on that mesh,
  so the safety factor keeps it above the error while r < 1 - 1 / P3_SAFETY.

A dynamic case's bars add the time step's part, by the reference's own rules (``reference.driver``):
``difference`` adds 2 |u_dt - u_dt/2| at the coarse level; ``p3`` adds 4/3 |u_dt - u_dt/2| on the
returned mesh (Richardson for Newmark's second order). Its truth is P2 two refinements finer at dt / 4.

The adaptive reference (``reference.adaptive``: P2 refined where its P3 check says the error lives, the
same P3 bar at every level) is measured beside them on its own solution: from refinement 0, adapted
``returned`` + 1 times, so that no cell of its mesh is finer than the uniform truth's minus one level. Its row
says its dofs, its true error against the same truth and its bar's effectivity; the manufactured case has
no scene to adapt (its body force lives in ``reference.manufactured``), so its adaptive row is unknown.

Effectivity under 1 means the bar promises less error than there is: the one thing a bar must never
do. ``tissuebench effectivity`` writes the table (docs/effectivity.md) and its JSON with the machine,
the commit and the date; every number in it comes from the run that wrote it.
"""

from __future__ import annotations

import gc
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from multiprocessing import get_context

import numpy as np

from reference.levels import P3_SAFETY  # the reference's own estimate, measured here
from verification.progress import log

#: The refinement the reference returns (the truth is solved two levels finer).
RETURNED = 1


@dataclass(frozen=True)
class Case:
    """A built-in scene with ``edits`` ({"table.key": value}, or a whole table under its name), and what
    its error is about."""

    scene: str
    what: str
    edits: dict = field(default_factory=dict)
    state: int | None = None  # a scene with events: the state solved (its index in events.states)


#: The blocks on a structured grid of 2 cm cells (gmsh's box mesher keeps 337 vertices at any h over
#: 1 cm there): P2 three refinements finer is then about 100 000 dofs.
GRID = {"mesh.generator": "grid", "mesh.h": 0.02}

#: The cases, by name.
CASES = {
    "smooth bending": Case("cantilever", "a beam bent by its weight, held at one end", {"mesh.h": 0.02}),
    "clamp corner": Case("cantilever-pull", "a beam held at one end, its other end pulled down 1 cm", {"mesh.h": 0.02}),
    "tool-pressed liver": Case(
        "liver",
        "a coarse liver held at its back, a 1.5 cm tool pressing its right lobe 5 mm",
        {
            "mesh.h": 0.05,
            "load": [
                {
                    "kind": "displacement",
                    "sphere": {"center": [0.07, 0.0, 0.03], "radius": 0.03},
                    "value": [0.0, 0.0, -0.005],
                }
            ],
        },
    ),
    "near-incompressible block": Case(
        "block-press", "a block pressed by a tool, nu = 0.49", {**GRID, "material.poisson": 0.49}
    ),
    "twisted block": Case("block-twist", "a block's top turned by a tool", GRID),
    "stiff inclusion": Case(
        "stiff-inclusion", "a block with a stiffer core, pressed", {**GRID, "mesh.h": 0.04 / 3}
    ),  # three cells a side: the core's sphere (8 mm) holds the middle cell's tetrahedra
    "cut beam": Case("cantilever-cut", "the beam cut half through at mid-span, under its weight", {"mesh.h": 0.01}, 1),
    "layered slab": Case("layered-slab", "three linear layers of different stiffness, pressed", {"mesh.h": 0.01}),
    "dynamic beam": Case(
        "cantilever-dynamic", "a beam's end pushed 5 mm in 50 ms and held, 0.3 s of damped motion", GRID
    ),
    "manufactured": Case("manufactured", "the manufactured StVK solution on the unit cube, exact"),
}


def _estimates(u: dict, r: int) -> dict:
    """Each estimator's relative bar on the solution returned at refinement ``r``, from the solutions
    ``u`` at the scene's vertices: {(degree, refinement): (K, 3) m}; None for one whose solutions are not
    there (``difference`` at refinement 0 has no coarser level)."""
    n = np.linalg.norm
    return {
        "difference": float(n(u[(2, r - 1)] - u[(2, r)]) / n(u[(2, r)])) if (2, r - 1) in u else None,
        "p3": P3_SAFETY * float(n(u[(2, r)] - u[(3, r)]) / n(u[(3, r)])),
    }


#: The estimators the table compares, in its column order.
ESTIMATORS = ("difference", "p3")


def case_scene(case: Case):
    """The case's scene: the built-in one with the edits, or the stated state of a scene with events."""
    from verification.events import states
    from verification.scene_file import builtin_scenes, parse

    path = builtin_scenes()[case.scene]
    data = tomllib.loads(path.read_text())
    for key, value in case.edits.items():
        table, _, name = key.partition(".")
        if name:
            data[table][name] = value
        else:
            data[table] = value
    scene = parse(path, data)
    return states(scene)[case.state].scene if case.state is not None else scene


def _scene_solutions(scene, returned: int) -> tuple[dict, dict]:
    """P2 at refinements 0 .. ``returned`` + 2 (the truth) and P3 at ``returned``, each at the scene's
    vertices, and their sizes."""
    from reference.fem import ElasticityProblem
    from reference.levels import solve_level

    x = scene.mesh.points
    u, dofs, coarse = {}, {}, None
    plan = [(2, k) for k in range(returned + 3)] + [(3, returned)]
    for degree, level in plan:
        t0 = time.perf_counter()
        ep = ElasticityProblem(scene.mesh, scene.body_material(), scene.problem, degree=degree, refine=level)
        nested = coarse if degree == 2 else None
        solve_level(ep, nested, [], {"steps": 1, "min_increment": 1e-4}, None)
        coarse = ep if degree == 2 else coarse
        u[(degree, level)], dofs[(degree, level)] = ep.evaluate(x), ep.n_dofs
        log(f"effectivity: {scene.name} P{degree} refined {level}: {ep.n_dofs} dofs, {time.perf_counter() - t0:.1f} s")
        del ep
        gc.collect()  # a solved level's factor (GB at the truth's level) goes before the next is made
    return u, dofs


def _dynamic_solutions(scene, returned: int) -> tuple[dict, dict]:
    """A dynamic case's Newmark trajectories at the scene's vertices, each (displacement (T, K, 3) m, tool
    force (T, 3) N), keyed (degree, refinement, dt divisor), dt the reference's (``reference.driver``:
    output_every / 4): what the default bar reads (P2 at ``returned`` - 1 at dt and dt / 2, and at
    ``returned``), what the p3 bar reads (P3 at ``returned``, P2 there at dt / 2), and the truth, P2 two
    refinements finer at dt / 4; and their sizes."""
    from reference.fem import ElasticityProblem

    ts, x = scene.time, scene.mesh.points
    dt = ts.output_every / 4
    plan = [(2, returned, 1), (3, returned, 1), (2, returned, 2)]
    plan += [(2, returned - 1, 1), (2, returned - 1, 2)] if returned >= 1 else []
    u, dofs = {}, {}
    for degree, level, divisor in [*plan, (2, returned + 2, 4)]:
        t0 = time.perf_counter()
        ep = ElasticityProblem(scene.mesh, scene.body_material(), scene.problem, degree=degree, refine=level)
        run = ep.solve_dynamic(
            dt / divisor, ts.end, ts.output_every, x, rayleigh=(ts.damping_mass, ts.damping_stiffness)
        )
        u[(degree, level, divisor)], dofs[(degree, level)] = (run.values, run.reactions), ep.n_dofs
        log(
            f"effectivity: {scene.name} P{degree} refined {level} at dt / {divisor}: {ep.n_dofs} dofs, "
            f"{time.perf_counter() - t0:.1f} s"
        )
        del ep
        gc.collect()
    return u, dofs


def _dynamic_estimates(u: dict, r: int) -> dict:
    """Each estimator's relative bar on the trajectory returned at refinement ``r`` (P2 at dt), computed by
    the reference's own rules (``reference.driver``) from ``_dynamic_solutions``."""
    from reference.driver import dynamic_bars, dynamic_p3_bars

    def bars(rule, keys, level):
        return rule(tuple(u[k][0] for k in keys), tuple(u[k][1] for k in keys), level)["ref_err_estimate"]

    return {
        "difference": bars(dynamic_bars, [(2, r - 1, 1), (2, r, 1), (2, r - 1, 2)], r - 1) if r >= 1 else None,
        "p3": bars(dynamic_p3_bars, [(2, r, 1), (3, r, 1), (2, r, 2)], r - 1),
    }


def _adaptive(scene, returned: int, truth: np.ndarray) -> dict:
    """The adaptive reference from refinement 0, adapted ``returned`` + 1 times (module docstring), judged
    against ``truth`` (K, 3) m at the scene's vertices: its P2 dofs, true error, bar and effectivity."""
    from reference.adaptive import solve_adaptive

    t0 = time.perf_counter()
    run = solve_adaptive(scene.mesh, scene.body_material(), scene.problem, max_levels=returned + 1)
    p2 = run["problems"][0]
    x = scene.mesh.points
    err = float(np.linalg.norm(p2.evaluate(x) - truth) / np.linalg.norm(truth))
    records = run["adaptive"]["levels"]
    bar = records[-1]["bar"] if len(run["problems"]) > 1 else None
    log(f"effectivity: {scene.name} adaptive: {p2.n_dofs} dofs, {time.perf_counter() - t0:.1f} s")
    return {
        "dofs": p2.n_dofs,
        "levels": len(records),
        "true_error": err,
        "bar": bar,
        "effectivity": bar / err if bar is not None and err > 0 else None,
        "stop": run["adaptive"]["stop"],
    }


def _manufactured_solutions(scene, returned: int) -> tuple[dict, dict, np.ndarray]:
    """The manufactured problem on the unit cube of 2 x 2 x 2 cells (six tetrahedra each) and its
    refinements: P2 at ``returned`` and the level below it, P3 at ``returned``, at the coarse grid's
    vertices, and the exact field there."""
    from reference.manufactured import manufactured_errors

    n = 2
    g = np.linspace(0.0, 1.0, n + 1)
    x = np.array(np.meshgrid(g, g, g, indexing="ij")).reshape(3, -1).T
    u, dofs = {}, {}
    for degree, level in [(2, k) for k in range(max(returned - 1, 0), returned + 1)] + [(3, returned)]:
        out = manufactured_errors(scene.material.law, degree, n, scene.material, refine=level, points=x)
        u[(degree, level)], dofs[(degree, level)] = out["values"], out["dofs"]
        log(f"effectivity: manufactured P{degree} refined {level}: {out['dofs']} dofs")
    return u, dofs, out["exact"]


def measure(name: str, returned: int = RETURNED) -> dict:
    """One case's row: its size, the true relative error of the solution returned at refinement
    ``returned`` (against the exact field, or P2 two refinements finer), and each estimator's bar and
    effectivity (bar / true error; unknown where the estimator has no bar)."""
    case = CASES[name]
    scene = case_scene(case)
    t0 = time.perf_counter()
    adaptive = None
    if case.scene == "manufactured":
        u, dofs, exact = _manufactured_solutions(scene, returned)
        truth, kind = exact, "exact"
    elif scene.time.mode == "dynamic":  # the truth is a trajectory; a dynamic reference is not adapted
        u, dofs = _dynamic_solutions(scene, returned)
        truth, kind = u[(2, returned + 2, 4)][0], f"P2 refined {returned + 2} times at dt / 4"
        u[(2, returned)] = u[(2, returned, 1)][0]
    else:
        u, dofs = _scene_solutions(scene, returned)
        truth, kind = u[(2, returned + 2)], f"P2 refined {returned + 2} times"
        adaptive = _adaptive(scene, returned, truth)
    err = float(np.linalg.norm(u[(2, returned)] - truth) / np.linalg.norm(truth))
    bars = _dynamic_estimates(u, returned) if scene.time.mode == "dynamic" else _estimates(u, returned)
    return {
        "case": name,
        "what": case.what,
        "scene": case.scene,
        "vertices": truth.shape[-2],
        "returned": returned,
        "dofs": dofs[(2, returned)],
        "p3_dofs": dofs[(3, returned)],
        "truth": kind,
        "truth_dofs": dofs.get((2, returned + 2)),
        "true_error": err,
        "bars": bars,
        "effectivity": {k: (b / err if b is not None and err > 0 else None) for k, b in bars.items()},
        "adaptive": adaptive,
        "wall_s": time.perf_counter() - t0,
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
    }


def row_path(name: str, returned: int):
    """Where a case's row is kept: keyed by the case, the returned level, the reference's code and this
    module's, and the libraries' versions, so that a killed table resumes from its finished cases."""
    from verification.cache import REFERENCE_CODE, code_digest, digest, entry, library_versions

    case = CASES[name]
    key = digest(
        {
            "case": [case.scene, case.edits, case.state],
            "returned": returned,
            "p3_safety": P3_SAFETY,
            "code": code_digest((*REFERENCE_CODE, "verification/studies/effectivity.py", "verification/scene*.py")),
            "libraries": library_versions(),
        }
    )
    return entry("effectivity", case.scene, key, ".json")


def effectivity_table(names=None, returned: int = RETURNED, use_cache: bool = True) -> dict:
    """Every case's row (``measure``), in CASES' order, with the machine, commit and date they ran at.
    Each row is kept as it is made (``row_path``): a table stopped half-way starts again from there."""
    import json

    from meshes.io import atomic_write_text
    from verification.cache import git_commit, machine_id, read_cached

    names = list(CASES) if not names else list(names)
    rows = []
    # one process per case: what a case's solves leave in PETSc is gone with it (in one process the
    # nine cases' truths grew past 24 GB)
    with ProcessPoolExecutor(1, mp_context=get_context("spawn"), max_tasks_per_child=1) as pool:
        for k, name in enumerate(names, 1):
            path = row_path(name, returned)
            kept = read_cached(path, lambda p: json.loads(p.read_text())) if use_cache else None
            log(f"effectivity: case {k} of {len(names)}: {name}" + (" (kept from an earlier run)" if kept else ""))
            row = kept or pool.submit(measure, name, returned).result()
            if use_cache and not kept:
                atomic_write_text(path, json.dumps(row))
            rows.append(row)
    meta = {
        "machine": machine_id(),
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        "returned": f"P2 refined {returned} time(s)",
        "p3_safety": P3_SAFETY,
    }
    return {"rows": rows, "meta": meta}


def format_markdown(table: dict) -> str:
    """The table as docs/effectivity.md shows it."""
    m = table["meta"]
    lines = [
        "# The reference's bar against its true error",
        "",
        "Written by `tissuebench effectivity --markdown docs/effectivity.md` "
        f"(commit {m['commit']}, {m['date']}, {m['machine']['cpu']}, {m['machine']['cores']} cores). "
        f"The reference returns {m['returned']}; effectivity is bar / true error, and under 1 the bar "
        "promises less error than there is. `difference` is |u_0 - u_1| / |u_1| (the bar today), "
        f"`p3` is {m['p3_safety']:g} |u_1 - u_1^P3| / |u_1^P3| (verification/studies/effectivity.py says why). "
        "`adaptive` is the reference refined where its error lives (`reference --estimate adaptive`, from "
        "refinement 0, one level more than the returned refinement), judged on its own solution: its P2 dofs, "
        "its true error against the same truth and its P3 bar. A dynamic case's bars add the time step's part: "
        "`difference` 2 |u_dt - u_dt/2| at refinement 0, `p3` 4/3 |u_dt - u_dt/2| at refinement 1 (Newmark's "
        "second order); its truth is also at dt / 4, and a dynamic reference is not adapted.",
        "",
        "| case | vertices | dofs | true error | truth | "
        + " | ".join(f"{e} bar (effectivity)" for e in ESTIMATORS)
        + " | adaptive dofs | adaptive true error | adaptive bar (effectivity) |",
        "|---|---|---|---|---|" + "---|" * (len(ESTIMATORS) + 3),
    ]
    for r in table["rows"]:
        cells = " | ".join(f"{_fmt(r['bars'][e], '.3g')} ({_fmt(r['effectivity'][e])})" for e in ESTIMATORS)
        a = r.get("adaptive") or {}
        adaptive = (
            f"{a.get('dofs', 'unknown')} | {_fmt(a.get('true_error'), '.3g')} | "
            f"{_fmt(a.get('bar'), '.3g')} ({_fmt(a.get('effectivity'))})"
        )
        lines.append(
            f"| {r['case']} | {r['vertices']} | {r['dofs']} | {r['true_error']:.3g} | {r['truth']} | {cells} | {adaptive} |"
        )
    lines.append("")
    for e in ESTIMATORS:
        values = [r["effectivity"][e] for r in table["rows"] if r["effectivity"][e] is not None]
        if values:
            lines.append(f"- `{e}`: effectivity {min(values):.2f} to {max(values):.2f} over {len(values)} cases.")
    values = [a["effectivity"] for r in table["rows"] if (a := r.get("adaptive")) and a["effectivity"] is not None]
    if values:
        lines.append(f"- `adaptive`: effectivity {min(values):.2f} to {max(values):.2f} over {len(values)} cases.")
    return "\n".join(lines) + "\n"


def _fmt(x: float | None, spec: str = ".2f") -> str:
    return "unknown" if x is None else format(x, spec)
