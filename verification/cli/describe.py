"""What ``tissuebench check`` says of a scene: its mesh, regions, materials, states and warnings, read as
every command reads them, nothing solved."""

from __future__ import annotations

import numpy as np

from realtime.models import linear_tm
from verification.scene import implausible


def describe(scene) -> dict:
    """The scene's description (``check --json``): mesh quality and extent, each region's vertices (a
    load's inside the body counted: precomputed's responses exist for surface vertices only), the
    materials, the element estimate of the explicit critical step, the warnings and the event states."""
    import realtime
    from verification.inputs import scene_loading

    mesh = scene.mesh
    loading = scene_loading(scene)
    lo, hi = mesh.bounding_box()
    model = realtime.build_model(linear_tm.NAME, mesh.points, mesh.tets, scene.body_material(), loading)
    m = scene.material
    return {
        "scene": scene.name,
        "path": str(scene.path),
        "mode": scene.time.mode,
        "law": m.law,
        "mesh": {**mesh.quality(), "sha256": mesh.sha256(), "parts": mesh.parts()[0], "notes": list(mesh.notes)},
        "regions": _regions(scene),
        "material": {"lambda_pa": m.lam, "mu_pa": m.mu, "wave_speed_m_s": m.wave_speed},
        "materials": _zones(scene),
        "dt_crit_element_s": realtime.element_critical_dt(model),
        "extent_m": {"min": lo.tolist(), "max": hi.tolist(), "size": (hi - lo).tolist()},
        "warnings": implausible(scene),
        "states": _states(scene),
    }


def _regions(scene) -> list[dict]:
    """Each [[fixed]] and [[load]] region: its table, description and vertices held, and for a load the
    vertices of it inside the body."""
    mesh = scene.mesh
    regions = [
        {"table": f"fixed[{i}]", "region": fx.region.describe(), "vertices": len(fx.region.vertices(mesh))}
        for i, fx in enumerate(scene.problem.fixed)
    ]
    surface = np.zeros(mesh.n_vertices, dtype=bool)
    surface[mesh.surface_vertices] = True
    for i, ld in enumerate(scene.problem.loads):
        if hasattr(ld, "region"):
            held = ld.region.vertices(mesh)
            regions.append(
                {"table": f"load[{i}]", "region": ld.region.describe(), "vertices": len(held),
                 "inside": int((~surface[held]).sum())}
            )  # fmt: skip
    for i, tool in enumerate(scene.problem.contacts):
        size = f"radius {tool.radius:g} m" if tool.shape != "plane" else f"normal {list(tool.normal)}"
        regions.append(
            {"table": f"tool[{i}]", "region": f"a rigid {tool.shape}, {size}, travelling {list(tool.travel)} m",
             "vertices": int((tool.gap(mesh.points[surface], 1.0) < 0.0).sum()), "rigid": True}
        )  # fmt: skip
    return regions


def _zones(scene) -> list:
    """Each [[material]] table: its region, law constants and how many tetrahedra it holds."""
    if not scene.zones:
        return []
    counts = np.bincount(scene.body_material().index, minlength=len(scene.zones))
    return [
        {
            "table": f"material[{k}]",
            "region": region.describe(),
            "tets": int(counts[k]),
            "young_pa": m.young,
            "poisson": m.poisson,
            "density_kg_m3": m.density,
            "wave_speed_m_s": m.wave_speed,
        }
        for k, (region, m) in enumerate(scene.zones)
    ]


def _states(scene) -> list[dict]:
    """A scene with events: each state's time, events and mesh (a cut adds vertices and boundary faces)."""
    if not scene.events:
        return []
    from verification.events import states

    return [
        {
            "time": s.time,
            "label": s.label,
            "n_vertices": s.scene.mesh.n_vertices,
            "n_tets": s.scene.mesh.n_tets,
            "boundary_faces": len(s.scene.mesh.boundary),
        }
        for s in states(scene)
    ]


def check_text(o: dict) -> str:
    """``check``'s description (``describe``) as lines of text."""
    q = o["mesh"]
    lines = [
        f"{o['scene']} ({o['mode']}, {o['law']}): {q['n_vertices']} vertices, {q['n_tets']} tetrahedra, "
        f"{q['parts']} part(s), dihedral angles {q['min_dihedral_deg']:.1f} to {q['max_dihedral_deg']:.1f} "
        f"degrees, aspect ratio up to {q['max_aspect_ratio']:.2f}"
    ]
    e = o["extent_m"]
    lines.append(
        "  extent: {:.4g} x {:.4g} x {:.4g} m, from ({:.4g}, {:.4g}, {:.4g}) to ({:.4g}, {:.4g}, {:.4g}) m".format(
            *e["size"], *e["min"], *e["max"]
        )
    )
    lines += [f"  warning: {w}" for w in o["warnings"]]
    lines += [f"  mesh repaired: {n}" for n in q["notes"]]
    lines += [
        f"  {z['table']}: {z['region']} holds {z['tets']} tetrahedra: E = {z['young_pa']:.4g} Pa, "
        f"nu = {z['poisson']:.4g}, rho = {z['density_kg_m3']:.4g} kg/m^3"
        for z in o["materials"]
    ]
    lines += [
        f"  {r['table']}: {r['region']} {'ends with' if 'rigid' in r else 'holds'} {r['vertices']} "
        f"{'surface ' if 'rigid' in r else ''}vert{'ex' if r['vertices'] == 1 else 'ices'}"
        + (" of the rest shape inside it" if "rigid" in r else "")
        + (
            f", {r['inside']} inside the body (precomputed, whose responses exist for surface vertices only, "
            "will not run this scene)"
            if r.get("inside")
            else ""
        )
        for r in o["regions"]
    ]
    lines.append(f"  element estimate of the explicit critical step: {o['dt_crit_element_s']:.3g} s")
    lines += [
        f"  state t = {st['time']:g} s: {st['label']}: {st['n_vertices']} vertices, {st['n_tets']} tetrahedra, "
        f"{st['boundary_faces']} boundary faces"
        for st in o["states"]
    ]
    if o.get("picture"):
        lines.append(f"  picture: {o['picture']} (from above, the front and the side)")
    return "\n".join(lines)
