"""TetMesh: a validated linear tetrahedral mesh, its quality, hash and region selectors."""

from __future__ import annotations

import hashlib
from dataclasses import dataclass, field

import numpy as np

from realtime.geometry import (
    InvalidMeshError,
    boundary_faces,
    check_tets,
    inverse_order,
    min_altitudes,
    orient_positive,
    red_refinement,
    signed_volumes,
    spatial_numbering,
    unique_edges,
)

__all__ = ["InvalidMeshError", "TetMesh", "structured_box"]


@dataclass(frozen=True)
class TetMesh:
    """A tetrahedral mesh.

    Attributes:
        points: (N, 3) float64 vertex positions, m.
        tets: (M, 4) int64, positively oriented.
        vertex_tags: name -> (K,) int64 vertex indices (gmsh physical groups of faces and volumes).
        cell_tags: name -> (K,) int64 tetrahedron indices.
        cell_fields: name -> (M,) float64, a value per tetrahedron read from the mesh file (its cell
            data: a stiffness map, a segmentation label), in any unit the file uses.
        source: where the mesh came from (a file path or a generator description).
        notes: what reading the mesh repaired (merged duplicate vertices, turned tetrahedra...), one
            sentence each.
    """

    points: np.ndarray
    tets: np.ndarray
    vertex_tags: dict = field(default_factory=dict)
    cell_tags: dict = field(default_factory=dict)
    source: str = ""
    notes: tuple = ()
    cell_fields: dict = field(default_factory=dict)

    def __post_init__(self):
        pts = np.ascontiguousarray(self.points, dtype=np.float64)
        tets = np.ascontiguousarray(self.tets, dtype=np.int64)
        object.__setattr__(self, "points", pts)
        object.__setattr__(self, "tets", tets)
        check_tets(pts, tets, where=self.source or "mesh")
        fields = {name: np.ascontiguousarray(v, dtype=np.float64) for name, v in self.cell_fields.items()}
        for name, values in fields.items():
            if values.shape != (len(tets),):
                where = self.source or "mesh"
                raise InvalidMeshError(f"{where}: cell field {name!r} has shape {values.shape}, need ({len(tets)},)")
        object.__setattr__(self, "cell_fields", fields)

    @staticmethod
    def from_arrays(points, tets, source: str = "", fix_orientation: bool = True, **tags) -> TetMesh:
        """A mesh from arrays. If *every* tetrahedron is negatively oriented (a file's convention) the
        mesh is reoriented; a mix of orientations is an error naming the first inverted element."""
        points = np.asarray(points, dtype=np.float64)
        tets = np.asarray(tets, dtype=np.int64)
        if fix_orientation and len(tets):
            vol = signed_volumes(points, tets)
            if np.all(vol < 0.0):
                tets = orient_positive(points, tets)
        return TetMesh(points, tets, source=source, **tags)

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def n_tets(self) -> int:
        return len(self.tets)

    @property
    def boundary(self) -> np.ndarray:
        """Boundary triangles (F, 3) int64, outward normals."""
        return boundary_faces(self.tets)

    @property
    def surface_vertices(self) -> np.ndarray:
        """Indices (S,) int64 of the vertices on the boundary, sorted."""
        return np.unique(self.boundary)

    @property
    def edges(self) -> np.ndarray:
        return unique_edges(self.tets)

    def mean_edge(self) -> float:
        """The mean edge length, m: the h of convergence studies and of the advisor's refinements."""
        e = self.edges
        return float(np.linalg.norm(self.points[e[:, 1]] - self.points[e[:, 0]], axis=1).mean())

    def refined(self) -> TetMesh:
        """The mesh cut uniformly, each tetrahedron into eight (red refinement: four corner tetrahedra
        and the inner octahedron split along its shortest diagonal). The vertices keep their
        indices and the edge midpoints follow, so the coarse mesh's vertices are the first N of the fine
        one's. Cell tags and fields pass to the children; a vertex tag takes the midpoints of the edges of
        tagged boundary triangles."""
        points, tets = red_refinement(self.points, self.tets)
        t = self.tets
        n = self.n_vertices
        index = {(int(a), int(b)): n + k for k, (a, b) in enumerate(self.edges)}
        cell_tags = {
            k: np.concatenate([np.asarray(v) + i * len(t) for i in range(8)]) for k, v in self.cell_tags.items()
        }
        vertex_tags = {}
        faces = self.boundary
        for name, verts in self.vertex_tags.items():
            inside = np.zeros(n, dtype=bool)
            inside[np.asarray(verts)] = True
            tagged = faces[np.all(inside[faces], axis=1)]
            mids = [
                index[(int(min(f[a], f[b])), int(max(f[a], f[b])))] for f in tagged for a, b in ((0, 1), (1, 2), (0, 2))
            ]
            vertex_tags[name] = np.unique(
                np.concatenate([np.asarray(verts, dtype=np.int64), np.asarray(mids, dtype=np.int64)])
            )
        return TetMesh(
            points,
            orient_positive(points, tets),
            vertex_tags=vertex_tags,
            cell_tags=cell_tags,
            source=f"{self.source} refined",
            cell_fields={k: np.tile(np.asarray(v, dtype=np.float64), 8) for k, v in self.cell_fields.items()},
        )

    def renumbered(self) -> tuple[TetMesh, np.ndarray, np.ndarray]:
        """The same mesh numbered along the body (realtime.geometry.spatial_numbering: the tetrahedra in
        Morton order, the vertices in the order they first appear in them, those only the first half of
        the tetrahedra holds before those both halves hold, before the rest), which the real-time engine
        steps faster, more so on threads; with vertex_order (N,) and tet_order (M,) int64, the old index
        of each new vertex and tetrahedron (a field on the old vertices maps by ``u[vertex_order]``).
        Tags and cell fields follow their vertices and tetrahedra."""
        vertex_order, tet_order = spatial_numbering(self.points, self.tets)
        new_vertex, new_tet = inverse_order(vertex_order), inverse_order(tet_order)
        mesh = TetMesh(
            self.points[vertex_order],
            new_vertex[self.tets[tet_order]],
            vertex_tags={k: np.sort(new_vertex[np.asarray(v, dtype=np.int64)]) for k, v in self.vertex_tags.items()},
            cell_tags={k: np.sort(new_tet[np.asarray(v, dtype=np.int64)]) for k, v in self.cell_tags.items()},
            source=f"{self.source} renumbered along the body",
            notes=self.notes,
            cell_fields={k: v[tet_order] for k, v in self.cell_fields.items()},
        )
        return mesh, vertex_order, tet_order

    def parts(self) -> tuple[int, np.ndarray]:
        """Connected parts (tetrahedra sharing a vertex are connected): their number and the part of
        each vertex, (N,) int64 in 0..parts-1, numbered by their lowest vertex."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        e = self.edges
        n = self.n_vertices
        graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(n, n))
        count, labels = connected_components(graph, directed=False)
        return int(count), labels.astype(np.int64)

    def blocks(self) -> tuple[int, np.ndarray]:
        """Blocks: tetrahedra joined through shared faces (rigid together); blocks that meet only at a
        vertex or an edge turn about it. Their number and the block of each tetrahedron, (M,) int64."""
        from scipy.sparse import coo_matrix
        from scipy.sparse.csgraph import connected_components

        faces = np.sort(self.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]], axis=2).reshape(-1, 3)
        _, face = np.unique(faces, axis=0, return_inverse=True)
        tet = np.repeat(np.arange(self.n_tets), 4)
        graph = coo_matrix((np.ones(len(tet)), (tet, face.ravel())), shape=(self.n_tets, face.max() + 1))
        count, labels = connected_components(graph @ graph.T, directed=False)
        return int(count), labels.astype(np.int64)

    def volumes(self) -> np.ndarray:
        """(M,) float64, m^3."""
        return signed_volumes(self.points, self.tets)

    def bounding_box(self) -> tuple[np.ndarray, np.ndarray]:
        return self.points.min(axis=0), self.points.max(axis=0)

    def sha256(self) -> str:
        """Hash of the vertex coordinates and connectivity (bytes of float64 and int64 arrays), and of
        the cell fields, by name, when there are any (a material drawn from one depends on it)."""
        h = hashlib.sha256()
        h.update(np.ascontiguousarray(self.points, dtype="<f8").tobytes())
        h.update(np.ascontiguousarray(self.tets, dtype="<i8").tobytes())
        for name in sorted(self.cell_fields):
            h.update(name.encode())
            h.update(np.ascontiguousarray(self.cell_fields[name], dtype="<f8").tobytes())
        return h.hexdigest()

    def tags_sha256(self) -> str:
        """Hash of the vertex and cell tags, by name (indices as int64). Apart from ``sha256``, which is
        the mesh's geometry and cell data (the stored meshes' manifest and the gates' baselines record
        it); a scene's hash holds both, since a region or a material drawn by tag depends on them."""
        h = hashlib.sha256()
        for kind, tags in (("vertex", self.vertex_tags), ("cell", self.cell_tags)):
            for name in sorted(tags):
                h.update(f"{kind}:{name}".encode())
                h.update(np.ascontiguousarray(np.sort(tags[name]), dtype="<i8").tobytes())
        return h.hexdigest()

    def quality(self) -> dict:
        """Quality report: dihedral angles (degrees), aspect ratio, volumes, edge lengths.

        Aspect ratio: longest edge / (2 sqrt(6) inradius), 1 for the regular tetrahedron and growing
        without bound for slivers and needles.
        """
        x = self.points[self.tets]
        vol = np.abs(self.volumes())
        faces = np.array([(1, 2, 3), (0, 3, 2), (0, 1, 3), (0, 2, 1)])
        fx = x[:, faces]  # (M, 4, 3, 3)
        normals = np.cross(fx[:, :, 1] - fx[:, :, 0], fx[:, :, 2] - fx[:, :, 0])
        areas = 0.5 * np.linalg.norm(normals, axis=2)
        n = normals / np.linalg.norm(normals, axis=2, keepdims=True)
        dihedral = []
        for a, b in [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]:
            cos = -np.einsum("ij,ij->i", n[:, a], n[:, b])
            dihedral.append(np.degrees(np.arccos(np.clip(cos, -1.0, 1.0))))
        dihedral = np.stack(dihedral, axis=1)
        pairs = [(0, 1), (0, 2), (0, 3), (1, 2), (1, 3), (2, 3)]
        lengths = np.stack([np.linalg.norm(x[:, a] - x[:, b], axis=1) for a, b in pairs], axis=1)
        inradius = 3.0 * vol / areas.sum(axis=1)
        aspect = lengths.max(axis=1) / (2.0 * np.sqrt(6.0) * inradius)
        return {
            "n_vertices": self.n_vertices,
            "n_tets": self.n_tets,
            "n_boundary_faces": int(len(self.boundary)),
            "min_dihedral_deg": float(dihedral.min()),
            "max_dihedral_deg": float(dihedral.max()),
            "max_aspect_ratio": float(aspect.max()),
            "mean_aspect_ratio": float(aspect.mean()),
            "min_volume_m3": float(vol.min()),
            "max_volume_m3": float(vol.max()),
            "total_volume_m3": float(vol.sum()),
            "min_edge_m": float(lengths.min()),
            "max_edge_m": float(lengths.max()),
            "min_altitude_m": float(min_altitudes(self.points, self.tets).min()),
        }

    # ---- region selectors (docs/data-flow.md) ----

    def select_box(self, lo, hi) -> np.ndarray:
        """Vertices with lo <= x <= hi componentwise, (K,) int64."""
        lo, hi = np.asarray(lo, float), np.asarray(hi, float)
        inside = np.all((self.points >= lo) & (self.points <= hi), axis=1)
        return np.flatnonzero(inside)

    def select_sphere(self, center, radius: float) -> np.ndarray:
        """Vertices with |x - center| <= radius, (K,) int64."""
        d = np.linalg.norm(self.points - np.asarray(center, float), axis=1)
        return np.flatnonzero(d <= radius)

    def select_tag(self, name: str) -> np.ndarray:
        """Vertices of a named group; KeyError listing the known names."""
        if name in self.vertex_tags:
            return np.asarray(self.vertex_tags[name], dtype=np.int64)
        if name in self.cell_tags:
            return np.unique(self.tets[np.asarray(self.cell_tags[name])])
        known = sorted(set(self.vertex_tags) | set(self.cell_tags))
        raise KeyError(f"tag {name!r} is not in the mesh; its tags are {known}")


def structured_box(size, divisions) -> TetMesh:
    """A box [0, size] cut into nx x ny x nz cubes of six tetrahedra each (Kuhn subdivision).

    Exactly reproducible with no mesher, conforming, and with every tetrahedron of the same shape:
    the mesh of analytic and manufactured-solution tests.
    """
    size = np.asarray(size, dtype=float)
    nx, ny, nz = (int(d) for d in np.broadcast_to(divisions, (3,)))
    axes = [np.linspace(0.0, s, n + 1) for s, n in zip(size, (nx, ny, nz), strict=True)]
    points = np.stack(np.meshgrid(*axes, indexing="ij"), axis=-1).reshape(-1, 3)

    def idx(i, j, k):
        return (i * (ny + 1) + j) * (nz + 1) + k

    ii, jj, kk = np.meshgrid(np.arange(nx), np.arange(ny), np.arange(nz), indexing="ij")
    ii, jj, kk = ii.ravel(), jj.ravel(), kk.ravel()
    tets = []
    for perm in [(0, 1, 2), (0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0)]:
        c = [ii.copy(), jj.copy(), kk.copy()]
        verts = [idx(*c)]
        for ax in perm:
            c[ax] = c[ax] + 1
            verts.append(idx(*c))
        tets.append(np.stack(verts, axis=1))
    tets = np.concatenate(tets)
    return TetMesh(points, orient_positive(points, tets), source=f"structured_box({size.tolist()}, {[nx, ny, nz]})")
