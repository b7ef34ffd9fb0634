"""An exported scene carried onto a mesh an engine made of the body itself (docs/adapters.md, "On the
engine's own mesh").

An engine that tetrahedralises a surface itself (Genesis's FEM, through tetgen) is judged on its own mesh
by ``tissuebench judge``: the reference is evaluated at its vertices and the error budget's mesh part is
the P1 solution on its tetrahedra. The scene's arrays are the scene mesh's, so here the same scene is
posed on the engine's vertices from what ``scene.json`` says in words: its held and driven regions by
their rule (``regions``: a box, a sphere, the whole body, as ``meshes.regions`` applies them, which the
judge applies again to the result's points), its tools' motion (``tools``), its gravity and its material.
What has no rule on another mesh (a region drawn by the scene mesh's tags, a field or vertex ids; a
traction or a point force; several materials; a dynamic scene's tool ramps) is refused, naming it.
"""

from __future__ import annotations

import dataclasses

import numpy as np

from exported import AdapterError, Exported, gravity_only

#: the components' names, in the export's order
AXES = ("x", "y", "z")


def surface(scene: Exported) -> np.ndarray:
    """(F, 3) int64: the scene mesh's boundary triangles, each ordered so that its normal (b - a) x (c - a)
    points out of the body (the file a mesher reads)."""
    tets = np.asarray(scene.tets, dtype=np.int64)
    faces = np.concatenate([tets[:, [1, 2, 3]], tets[:, [0, 3, 2]], tets[:, [0, 1, 3]], tets[:, [0, 2, 1]]])
    opposite = np.concatenate([tets[:, 0], tets[:, 1], tets[:, 2], tets[:, 3]])
    _, index, count = np.unique(np.sort(faces, axis=1), axis=0, return_index=True, return_counts=True)
    faces, opposite = faces[index[count == 1]], opposite[index[count == 1]]
    x = scene.points
    normal = np.cross(x[faces[:, 1]] - x[faces[:, 0]], x[faces[:, 2]] - x[faces[:, 0]])
    inward = np.einsum("ij,ij->i", normal, x[opposite] - x[faces[:, 0]]) > 0.0
    faces[inward] = faces[inward][:, [0, 2, 1]]
    return faces


def write_obj(path, points: np.ndarray, faces: np.ndarray) -> None:
    """A Wavefront .obj of the triangles ``faces`` (F, 3) of ``points`` (N, 3) m: the vertices they use, in
    the order of their index, each written to its last digit."""
    used, local = np.unique(faces, return_inverse=True)
    lines = [f"v {p[0]!r} {p[1]!r} {p[2]!r}" for p in points[used].tolist()]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in local.reshape(-1, 3).tolist()]
    with open(path, "w") as f:
        f.write("\n".join(lines) + "\n")


def _selected(rule: dict | None, x: np.ndarray, what: str) -> np.ndarray:
    """(K,) bool: the points of ``x`` (K, 3) m the region ``rule`` holds, as ``meshes.regions`` decides."""
    if rule is None:
        raise AdapterError(
            f"{what} is drawn on the scene mesh (its tags, a field or vertex ids): no rule carries it to the "
            "engine's own mesh"
        )
    if "all" in rule:
        return np.ones(len(x), dtype=bool)
    if "box" in rule:
        lo, hi = np.asarray(rule["box"]["lo_m"]), np.asarray(rule["box"]["hi_m"])
        return np.all((x >= lo) & (x <= hi), axis=1)
    if "sphere" in rule:
        s = rule["sphere"]
        return np.linalg.norm(x - np.asarray(s["center_m"]), axis=1) <= s["radius_m"]
    raise AdapterError(f"{what}: a region {sorted(rule)} this adapter does not know")


def _rotation(axis, angle: float) -> np.ndarray:
    """(3, 3): the rotation by ``angle`` rad about the unit ``axis`` (Rodrigues)."""
    k = np.asarray(axis, dtype=float) / np.linalg.norm(axis)
    kx = np.array([[0.0, -k[2], k[1]], [k[2], 0.0, -k[0]], [-k[1], k[0], 0.0]])
    return np.eye(3) + np.sin(angle) * kx + (1.0 - np.cos(angle)) * kx @ kx


def _tool_place(tool: dict, x: np.ndarray) -> np.ndarray:
    """(K, 3) m: where a tool puts the points ``x`` (K, 3) m it drives at the end of its travel."""
    if tool["kind"] == "translation":
        return np.tile(np.asarray(tool["displacement_m"], dtype=float), (len(x), 1))
    c = np.asarray(tool["center_m"], dtype=float)
    return (x - c) @ _rotation(tool["axis"], tool["angle_rad"]).T + c - x


def on_mesh(scene: Exported, points: np.ndarray, tets: np.ndarray) -> Exported:
    """The static ``scene`` posed on another mesh of its body: ``points`` (V, 3) float64 m and ``tets``
    (K, 4) int64 (any orientation); AdapterError naming what of the scene has no rule there."""
    who = f"{scene.spec.get('scene', 'the scene')} on the engine's own mesh"
    regions = scene.spec.get("regions")
    if not regions:
        raise AdapterError(f"{who}: the export carries no regions (export it again with this tissuebench)")
    if not scene.static:
        raise AdapterError(f"{who}: a dynamic scene's tools are carried as the scene mesh's own arrays only")
    if len(scene.spec["materials"]) > 1:
        raise AdapterError(f"{who}: several materials, each drawn on the scene mesh")
    g = gravity_only(scene, who)
    x = np.asarray(points, dtype=float)
    free = np.ones_like(x)
    for k, fx in enumerate(regions["fixed"]):
        inside = _selected(fx["rule"], x, f"fixed[{k}]")
        if not inside.any():
            raise AdapterError(f"{who}: fixed[{k}] holds none of its {len(x)} vertices")
        free[np.ix_(inside, [AXES.index(c) for c in fx["components"]])] = 0.0
    vertex, mask, place = [], [], []
    for k, (tool, where) in enumerate(zip(scene.spec["tools"], regions["tools"], strict=True)):
        inside = np.flatnonzero(_selected(where["rule"], x, f"tool {k}"))
        if not len(inside):
            raise AdapterError(f"{who}: tool {k} drives none of its {len(x)} vertices")
        m = np.array([float(c in where["components"]) for c in AXES])
        free[inside] = free[inside] * (1.0 - m)
        vertex.append(inside)
        mask.append(np.tile(m, (len(inside), 1)))
        place.append(_tool_place(tool, x[inside]))
    mesh = dataclasses.replace(
        scene,
        points=x,
        tets=np.asarray(tets, dtype=np.int64),
        material_index=np.zeros(len(tets), dtype=np.int64),
        free=free,
        external_force=np.zeros_like(x),
        tool_vertex=np.concatenate(vertex) if vertex else np.zeros(0, dtype=np.int64),
        tool_mask=np.concatenate(mask) if mask else np.zeros((0, 3)),
        tool_displacement=(np.concatenate(place) if place else np.zeros((0, 3)))[None],
    )
    return dataclasses.replace(mesh, external_force=mesh.lumped_masses()[:, None] * g)
