"""What another engine wrote, read for judging (``tissuebench judge``; docs/commands.md).

A result is a displacement field (a static scene) or a time series of them (a dynamic one), with the
points it is given at, which need not be the scene mesh's:

- ``.npz``: ``displacement`` (N, 3) or (T, N, 3), ``points`` (N, 3) (default the scene mesh's vertices),
  optional ``times`` (T,) s, ``tets`` (M, 4) and ``reaction`` (T, 3) N (the tools' force on the body);
- ``.vtu`` / ``.vtk``: one field at the mesh's points, the point field named ``displacement`` (or the
  only point field with three components); the file's tetrahedra are kept;
- ``.pvd``: a ParaView series, each listed file a ``.vtu`` as above at its ``timestep``;
- ``.xdmf``: a meshio time series (or one field), the same field rule.

Every defect is an ``EngineResultError`` naming the file and what is wrong: a missing field, a wrong
shape, a value that is not finite.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from realtime.errors import InputError

#: A held component or a tool vertex may be this far (relative to the largest displacement) from where
#: the scene puts it: an engine whose tool is a penalty or a soft constraint holds it to a few percent;
#: an export made before the tool moved, or a result in another frame, is off by far more.
GAP = 0.05
#: ... and never nearer than the round-off of a position written in float32 (an engine's own arithmetic, a
#: VTK file), relative to the largest coordinate: eight of float32's machine epsilons. A body nothing loads
#: yet (a rigid tool short of it) has no displacement to take GAP of: newton's held vertices, read back
#: from float32, were 3.7e-9 m off there on the liver press.
POSITION_ROUNDOFF = 8.0 * float(np.finfo(np.float32).eps)
#: A result whose displacements are 10^k times the expected ones (k in UNITS) and whose rescaled field
#: is within SHAPE_MATCH of them (relative L2) is in other length units.
UNITS = {2: "centimetres", 3: "millimetres"}
SHAPE_MATCH = 0.5
#: The names a displacement field goes by, tried in this order.
FIELD_NAMES = ("displacement", "Displacement", "u", "U", "disp")


class EngineResultError(InputError):
    """A result file that cannot be judged; ``str()`` names the file and the defect."""


@dataclass(frozen=True)
class EngineResult:
    """A result as read: points (N, 3) m, times (T,) s (None where the file gives none), displacement
    (T, N, 3) m, tets (M, 4) or None, reaction (T, 3) N or None, and the file it came from. ``scale``
    has been applied to points and displacements (file units to metres)."""

    source: str
    points: np.ndarray
    times: np.ndarray | None
    displacement: np.ndarray
    tets: np.ndarray | None = None
    reaction: np.ndarray | None = None


def _field(path: Path, point_data: dict, n: int) -> np.ndarray:
    """The displacement field of one mesh's point data (N, 3)."""
    for name in FIELD_NAMES:
        if name in point_data:
            return np.asarray(point_data[name], dtype=float)
    vectors = [k for k, v in point_data.items() if np.ndim(v) == 2 and np.shape(v)[1] == 3]
    if len(vectors) == 1:
        return np.asarray(point_data[vectors[0]], dtype=float)
    raise EngineResultError(
        f"{path}: no displacement field: name it one of {', '.join(FIELD_NAMES)} "
        f"(point fields: {', '.join(point_data) or 'none'})"
    )


def _tets(mesh) -> np.ndarray | None:
    blocks = [c.data for c in mesh.cells if c.type == "tetra"]
    return np.concatenate(blocks).astype(np.int64) if blocks else None


def _read_mesh_file(path: Path):
    """meshio's reading of ``path``, what it prints kept off the terminal (``meshes.io.quiet_meshio_read``)."""
    from meshes.io import quiet_meshio_read

    try:
        return quiet_meshio_read(path)
    except Exception as exc:  # its reason, from meshio's exception or its last "Error:" line
        raise EngineResultError(f"{path}: cannot read it as a mesh with a field: {exc}") from None


def _read_pvd(path: Path) -> tuple:
    try:
        root = ET.parse(path).getroot()
        sets = root.find("Collection").findall("DataSet")
    except (ET.ParseError, AttributeError) as exc:
        raise EngineResultError(f"{path}: not a ParaView collection ({exc or 'no Collection'})") from None
    times, fields, points, tets = [], [], None, None
    for d in sets:
        m = _read_mesh_file(path.parent / d.get("file", ""))
        points = m.points if points is None else points
        if len(m.points) != len(points):
            raise EngineResultError(f"{path}: {d.get('file')} has {len(m.points)} points, the first {len(points)}")
        times.append(float(d.get("timestep", len(times))))
        fields.append(_field(path.parent / d.get("file"), m.point_data, len(m.points)))
        tets = _tets(m) if tets is None else tets
    if not sets:
        raise EngineResultError(f"{path}: the collection lists no data set")
    return points, np.array(times), np.array(fields), tets, None


def _read_xdmf(path: Path) -> tuple:
    import contextlib
    import io

    import meshio

    try:
        with contextlib.redirect_stdout(io.StringIO()), meshio.xdmf.TimeSeriesReader(str(path)) as reader:
            points, cells = reader.read_points_cells()
            times, fields = [], []
            for k in range(reader.num_steps):
                t, point_data, _ = reader.read_data(k)
                times.append(float(t))
                fields.append(_field(path, point_data, len(points)))
        tets = [c.data for c in cells if c.type == "tetra"]
        return points, np.array(times), np.array(fields), (np.concatenate(tets) if tets else None), None
    except EngineResultError:
        raise
    except (Exception, SystemExit):  # not a time series (meshio says so and exits): one field
        m = _read_mesh_file(path)
        return m.points, None, _field(path, m.point_data, len(m.points))[None], _tets(m), None


def _read_npz(path: Path) -> tuple:
    try:
        with np.load(path) as z:
            data = {k: z[k] for k in z.files}
    except (OSError, ValueError) as exc:
        raise EngineResultError(f"{path}: not a numpy .npz file ({exc})") from None
    if "displacement" not in data:
        raise EngineResultError(f"{path}: no 'displacement' array (arrays: {', '.join(data) or 'none'})")
    u = np.asarray(data["displacement"], dtype=float)
    u = u[None] if u.ndim == 2 else u
    times = data.get("times")
    return data.get("points"), times, u, data.get("tets"), data.get("reaction")


def read_result(path: str | Path, default_points: np.ndarray, scale: float = 1.0) -> EngineResult:
    """The result in ``path`` (see the module docstring), its lengths times ``scale`` (m per file unit).
    ``default_points`` (N, 3) m: the points of an .npz that gives none (the scene mesh's vertices)."""
    path = Path(path)
    if not path.is_file():
        raise EngineResultError(f"{path}: no such file")
    suffix = path.suffix.lower()
    if suffix == ".npz":
        points, times, u, tets, reaction = _read_npz(path)
    elif suffix == ".pvd":
        points, times, u, tets, reaction = _read_pvd(path)
    elif suffix in (".xdmf", ".xmf"):
        points, times, u, tets, reaction = _read_xdmf(path)
    elif suffix in (".vtu", ".vtk"):
        m = _read_mesh_file(path)
        points, times, u, tets, reaction = (
            m.points,
            None,
            _field(path, m.point_data, len(m.points))[None],
            _tets(m),
            None,
        )
    else:
        raise EngineResultError(f"{path}: unknown result format {suffix!r}: give .npz, .vtu, .vtk, .pvd or .xdmf")
    return _checked(path, points, times, u, tets, reaction, scale, default_points)


def _checked(path: Path, points, times, u, tets, reaction, scale: float, default_points) -> EngineResult:
    """Shapes and finiteness checked, lengths scaled to metres; no points: ``default_points`` (m), as
    they are (not scaled, so that they stay the scene's vertices exactly)."""
    given = points is not None
    points = np.asarray(points if given else default_points, dtype=float)
    if points.ndim != 2 or points.shape[1] != 3:
        raise EngineResultError(f"{path}: points must be (N, 3), got {points.shape}")
    n = len(points)
    if u.ndim != 3 or u.shape[1:] != (n, 3):
        raise EngineResultError(
            f"{path}: displacement must be ({n}, 3) or (T, {n}, 3) for its {n} points, got {u.shape}"
        )
    for name, a in (("points", points), ("displacement", u)):
        if not np.all(np.isfinite(a)):
            bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
            raise EngineResultError(f"{path}: {name}{list(bad)} is {a[bad]}, not a finite number")
    if times is not None:
        times = np.asarray(times, dtype=float).reshape(-1)
        if len(times) != len(u):
            raise EngineResultError(f"{path}: {len(times)} times for {len(u)} displacement fields")
    if reaction is not None:
        reaction = np.asarray(reaction, dtype=float).reshape(len(u), 3)
    if tets is not None:
        tets = np.asarray(tets, dtype=np.int64)
        if tets.ndim != 2 or tets.shape[1] != 4 or (len(tets) and (tets.min() < 0 or tets.max() >= n)):
            raise EngineResultError(f"{path}: tets must be (M, 4) indices of its {n} points")
    return EngineResult(str(path), points * scale if given else points, times, u * scale, tets, reaction)
