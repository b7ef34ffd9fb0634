"""ParaView output: a displacement time series as a ``.pvd`` collection of ``.vtu`` files.

``write_series(target, name, points, tets, times, fields)`` writes ``NAME_000000.vtu``, ... (one
unstructured grid per output time, with the point fields) and ``NAME.pvd`` listing them with their
times, the file ParaView opens (File > Open, then Apply: the time slider walks the series). ``target`` is a
directory, or a path ending in ``.pvd`` whose folder receives the ``.vtu`` files. Every file is written
to a temporary name and renamed, the collection last, so an interrupted run leaves no half-written file
and no collection that lists a missing step.
"""

from __future__ import annotations

import os
from pathlib import Path
from xml.sax.saxutils import quoteattr

import numpy as np

from meshes.io import atomic_write
from verification.scene import SceneError


def series_path(target: str | os.PathLike, name: str) -> Path:
    """The .pvd file for ``target`` (a directory, or a .pvd path) and a series name."""
    target = Path(target)
    if target.suffix.lower() == ".pvd":
        return target
    if target.suffix:
        raise SceneError(f"--vtk {target}: give a directory or a .pvd file, not a {target.suffix} file")
    return target / f"{name}.pvd"


def write_series(
    target: str | os.PathLike,
    name: str,
    points: np.ndarray,
    tets: np.ndarray,
    times: np.ndarray,
    fields: dict[str, np.ndarray],
) -> Path:
    """Write the series and return the .pvd path.

    Args:
        points: (N, 3) float64 rest positions, m.
        tets: (M, 4) int64 tetrahedra.
        times: (T,) float64 output times, s.
        fields: name -> (T, N, 3) or (T, N) float64 point values at each time (displacements in m).
    """
    import meshio

    pvd = series_path(target, name)
    try:
        pvd.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"--vtk {target}: cannot create the directory ({exc.strerror})") from None
    times = np.atleast_1d(np.asarray(times, dtype=float))
    for key, values in fields.items():
        if values.shape[:2] != (len(times), len(points)):
            raise ValueError(
                f"field {key}: shape {values.shape} does not match {len(times)} times x {len(points)} points"
            )
    grids = [
        meshio.Mesh(
            points, [("tetra", tets)], point_data={key: np.ascontiguousarray(v[k]) for key, v in fields.items()}
        )
        for k in range(len(times))
    ]
    return _write_collection(pvd, times, grids)


def write_levels(target: str | os.PathLike, name: str, levels: list[dict]) -> Path:
    """An adaptive reference's levels (``verification.runs.reference.read_levels``) as a series whose step k
    is level k: its mesh, the P2 displacement (m) at its vertices and, as cell data, the indicator eta^2
    (J) that chose the next level's cells (zero where that level's P3 check found no equilibrium).
    Returns the .pvd path."""
    import meshio

    pvd = series_path(target, name)
    try:
        pvd.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise SceneError(f"--vtk {target}: cannot create the directory ({exc.strerror})") from None
    grids = []
    for level in levels:
        eta2 = level["eta2"] if level["eta2"] is not None else np.zeros(len(level["cells"]))
        grids.append(
            meshio.Mesh(
                level["x"],
                [("tetra", level["cells"])],
                point_data={"displacement": np.ascontiguousarray(level["u"])},
                cell_data={"eta2": [np.ascontiguousarray(eta2)]},
            )
        )
    return _write_collection(pvd, np.arange(len(levels), dtype=float), grids)


def _write_collection(pvd: Path, times: np.ndarray, grids: list) -> Path:
    """Each grid (a meshio.Mesh) as ``pvd``'s step at its time, each file through a temporary name, the
    collection last."""
    import meshio

    entries = []
    for k, (t, grid) in enumerate(zip(times, grids, strict=True)):
        vtu = pvd.parent / f"{pvd.stem}_{k:06d}.vtu"
        atomic_write(vtu, lambda tmp, grid=grid: meshio.write(tmp, grid, file_format="vtu"))
        entries.append(f'    <DataSet timestep="{t!r}" group="" part="0" file={quoteattr(vtu.name)}/>')
    text = "\n".join(
        [
            '<?xml version="1.0"?>',
            '<VTKFile type="Collection" version="0.1" byte_order="LittleEndian">',
            "  <Collection>",
            *entries,
            "  </Collection>",
            "</VTKFile>",
            "",
        ]
    )
    atomic_write(pvd, lambda tmp: Path(tmp).write_text(text))
    return pvd
