"""A scene as data any engine can read (``tissuebench export SCENE DIR``; docs/scenes.md, "Exported
scenes").

DIR receives, each written whole (a temporary file, then a rename):

- ``scene.json``: what the problem is, in SI units: the format and its version, the scene's name and
  hash, the law, each material with its Lame constants, the time mode (static; dynamic with end, the
  output times and Rayleigh damping), gravity, the tools (their motion and ramp as a formula) and where
  every array is;
- ``arrays.npz``: the arrays, named as ``scene.json`` says: points (N, 3) m, tets (M, 4) (0-based,
  positively oriented), material_index (M,) into the materials, free (N, 3) (1 moves, 0 held or
  prescribed), external_force (N, 3) N (the P1 nodal load vector of gravity, forces and tractions, what
  the reference applies), the tools' vertices, components and the prescribed displacement of each at
  every output time (T, P, 3) m, so that an engine need not implement the ramp;
- a scene with rigid tools (``[[tool]] shape``) lists them in ``scene.json`` under ``rigid_tools``: each
  one's shape (sphere, capsule, plane), its place at t = 0, its size and its translation along its ramp,
  for the engine's own contact to meet (``rigid_tools``);
- ``regions`` in ``scene.json``: the held regions and the tools' regions by their rule (a box, a sphere,
  the whole body; null where the scene draws one by its mesh's tags, a field or vertex ids), for an engine
  that meshes the body itself and must find them on its own vertices (``SceneInputs.regions``);
- ``mesh.vtu`` and ``mesh.msh`` (gmsh 2.2 ASCII): the mesh, with the material index per tetrahedron.

A scene with events (a cut) is one static problem per state: DIR holds the body as meshed, and
``state-K/`` each later state's body (its mesh cut open), written the same way; every ``scene.json``
lists the states under ``states`` and names its own under ``state``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from meshes.io import atomic_savez, atomic_write
from realtime.contact import SHAPES
from realtime.material import Materials
from realtime.model import RAMP_SHAPES, TOOL_TRANSLATION, _tool_displacements

from .protocol import SceneInputs

#: The exported format's name and version: a reader checks both.
FORMAT, VERSION = "tissuebench-scene", 1


def _material(m) -> dict:
    """One material's constants in SI units, with the Lame constants the reference derives."""
    out = {"law": m.law, "young_pa": m.young, "poisson": m.poisson, "density_kg_m3": m.density}
    out.update(lambda_pa=m.lam, mu_pa=m.mu, volume_penalty_pa=m.volume_penalty)
    if m.fiber is not None or m.fiber_axis is not None:
        out.update(
            fiber=None if m.fiber is None else list(m.fiber),
            fiber_axis=None if m.fiber_axis is None else list(m.fiber_axis),
            fiber_point_m=list(m.fiber_point),
            young_fiber_pa=m.young_fiber,
            fiber_shear_pa=m.fiber_shear,
        )
    return out


def output_times(inputs: SceneInputs) -> np.ndarray:
    """The instants a result is written at, s: 0 for a static scene, 0, output_every, ... end otherwise."""
    ts = inputs.time
    if ts.mode == "static":
        return np.zeros(1)
    return np.arange(int(round(ts.end / ts.output_every)) + 1) * ts.output_every


def tool_motions(inputs: SceneInputs) -> tuple[list[dict], np.ndarray]:
    """Each tool in words (kind, motion, ramp) and the prescribed displacement (T, P, 3) m of every
    tool vertex at every output time (a static scene's single time is the tools' final place)."""
    lo = inputs.loading
    tools = []
    for k in range(len(lo.tool_kind)):
        tool = {"kind": "translation" if lo.tool_kind[k] == TOOL_TRANSLATION else "rotation"}
        if lo.tool_kind[k] == TOOL_TRANSLATION:
            tool["displacement_m"] = lo.tool_vector[k].tolist()
        else:
            tool.update(axis=lo.tool_axis[k].tolist(), center_m=lo.tool_center[k].tolist())
            tool["angle_rad"] = float(lo.tool_angle[k])
        tool.update(ramp_s=float(lo.tool_ramp[k]), ramp_shape=RAMP_SHAPES[int(lo.tool_ramp_shape[k])])
        tools.append(tool)
    times = output_times(inputs) if inputs.time.mode == "dynamic" else np.array([np.inf])
    out = np.zeros((len(times), len(lo.tool_vertex), 3))
    for i, t in enumerate(times):
        _tool_displacements(inputs.points, lo.tools_tuple(), float(t), out[i])
    return tools, out


def rigid_tools(inputs: SceneInputs) -> list[dict]:
    """Each rigid tool in SI units: ``shape``; ``center_m`` (the sphere's centre, the capsule's first end,
    a point of the plane, at t = 0); ``end_m`` (the capsule's second end); ``normal`` (the plane's unit
    normal, out of the tool toward the body); ``radius_m``; ``travel_m``, the translation reached at
    ``ramp_s`` along ``ramp_shape`` and then held (a static scene's answer is at the end of the travel).
    The truth's contact is frictionless."""
    c = inputs.loading.contacts
    if c is None:
        return []
    out = []
    for k in range(c.count):
        tool = {"shape": SHAPES[int(c.shape[k])], "center_m": c.center[k].tolist()}
        if tool["shape"] == "capsule":
            tool["end_m"] = c.end[k].tolist()
        if tool["shape"] == "plane":
            tool["normal"] = c.normal[k].tolist()
        else:
            tool["radius_m"] = float(c.radius[k])
        tool.update(travel_m=c.travel[k].tolist(), ramp_s=float(c.ramp[k]))
        tool.update(ramp_shape=RAMP_SHAPES[int(c.ramp_shape[k])], friction=0.0)
        out.append(tool)
    return out


def describe(inputs: SceneInputs) -> dict:
    """``scene.json``'s content."""
    mats = Materials.of(inputs.material, len(inputs.tets))
    tools, _ = tool_motions(inputs)
    ts = inputs.time
    return {
        "format": FORMAT,
        "version": VERSION,
        "units": "SI (m, s, kg, N, Pa)",
        "scene": inputs.name,
        "scene_sha256": inputs.sha256,
        "law": mats.materials[0].law,
        "materials": [_material(m) for m in mats.materials],
        "time": {
            "mode": ts.mode,
            "end_s": ts.end if ts.mode == "dynamic" else None,
            "output_times_s": output_times(inputs).tolist(),
            "damping_mass_per_s": ts.damping_mass,
            "damping_stiffness_s": ts.damping_stiffness,
        },
        "gravity_m_s2": list(inputs.gravity),
        "tools": tools,
        "rigid_tools": rigid_tools(inputs),
        "regions": dict(inputs.regions),
        "mesh": {"vtu": "mesh.vtu", "gmsh22": "mesh.msh", "n_vertices": len(inputs.points), "n_tets": len(inputs.tets)},
        "arrays": {
            "file": "arrays.npz",
            "points": "(N, 3) float64, m",
            "tets": "(M, 4) int64, 0-based vertex indices, positively oriented",
            "material_index": "(M,) int64, index into materials",
            "free": "(N, 3) float64, 1 where the component moves, 0 where it is held or prescribed",
            "external_force": "(N, 3) float64, N: the P1 nodal load vector of gravity, forces and tractions",
            "tool_vertex": "(P,) int64, the vertices the tools drive",
            "tool_mask": "(P, 3) float64, 1 on the components the tool prescribes",
            "tool_id": "(P,) int64, index into tools",
            "tool_displacement": "(T, P, 3) float64, m: the prescribed displacement of each tool vertex at each "
            "output time (a static scene: T = 1, the final place)",
        },
    }


def export(inputs: SceneInputs, directory: str | Path, extra: dict | None = None) -> Path:
    """Write the scene as data into ``directory`` (created); returns ``scene.json``'s path. ``extra``:
    more keys for ``scene.json`` (a scene with events: its states, and which one this is)."""
    import meshio

    out = Path(directory)
    out.mkdir(parents=True, exist_ok=True)
    lo = inputs.loading
    mats = Materials.of(inputs.material, len(inputs.tets))
    _, tool_u = tool_motions(inputs)
    atomic_savez(
        out / "arrays.npz",
        points=inputs.points,
        tets=inputs.tets,
        material_index=mats.index.astype(np.int64),
        free=lo.free,
        external_force=lo.external_force,
        tool_vertex=lo.tool_vertex,
        tool_mask=lo.tool_mask,
        tool_id=lo.tool_id,
        tool_displacement=tool_u,
    )
    mesh = meshio.Mesh(inputs.points, [("tetra", inputs.tets)], cell_data={"material_index": [mats.index]})
    atomic_write(out / "mesh.vtu", lambda tmp: meshio.write(tmp, mesh, file_format="vtu"))
    msh = meshio.Mesh(
        inputs.points,
        [("tetra", inputs.tets)],
        cell_data={"gmsh:physical": [mats.index + 1], "gmsh:geometrical": [mats.index + 1]},
    )
    atomic_write(out / "mesh.msh", lambda tmp: meshio.write(tmp, msh, file_format="gmsh22", binary=False))
    text = json.dumps(describe(inputs) | (extra or {}), indent=1)
    return atomic_write(out / "scene.json", lambda tmp: Path(tmp).write_text(text))
