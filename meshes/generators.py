"""gmsh generators of the suite's geometries: box (beam), cylinder, tube, liver.

gmsh runs single-threaded with a fixed algorithm, so the same arguments give the same mesh, bit for
bit, on the same gmsh version. Every generator names the faces of its geometry as vertex tags
("xmin", "xmax", ... for the box; "bottom", "top", "side" for the cylinder; plus "inner" for the tube)
so that scenes can select them with ``tag = "..."``.
"""

from __future__ import annotations

import contextlib

import numpy as np

from realtime.errors import InputError

from .tetmesh import TetMesh, structured_box

GENERATORS = ("box", "grid", "cylinder", "tube", "liver")


@contextlib.contextmanager
def _gmsh_session(name: str, h: float):
    import gmsh

    gmsh.initialize(readConfigFiles=False)
    gmsh.option.setNumber("General.Terminal", 0)
    gmsh.option.setNumber("General.NumThreads", 1)
    gmsh.option.setNumber("Mesh.Algorithm", 6)  # Frontal-Delaunay surfaces
    gmsh.option.setNumber("Mesh.Algorithm3D", 1)  # Delaunay volumes
    gmsh.option.setNumber("Mesh.Optimize", 1)
    gmsh.option.setNumber("Mesh.RandomSeed", 1)
    gmsh.option.setNumber("Mesh.MeshSizeMax", h)
    gmsh.option.setNumber("Mesh.MeshSizeMin", h / 4.0)
    gmsh.option.setNumber("Mesh.MeshSizeFromCurvature", 0)
    gmsh.model.add(name)
    try:
        yield gmsh
    finally:
        gmsh.finalize()


def _extract(gmsh, source: str, face_names: dict[int, str]) -> TetMesh:
    """The volume mesh of the current model as a TetMesh, with the named faces as vertex tags."""
    tags, coords, _ = gmsh.model.mesh.getNodes()
    coords = coords.reshape(-1, 3)
    _, elem_tags, elem_nodes = gmsh.model.mesh.getElements(3)
    tets_tags = np.concatenate([n for n in elem_nodes]).reshape(-1, 4)
    used = np.unique(tets_tags)
    lookup = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    lookup[tags.astype(np.int64)] = np.arange(len(tags))
    order = lookup[used]
    compact = np.full(int(tags.max()) + 1, -1, dtype=np.int64)
    compact[used] = np.arange(len(used))
    points = coords[order]
    tets = compact[tets_tags]
    vertex_tags = {}
    for surf, name in face_names.items():
        node_tags, _ = gmsh.model.mesh.getNodesForPhysicalGroup(2, surf)
        idx = compact[node_tags.astype(np.int64)]
        vertex_tags[name] = np.unique(np.concatenate([vertex_tags.get(name, []), idx[idx >= 0]])).astype(np.int64)
    return TetMesh.from_arrays(points, tets, source=source, vertex_tags=vertex_tags)


def _name_surfaces(gmsh, classify) -> dict[int, str]:
    """Create one physical group per name given by ``classify(bounding box) -> name``."""
    groups: dict[str, list[int]] = {}
    for dim, tag in gmsh.model.getEntities(2):
        name = classify(np.array(gmsh.model.getBoundingBox(dim, tag)))
        groups.setdefault(name, []).append(tag)
    out = {}
    for name, tags in sorted(groups.items()):
        out[gmsh.model.addPhysicalGroup(2, tags)] = name
    vols = [t for _, t in gmsh.model.getEntities(3)]
    gmsh.model.addPhysicalGroup(3, vols)
    return out


def box(size=(0.1, 0.02, 0.02), h: float = 0.005, fine: dict | None = None) -> TetMesh:
    """A box from the origin to ``size`` (m), target edge length h (m). Faces xmin ... zmax.

    ``fine``: {"point": (3,) m, "h": m, "radius": m}, edges of ``fine["h"]`` within ``fine["radius"]`` of
    the point, growing by GRADE of the distance beyond it up to h: a mesh graded under a tool."""
    size = [float(s) for s in size]
    with _gmsh_session("box", h) as gmsh:
        gmsh.model.occ.addBox(0, 0, 0, *size)
        gmsh.model.occ.synchronize()
        tol = 1e-3 * h  # OCC pads bounding boxes by about 1e-7 m

        def classify(bb):
            for axis, name in enumerate("xyz"):
                if bb[3 + axis] - bb[axis] < tol:
                    return f"{name}min" if abs(bb[axis]) < tol else f"{name}max"
            return "other"

        names = _name_surfaces(gmsh, classify)
        if fine is not None:
            _graded(gmsh, h, **fine)
        gmsh.model.mesh.generate(3)
        graded = "" if fine is None else f", fine={fine}"
        return _extract(gmsh, f"box(size={size}, h={h}{graded})", names)


#: How fast a graded mesh's edges grow away from its fine region: by this fraction of the distance.
GRADE = 0.35


def _graded(gmsh, h_max: float, point, h: float, radius: float) -> None:
    """Edge lengths h (m) within ``radius`` (m) of ``point`` (3,) m, growing by GRADE of the distance
    beyond it, up to h_max (gmsh's Distance and MathEval fields)."""
    anchor = gmsh.model.occ.addPoint(*[float(c) for c in point])
    gmsh.model.occ.synchronize()
    field = gmsh.model.mesh.field
    distance = field.add("Distance")
    field.setNumbers(distance, "PointsList", [anchor])
    size = field.add("MathEval")
    field.setString(size, "F", f"min({h_max}, {h} + {GRADE} * max(F{distance} - {radius}, 0))")
    field.setAsBackgroundMesh(size)
    gmsh.option.setNumber("Mesh.MeshSizeMin", h / 2.0)
    gmsh.option.setNumber("Mesh.MeshSizeExtendFromBoundary", 0)
    gmsh.option.setNumber("Mesh.MeshSizeFromPoints", 0)


def grid(size=(0.02, 0.02, 0.03), h: float = 0.005) -> TetMesh:
    """A box from the origin to ``size`` (m) cut into cubes of side h (m), six tetrahedra each, with no
    mesher: every plane x, y or z = k h is a union of faces, so layers, inclusions and loads drawn on
    those planes are resolved exactly. Each side must be a whole number of h. Faces carry the vertex
    tags xmin ... zmax like ``box``'s."""
    size = np.asarray([float(s) for s in size])
    cells = size / h
    if not (
        h > 0.0 and np.all(np.abs(cells - np.round(cells)) <= 1e-9 * np.maximum(cells, 1.0)) and np.all(cells >= 0.5)
    ):
        k = int(np.argmax(np.abs(cells - np.round(cells))))
        raise InputError(f"grid: size[{k}] = {size[k]!r} m is not a whole number of h = {h!r} m")
    mesh = structured_box(size, np.round(cells).astype(int))
    x, tags = mesh.points, {}
    for axis, name in enumerate("xyz"):
        tags[f"{name}min"] = np.flatnonzero(np.abs(x[:, axis]) <= 1e-12 * size[axis])
        tags[f"{name}max"] = np.flatnonzero(np.abs(x[:, axis] - size[axis]) <= 1e-12 * size[axis])
    return TetMesh(mesh.points, mesh.tets, vertex_tags=tags, source=f"grid(size={size.tolist()}, h={h})")


def _axial_classify(tol):
    def classify(bb):
        if bb[5] - bb[2] < tol:
            return "bottom" if abs(bb[2]) < tol else "top"
        return "side"

    return classify


def cylinder(radius: float = 0.01, length: float = 0.1, h: float = 0.004) -> TetMesh:
    """A solid cylinder along z from 0 to ``length``. Faces bottom, top, side."""
    with _gmsh_session("cylinder", h) as gmsh:
        gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, length, radius)
        gmsh.model.occ.synchronize()
        names = _name_surfaces(gmsh, _axial_classify(1e-3 * h))
        gmsh.model.mesh.generate(3)
        return _extract(gmsh, f"cylinder(radius={radius}, length={length}, h={h})", names)


def tube(inner_radius: float = 0.006, outer_radius: float = 0.01, length: float = 0.1, h: float = 0.003) -> TetMesh:
    """A hollow cylinder (a vessel, an intestine) along z. Faces bottom, top, outer, inner."""
    if not 0.0 < inner_radius < outer_radius:
        raise InputError(f"tube: need 0 < inner_radius < outer_radius, got {inner_radius}, {outer_radius}")
    with _gmsh_session("tube", h) as gmsh:
        outer = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, length, outer_radius)
        inner = gmsh.model.occ.addCylinder(0, 0, 0, 0, 0, length, inner_radius)
        gmsh.model.occ.cut([(3, outer)], [(3, inner)])
        gmsh.model.occ.synchronize()
        tol = 1e-3 * h
        mid = 0.5 * (inner_radius + outer_radius)

        def classify(bb):
            if bb[5] - bb[2] < tol:
                return "bottom" if abs(bb[2]) < tol else "top"
            return "outer" if bb[3] > mid else "inner"

        names = _name_surfaces(gmsh, classify)
        gmsh.model.mesh.generate(3)
        return _extract(
            gmsh, f"tube(inner_radius={inner_radius}, outer_radius={outer_radius}, length={length}, h={h})", names
        )


def liver(scale: float = 1.0, h: float = 0.0102) -> TetMesh:
    """A smooth two-lobed organ-like solid: a large right lobe and a smaller left lobe, fused.

    Ellipsoids (semi-axes in m, times ``scale``): right lobe (0.09, 0.07, 0.04) at the origin, left
    lobe (0.07, 0.045, 0.028) centred at (-0.09, 0.02, 0.005). At the default size, about 1400
    vertices and 6300 tetrahedra, the size of the liver of Picinbono et al. (2003). The surface facing
    -y is the "back" (where the organ is held); all faces are tagged "surface".
    """
    with _gmsh_session("liver", h * scale) as gmsh:
        occ = gmsh.model.occ
        right = occ.addSphere(0, 0, 0, 1.0)
        occ.dilate([(3, right)], 0, 0, 0, 0.09 * scale, 0.07 * scale, 0.04 * scale)
        left = occ.addSphere(0, 0, 0, 1.0)
        occ.dilate([(3, left)], 0, 0, 0, 0.07 * scale, 0.045 * scale, 0.028 * scale)
        occ.translate([(3, left)], -0.09 * scale, 0.02 * scale, 0.005 * scale)
        occ.fuse([(3, right)], [(3, left)])
        occ.synchronize()
        names = _name_surfaces(gmsh, lambda bb: "surface")
        gmsh.model.mesh.generate(3)
        return _extract(gmsh, f"liver(scale={scale}, h={h})", names)


def generate(generator: str, **params) -> TetMesh:
    """Dispatch to a generator by name with its keyword parameters."""
    funcs = {"box": box, "grid": grid, "cylinder": cylinder, "tube": tube, "liver": liver}
    if generator not in funcs:
        raise InputError(f"generator = {generator!r}: must be one of {', '.join(GENERATORS)} or file")
    return funcs[generator](**params)


def structured_cube(cells: int = 11, size: float = 1.0) -> TetMesh:
    """A cube of side ``size`` (m) cut into cells^3 cubes of six tetrahedra each (Freudenthal's, around
    each cube's main diagonal): (cells + 1)^3 vertices, 6 cells^3 tetrahedra, no gmsh. The benchmark
    mesh the engines' authors quote (11 cells: 1728 vertices, 7986 tetrahedra)."""
    if not (isinstance(cells, int) and cells >= 1):
        raise InputError(f"structured_cube: cells = {cells!r}: must be a positive integer")
    n = cells + 1
    g = np.linspace(0.0, size, n)
    x, y, z = np.meshgrid(g, g, g, indexing="ij")
    points = np.stack([x.ravel(), y.ravel(), z.ravel()], axis=1)
    i, j, k = (a.ravel() for a in np.meshgrid(*(np.arange(cells),) * 3, indexing="ij"))

    def v(di, dj, dk):
        return ((i + di) * n + (j + dj)) * n + (k + dk)

    corners = [v(0, 0, 0), v(1, 0, 0), v(1, 1, 0), v(0, 1, 0), v(0, 0, 1), v(1, 0, 1), v(1, 1, 1), v(0, 1, 1)]
    # the six paths from corner 0 to corner 6 along the cube's edges, one tetrahedron each
    paths = [(1, 2), (2, 3), (3, 7), (7, 4), (4, 5), (5, 1)]
    tets = np.concatenate([np.stack([corners[0], corners[a], corners[b], corners[6]], axis=1) for a, b in paths])
    return TetMesh.from_arrays(points, tets, source=f"structured cube {cells}^3")
