"""Region selectors (docs/data-flow.md): box, sphere, tag, all, and a cell field's range.

A region answers two questions: which vertices of a mesh it holds (``vertices``), and whether
arbitrary points lie in it (``contains``), the second for the finer meshes and the P2 nodes of the
reference, which must see the same region as the scene mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

from .tetmesh import TetMesh

#: Points within this distance (relative to the mesh size) of a region's boundary count as inside:
#: gmsh places boundary vertices on the geometry to ~1e-12 relative, and regions drawn on a face
#: (x = 0) must catch them.
GEOMETRIC_TOL = 1e-9


@dataclass(frozen=True)
class Region:
    """Base class. ``describe()`` gives the scene-file text of the region."""

    def vertices(self, mesh: TetMesh) -> np.ndarray:
        return np.flatnonzero(self.contains(mesh.points, mesh))

    def contains(self, x: np.ndarray, mesh: TetMesh) -> np.ndarray:  # pragma: no cover - abstract
        raise NotImplementedError

    def rule(self) -> dict | None:
        """The region as data another program can apply to a mesh of its own (an engine that meshes the
        body itself: ``tissuebench export``'s "regions"); None where the region is drawn on this mesh (its
        tags, a field, vertex ids) and no rule carries it to another."""
        return None


@dataclass(frozen=True)
class BoxRegion(Region):
    lo: tuple
    hi: tuple

    def contains(self, x, mesh=None):
        return np.all((x >= np.asarray(self.lo)) & (x <= np.asarray(self.hi)), axis=1)

    def describe(self):
        return f"box = [{list(self.lo)}, {list(self.hi)}]"

    def rule(self):
        return {"box": {"lo_m": [float(v) for v in self.lo], "hi_m": [float(v) for v in self.hi]}}


@dataclass(frozen=True)
class SphereRegion(Region):
    center: tuple
    radius: float

    def contains(self, x, mesh=None):
        return np.linalg.norm(x - np.asarray(self.center), axis=1) <= self.radius

    def describe(self):
        return f"sphere = {{ center = {list(self.center)}, radius = {self.radius} }}"

    def rule(self):
        return {"sphere": {"center_m": [float(v) for v in self.center], "radius_m": float(self.radius)}}


@dataclass(frozen=True)
class AllRegion(Region):
    def contains(self, x, mesh=None):
        return np.ones(len(x), dtype=bool)

    def describe(self):
        return "all = true"

    def rule(self):
        return {"all": True}


@dataclass(frozen=True)
class VertexRegion(Region):
    """An explicit set of vertex indices of one mesh (a region carried onto a refined mesh by
    ``spanned``); it has no geometry of its own."""

    indices: tuple

    def vertices(self, mesh):
        return np.asarray(self.indices, dtype=np.int64)

    def contains(self, x, mesh):
        raise NotImplementedError("a VertexRegion selects vertices of its own mesh only")

    def describe(self):
        return f"{len(self.indices)} vertices"


@dataclass(frozen=True)
class TagRegion(Region):
    """A named group of the mesh. Face groups hold the points on their triangles; volume groups the
    points inside their tetrahedra (so a refined mesh or P2 nodes see the same region)."""

    name: str

    def vertices(self, mesh):
        return mesh.select_tag(self.name)

    def contains(self, x, mesh):
        x = np.asarray(x, dtype=float)
        scale = float(np.ptp(mesh.points, axis=0).max())
        tol = GEOMETRIC_TOL * scale
        if self.name in mesh.cell_tags:
            tets = mesh.tets[np.asarray(mesh.cell_tags[self.name])]
            return _inside_tets(mesh.points, tets, x, tol)
        verts = mesh.select_tag(self.name)
        faces = mesh.boundary
        faces = faces[np.all(np.isin(faces, verts), axis=1)]
        return _on_triangles(mesh.points, faces, x, tol)

    def describe(self):
        return f'tag = "{self.name}"'


@dataclass(frozen=True)
class FieldRegion(Region):
    """The tetrahedra whose value of the mesh's cell field ``name`` (TetMesh.cell_fields, read from the
    file's cell data) lies in [lo, hi], and the points inside them (so a refined mesh or P2 nodes see
    the same region). For a [[material]] table."""

    name: str
    lo: float
    hi: float

    def cells(self, mesh: TetMesh) -> np.ndarray:
        """(K,) int64: the tetrahedra of ``mesh`` the region holds; KeyError naming the fields there are
        if the mesh has no field ``name``."""
        if self.name not in mesh.cell_fields:
            raise KeyError(
                f"{self.name!r} is not a cell field of the mesh (its fields: {', '.join(sorted(mesh.cell_fields)) or 'none'})"
            )
        v = mesh.cell_fields[self.name]
        return np.flatnonzero((v >= self.lo) & (v <= self.hi)).astype(np.int64)

    def contains(self, x, mesh):
        tol = GEOMETRIC_TOL * float(np.ptp(mesh.points, axis=0).max())
        return _inside_tets(mesh.points, mesh.tets[self.cells(mesh)], np.asarray(x, dtype=float), tol)

    def describe(self):
        return f'field = {{ name = "{self.name}", min = {self.lo:g}, max = {self.hi:g} }}'


def _on_triangles(points, faces, x, tol):
    """Whether each point of x (K, 3) lies on one of the triangles (F, 3), within tol (m)."""
    out = np.zeros(len(x), dtype=bool)
    if len(faces) == 0:
        return out
    tri = points[faces]
    centroid = tri.mean(axis=1)
    radius = np.linalg.norm(tri - centroid[:, None], axis=2).max()
    tree = cKDTree(centroid)
    for k, cand in enumerate(tree.query_ball_point(x, radius + tol)):
        for f in cand:
            a, b, c = tri[f]
            n = np.cross(b - a, c - a)
            area2 = np.linalg.norm(n)
            if abs(np.dot(x[k] - a, n)) / area2 > tol:
                continue
            # barycentric coordinates in the triangle's plane
            l1 = np.dot(np.cross(c - b, x[k] - b), n) / area2**2
            l2 = np.dot(np.cross(a - c, x[k] - c), n) / area2**2
            l3 = 1.0 - l1 - l2
            eps = tol / np.sqrt(area2)
            if min(l1, l2, l3) >= -eps:
                out[k] = True
                break
    return out


def _inside_tets(points, tets, x, tol):
    """Whether each point of x (K, 3) lies in one of the tetrahedra (T, 4), within tol."""
    out = np.zeros(len(x), dtype=bool)
    X = points[tets]
    centroid = X.mean(axis=1)
    radius = np.linalg.norm(X - centroid[:, None], axis=2).max()
    D = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    Dinv = np.linalg.inv(D)
    tree = cKDTree(centroid)
    scale = np.cbrt(np.abs(np.linalg.det(D)))
    for k, cand in enumerate(tree.query_ball_point(x, radius + tol)):
        for t in cand:
            lam = Dinv[t] @ (x[k] - X[t, 0])
            if min(lam.min(), 1.0 - lam.sum()) >= -tol / scale[t]:
                out[k] = True
                break
    return out


def locate(mesh: TetMesh, x: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """The tetrahedron of ``mesh`` holding each point of x (K, 3) m: (K,) int64, -1 for a point in none.

    A point within ``tol`` (relative to each tetrahedron's size) of a face counts as inside; where two
    tetrahedra hold it, the nearer centroid wins. Candidates are the nearest centroids, then, for the
    few points they miss, every tetrahedron whose bounding sphere reaches the point.
    """
    x = np.asarray(x, dtype=float).reshape(-1, 3)
    out = np.full(len(x), -1, dtype=np.int64)
    if len(x) == 0 or mesh.n_tets == 0:
        return out
    X = mesh.points[mesh.tets]
    centroid = X.mean(axis=1)
    D = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    Dinv = np.linalg.inv(D)
    scale = np.cbrt(np.abs(np.linalg.det(D)))
    tree = cKDTree(centroid)

    def inside(points, t):
        lam = np.einsum("kij,kj->ki", Dinv[t], points - X[t, 0])
        return np.minimum(lam.min(axis=1), 1.0 - lam.sum(axis=1)) >= -tol / scale[t]

    _, near = tree.query(x, k=min(8, mesh.n_tets))
    near = near.reshape(len(x), -1)
    for j in range(near.shape[1]):
        todo = np.flatnonzero(out < 0)
        hit = inside(x[todo], near[todo, j])
        out[todo[hit]] = near[todo[hit], j]
    radius = np.linalg.norm(X - centroid[:, None], axis=2).max()
    for k in np.flatnonzero(out < 0):
        cand = np.asarray(tree.query_ball_point(x[k], radius * (1.0 + tol)), dtype=np.int64)
        if len(cand):
            hit = cand[inside(np.repeat(x[k][None], len(cand), axis=0), cand)]
            if len(hit):
                out[k] = hit[np.argmin(np.linalg.norm(centroid[hit] - x[k], axis=1))]
    return out


def spanned(mesh: TetMesh, selected: np.ndarray, x: np.ndarray, tol: float = 1e-9) -> np.ndarray:
    """Whether each point of x (K, 3) m lies on an entity of ``mesh`` spanned by selected vertices.

    A point inside the mesh is carried by the smallest vertex, edge, face or tetrahedron that holds it
    (the vertices where its barycentric coordinates exceed ``tol``); it is spanned when every vertex of
    that carrier is selected. So a region that selects scene-mesh vertices constrains, on a P2 or a
    refined mesh, exactly the nodes of the edges, faces and tetrahedra those vertices span: an edge's
    midside node only if both its ends are selected, a refined face only if its parent's three vertices
    are. ``selected`` is (S,) int vertex indices; points outside the mesh (beyond ``tol``) are an error.
    """
    x = np.ascontiguousarray(x, dtype=float).reshape(-1, 3)
    chosen = np.zeros(mesh.n_vertices, dtype=bool)
    chosen[np.asarray(selected, dtype=np.int64)] = True
    out = np.zeros(len(x), dtype=bool)
    if len(x) == 0:
        return out
    X = mesh.points[mesh.tets]
    D = np.stack([X[:, 1] - X[:, 0], X[:, 2] - X[:, 0], X[:, 3] - X[:, 0]], axis=2)
    Dinv = np.linalg.inv(D)
    tree = cKDTree(X.mean(axis=1))
    k = min(16, mesh.n_tets)
    _, cand = tree.query(x, k=k)
    cand = np.asarray(cand).reshape(len(x), k)
    b = np.einsum("pcij,pcj->pci", Dinv[cand], x[:, None, :] - X[cand, 0])  # (K, k, 3)
    bary = np.concatenate([1.0 - b.sum(axis=2, keepdims=True), b], axis=2)  # (K, k, 4)
    inside = bary.min(axis=2) >= -tol
    found = inside.any(axis=1)
    for p in np.flatnonzero(~found):  # far from the nearest centroids (large elements): all candidates
        bb = np.einsum("cij,cj->ci", Dinv, x[p] - X[:, 0])
        full = np.concatenate([1.0 - bb.sum(axis=1, keepdims=True), bb], axis=1)
        hit = np.flatnonzero(full.min(axis=1) >= -tol)
        if len(hit) == 0:
            raise ValueError(f"point {x[p].tolist()} lies outside the mesh")
        carrier = mesh.tets[hit[0]][full[hit[0]] > tol]
        out[p] = bool(chosen[carrier].all())
    idx = np.flatnonzero(found)
    first = np.argmax(inside[idx], axis=1)
    tets = mesh.tets[cand[idx, first]]  # (F, 4)
    weights = bary[idx, first]  # (F, 4)
    out[idx] = np.all(chosen[tets] | (weights <= tol), axis=1)
    return out
