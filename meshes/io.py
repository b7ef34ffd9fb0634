"""Reading and writing tetrahedral meshes through meshio (.msh, .vtu, .xdmf, and what else it reads)."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from .tetmesh import InvalidMeshError, TetMesh


def read_mesh(path: str | os.PathLike) -> TetMesh:
    """Read a tetrahedral mesh; lower-dimensional cells are dropped, unused vertices removed.

    gmsh physical groups become tags: of tetrahedra (cell tags) and of the vertices of tagged
    triangles (vertex tags). A file with no linear tetrahedra (hexahedra, quadratic tetrahedra,
    a surface mesh) is an InvalidMeshError naming the file and the cell types it has.
    """
    import meshio

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such mesh file")
    try:
        m = meshio.read(path)
    except Exception as exc:  # meshio raises many types for unreadable input
        raise InvalidMeshError(f"{path}: meshio cannot read it ({exc})") from exc
    blocks = [(i, c) for i, c in enumerate(m.cells) if c.type == "tetra"]
    if not blocks:
        kinds = sorted({c.type for c in m.cells})
        raise InvalidMeshError(f"{path}: not a linear tetrahedral mesh (cell types: {kinds})")
    tets = np.concatenate([c.data for _, c in blocks]).astype(np.int64)
    used = np.unique(tets)
    compact = np.full(len(m.points), -1, dtype=np.int64)
    compact[used] = np.arange(len(used))
    points = np.asarray(m.points, dtype=np.float64)[used]
    if points.shape[1] != 3:
        raise InvalidMeshError(f"{path}: points are {points.shape[1]}-dimensional, need 3")
    names = {}
    for name, pairs in getattr(m, "field_data", {}).items():
        names[int(pairs[0])] = name
    vertex_tags, cell_tags = {}, {}
    phys = m.cell_data.get("gmsh:physical")
    if phys is not None:
        offset = 0
        for i, cells in enumerate(m.cells):
            tags = np.asarray(phys[i])
            for t in np.unique(tags):
                name = names.get(int(t), str(int(t)))
                sel = cells.data[tags == t]
                if cells.type == "tetra":
                    idx = offset + np.flatnonzero(tags == t)
                    cell_tags[name] = np.concatenate([cell_tags.get(name, []), idx]).astype(np.int64)
                elif cells.type == "triangle":
                    v = compact[np.unique(sel)]
                    vertex_tags[name] = np.unique(np.concatenate([vertex_tags.get(name, []), v[v >= 0]])).astype(
                        np.int64
                    )
            if cells.type == "tetra":
                offset += len(cells.data)
    return TetMesh.from_arrays(points, compact[tets], source=str(path), vertex_tags=vertex_tags, cell_tags=cell_tags)


def write_mesh(mesh: TetMesh, path: str | os.PathLike, point_data: dict | None = None) -> Path:
    """Write a mesh (and optional point fields, each (N,) or (N, 3)) atomically: temp file, rename.

    Vertex tags are stored as 0/1 point fields ``tag:NAME`` so that ParaView shows them.
    """
    import meshio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    data = {f"tag:{k}": np.isin(np.arange(mesh.n_vertices), v).astype(np.int32) for k, v in mesh.vertex_tags.items()}
    data.update(point_data or {})
    m = meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data=data)
    fd, tmp = tempfile.mkstemp(suffix=path.suffix, dir=path.parent, prefix=".tmp-")
    os.close(fd)
    try:
        if path.suffix == ".msh":
            meshio.write(tmp, m, file_format="gmsh22", binary=False)
        elif path.suffix == ".xdmf":  # inline XML: one self-contained file survives the rename
            meshio.xdmf.write(tmp, m, data_format="XML")
        else:
            meshio.write(tmp, m)
        os.replace(tmp, path)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path
