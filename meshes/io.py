"""Reading and writing tetrahedral meshes: gmsh format 1 by our own reader, the rest through meshio,
and the gmsh files meshio cannot read through gmsh itself."""

from __future__ import annotations

import contextlib
import io
import os
import re
import socket
import tempfile
import warnings
from pathlib import Path

import numpy as np
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from realtime.errors import InputError
from realtime.geometry import signed_volumes

from .tetmesh import InvalidMeshError, TetMesh

#: Vertices closer than this fraction of the bounding-box diagonal are one vertex: far above the
#: round-off of coordinates printed with 16 digits, far below any element a mesher makes.
DUPLICATE_TOL = 1e-10
#: gmsh element types of the legacy format 1 (and of 2.x) that are neither triangles nor tetrahedra.
_GMSH1_TYPES = {1: "line", 3: "quad", 5: "hexahedron", 6: "wedge", 7: "pyramid", 15: "vertex"}


class _Cells:
    """What a reader hands on: points (N, 3), tetrahedra (M, 4) as the file numbers them (0-based),
    surface triangles (F, 3) with their tags, tetrahedron tags, group names, other cell types, the
    tetrahedra's numeric cell data (fields), and the tag that means "in no group" (gmsh's 0) if the
    format has one."""

    def __init__(
        self, points, tets, tet_tags=None, tris=None, tri_tags=None, names=None, others=(), fields=None, no_group=None
    ):
        self.points = np.asarray(points, dtype=np.float64)
        self.tets = np.asarray(tets, dtype=np.int64).reshape(-1, 4)
        self.tet_tags = None if tet_tags is None else np.asarray(tet_tags, dtype=np.int64)
        self.tris = np.zeros((0, 3), np.int64) if tris is None else np.asarray(tris, dtype=np.int64).reshape(-1, 3)
        self.tri_tags = None if tri_tags is None else np.asarray(tri_tags, dtype=np.int64)
        self.names = names or {}
        self.others = sorted(set(others))
        self.fields = fields or {}  # name -> (M,) float64, a value per tetrahedron (the file's cell data)
        self.no_group = no_group


def _msh_header(path: Path) -> bytes | None:
    """The first non-blank line of a .msh file: b"$NOD" in gmsh's format 1, b"$MeshFormat" in 2 and 4
    (None for another suffix or an empty file)."""
    if path.suffix.lower() != ".msh":
        return None
    with open(path, "rb") as fh:
        for line in fh:
            if line.strip():
                return line.strip()
    return None


def _vtk_content(path: Path) -> str | None:
    """What a .vtk file holds, by its first bytes: "xml" for VTK's XML format under the legacy suffix
    (SOFA's Bunny.vtk is an UnstructuredGrid .vtu so named, which meshio's legacy reader refuses),
    "polydata" for a legacy file of a surface, None otherwise or for another suffix."""
    if path.suffix.lower() != ".vtk":
        return None
    with open(path, "rb") as fh:
        head = fh.read(1024)
    if head.lstrip().startswith((b"<VTKFile", b"<?xml")):
        return "xml"
    return "polydata" if b"DATASET POLYDATA" in head else None


def _cat(blocks: list, width: int) -> np.ndarray:
    """The int64 blocks (K_i, width) (or (K_i,) for width 0) one after the other; empty if none."""
    return np.concatenate(blocks) if blocks else np.zeros((0, width) if width else 0, np.int64)


def _gmsh1_section(lines, header: str, row, fail) -> None:
    """Read a gmsh 1 section from ``lines`` (an iterator of (line number, text)): find ``header``, read
    its count, then hand each entry's fields to ``row``; ``fail`` (a function of a message that raises)
    where the file says otherwise."""
    for _, line in lines:
        if line.strip() == header:
            break
    else:
        fail(f"no {header} section")
    lineno, count = next(lines, (0, ""))
    try:
        n = int(count.split()[0])
    except (ValueError, IndexError):
        fail(f"line {lineno}: expected the number of entries after {header}, got {count!r}")
    for _ in range(n):
        lineno, line = next(lines, (None, None))
        if line is None:
            fail(f"{header} announces {n} entries but the file ends")
        try:
            row(line.split())
        except (ValueError, IndexError):
            fail(f"line {lineno}: cannot read {line.strip()!r}")


def _read_gmsh1(path: Path) -> _Cells:
    """gmsh's legacy format 1 ($NOD/$ELM, SOFA's classic meshes), which meshio cannot read.

    $NOD: a count, then ``label x y z`` per node (labels arbitrary); $ELM: a count, then ``number type
    physical elementary n-nodes node-labels...`` per element.
    """

    def fail(msg):
        raise InvalidMeshError(f"{path}: gmsh format 1: {msg}")

    lines = iter(enumerate(path.read_text(errors="replace").splitlines(), start=1))
    labels, coords, tets, tet_tags, tris, tri_tags, others = [], [], [], [], [], [], []

    def node(parts):
        labels.append(int(parts[0]))
        coords.append([float(x) for x in parts[1:4]])

    def element(parts):
        kind, phys, n = int(parts[1]), int(parts[2]), int(parts[4])
        nodes = [int(x) for x in parts[5 : 5 + n]]
        if len(nodes) != n:
            raise ValueError
        if kind in (4, 11):  # a quadratic tetrahedron lists its four corners first
            tets.append(nodes[:4])
            tet_tags.append(phys)
            if kind == 11:
                others.append("tetra10")
        elif kind == 2:
            tris.append(nodes)
            tri_tags.append(phys)
        else:
            others.append(_GMSH1_TYPES.get(kind, f"gmsh type {kind}"))

    _gmsh1_section(lines, "$NOD", node, fail)
    _gmsh1_section(lines, "$ELM", element, fail)
    labels = np.asarray(labels, dtype=np.int64)
    if len(np.unique(labels)) != len(labels):
        fail("a node label appears twice")
    order = np.argsort(labels)
    sorted_labels = labels[order]

    def index(conn, what):
        conn = np.asarray(conn, dtype=np.int64)
        if conn.size == 0:
            return conn
        pos = np.clip(np.searchsorted(sorted_labels, conn), 0, len(labels) - 1)
        if np.any(sorted_labels[pos] != conn):
            bad = conn[sorted_labels[pos] != conn][0]
            fail(f"a {what} refers to node {bad}, which $NOD does not define")
        return order[pos]

    return _Cells(
        np.asarray(coords, dtype=np.float64).reshape(-1, 3),
        index(tets, "tetrahedron"),
        tet_tags,
        index(tris, "triangle"),
        tri_tags,
        others=others,
        no_group=0,
    )


#: Cell data that meshio reads as the groups of a file, not as fields.
TAG_DATA = ("gmsh:physical", "gmsh:geometrical", "medit:ref")


class _MeshioError(Exception):
    """meshio could not read a file: the reason, from its exception or from what it printed."""


@contextlib.contextmanager
def _unfolded():
    """meshio prints through rich, which folds lines at the terminal's width (COLUMNS; 80 without a
    terminal) and cuts a word longer than that, a file's path, in two: "notes.ms h". COLUMNS is set
    wider than any path while meshio reads, then restored (rich reads it when meshio makes its Console)."""
    before = os.environ.get("COLUMNS")
    os.environ["COLUMNS"] = "1000000"
    try:
        yield
    finally:
        if before is None:
            os.environ.pop("COLUMNS", None)
        else:
            os.environ["COLUMNS"] = before


def quiet_meshio_read(path: Path, file_format: str | None = None):
    """meshio.read, with what it prints (and warns) kept from the terminal: for a .msh it tries the
    ANSYS reader first and prints that reader's (empty) error on stdout, a blank line in the middle of
    ``tissuebench check``; for a file no reader takes it prints an "Error:" line and calls
    sys.exit(1). Raises _MeshioError with the most specific reason: its exception's message, else what
    its last "Error:" said."""
    import meshio

    chatter = io.StringIO()
    try:
        with (
            contextlib.redirect_stdout(chatter),
            contextlib.redirect_stderr(chatter),
            warnings.catch_warnings(),
            _unfolded(),
        ):
            warnings.simplefilter("ignore")  # numpy's, from meshio's parsing of a broken file
            return meshio.read(path, file_format=file_format)
    except (Exception, SystemExit) as exc:
        said = " ".join(chatter.getvalue().split())
        text = str(exc).strip() if not isinstance(exc, SystemExit) or "Error:" not in said else ""
        reason = text.splitlines()[0] if text else said.rsplit("Error:", 1)[-1].strip()
        raise _MeshioError(reason or type(exc).__name__) from None


def _read_meshio(path: Path, file_format: str | None = None) -> _Cells:
    m = quiet_meshio_read(path, file_format)
    tets, tet_tags, tris, tri_tags = [], [], [], []
    phys = m.cell_data.get("gmsh:physical") or m.cell_data.get("medit:ref")
    for i, cells in enumerate(m.cells):
        tags = np.asarray(phys[i]).ravel() if phys is not None else np.zeros(len(cells.data), np.int64)
        if cells.type in ("tetra", "tetra10"):  # a quadratic tetrahedron lists its four corners first
            tets.append(cells.data[:, :4])
            tet_tags.append(tags)
        elif cells.type == "triangle":
            tris.append(cells.data)
            tri_tags.append(tags)
    names = {int(pairs[0]): name for name, pairs in (getattr(m, "field_data", None) or {}).items()}
    fields = {}
    tet_blocks = [i for i, cells in enumerate(m.cells) if cells.type in ("tetra", "tetra10")]
    for name, per_block in m.cell_data.items():
        if name in TAG_DATA or not tet_blocks:
            continue
        values = [np.asarray(per_block[i]) for i in tet_blocks]
        # one number per tetrahedron (a column vector counts); vectors and tensors are not regions' stuff
        if all(v.dtype.kind in "biuf" and v.reshape(len(v), -1).shape[1] == 1 for v in values):
            fields[name] = np.concatenate([v.reshape(-1) for v in values]).astype(np.float64)
    points = np.asarray(m.points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] not in (2, 3):
        raise InvalidMeshError(f"{path}: points have shape {points.shape}, need (N, 3)")
    if points.shape[1] == 2:
        raise InvalidMeshError(f"{path}: points are 2-dimensional, need 3")
    return _Cells(
        points,
        _cat(tets, 4),
        _cat(tet_tags, 0) if phys is not None else None,
        _cat(tris, 3),
        _cat(tri_tags, 0) if phys is not None else None,
        names,
        [c.type for c in m.cells if c.type not in ("tetra", "triangle")],
        fields,
        0 if "gmsh:physical" in m.cell_data else None,
    )


#: gmsh's element type numbers, by the names meshio gives them (the names read_mesh's errors use).
_GMSH_TYPES = {2: "triangle", 4: "tetra", 11: "tetra10", 8: "line3", 9: "triangle6", **_GMSH1_TYPES}


def _read_by_gmsh(path: Path) -> _Cells:
    """A gmsh file of format 2 or 4 read by gmsh itself (python3-gmsh), for the files gmsh writes that
    meshio cannot read: saved with Mesh.SaveAll = 1 beside physical groups, gmsh 4.1 lists the
    elements of untagged entities too, and meshio stops at its "Incompatible cell data
    'gmsh:physical'". Tetrahedra (the corners of quadratic ones) of every volume, with the first
    physical tag of their volume (0 for a volume in none), and the triangles of tagged surfaces with
    theirs; group names; the other element types, by meshio's names. Element data ($ElementData) is
    not read here."""
    import gmsh

    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.open(str(path))
        node_tags, coords, _ = gmsh.model.mesh.getNodes()
        if len(node_tags) == 0:
            raise ValueError("no nodes")
        index = np.full(int(node_tags.max()) + 1, -1, dtype=np.int64)
        index[node_tags.astype(np.int64)] = np.arange(len(node_tags))
        tagged = bool(gmsh.model.getPhysicalGroups())
        blocks = {2: ([], []), 3: ([], [])}
        for dim, keep in ((3, (4, 11)), (2, (2,))):
            for _, entity in gmsh.model.getEntities(dim):
                groups = gmsh.model.getPhysicalGroupsForEntity(dim, entity)
                if dim == 2 and len(groups) == 0:
                    continue  # an untagged surface's triangles name no vertices
                types, _, nodes = gmsh.model.mesh.getElements(dim, entity)
                for etype, conn in zip(types, nodes, strict=True):
                    if etype in keep:
                        per = gmsh.model.mesh.getElementProperties(etype)[3]
                        conn = index[conn.astype(np.int64).reshape(-1, per)[:, : dim + 1]]
                        blocks[dim][0].append(conn)
                        blocks[dim][1].append(np.full(len(conn), int(groups[0]) if len(groups) else 0))
        names = {int(tag): gmsh.model.getPhysicalName(dim, tag) for dim, tag in gmsh.model.getPhysicalGroups()}
        others = [
            _GMSH_TYPES.get(int(t), gmsh.model.mesh.getElementProperties(t)[0])
            for t in gmsh.model.mesh.getElementTypes()
            if t not in (2, 4)
        ]
        points = coords.reshape(-1, 3)
    finally:
        gmsh.finalize()
    (tets, tet_tags), (tris, tri_tags) = blocks[3], blocks[2]
    return _Cells(
        points,
        _cat(tets, 4),
        _cat(tet_tags, 0) if tagged else None,
        _cat(tris, 3),
        _cat(tri_tags, 0) if tagged else None,
        {k: v for k, v in names.items() if v},
        others,
        no_group=0,
    )


def _read_cells(path: Path) -> _Cells:
    """The file's raw cells by the reader its format needs: ours for gmsh format 1, meshio for the rest,
    and gmsh itself for the gmsh files meshio fails on. InvalidMeshError if none can read it."""
    header = _msh_header(path)
    if header == b"$NOD":
        return _read_gmsh1(path)
    vtk = _vtk_content(path)
    if vtk == "polydata":
        raise InvalidMeshError(
            f"{path}: a surface (VTK POLYDATA), not a volume mesh: tetrahedralise it first (gmsh, TetGen, fTetWild)"
        )
    try:
        return _read_meshio(path, "vtu" if vtk == "xml" else None)
    except InvalidMeshError:
        raise
    except (Exception, SystemExit) as exc:  # meshio raises many types, SystemExit among them
        reason = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
    if header == b"$MeshFormat":
        try:
            return _read_by_gmsh(path)
        except Exception as exc:
            why = str(exc).strip().splitlines()[0] if str(exc).strip() else type(exc).__name__
            reason = f"meshio: {reason}; gmsh: {why}"
    raise InvalidMeshError(f"{path}: cannot read it as a mesh ({reason})")


def _quadratic_note(cells: _Cells) -> list[str]:
    """The note for a file of quadratic tetrahedra, whose corners make the linear mesh."""
    quadratic = "tetra10" in cells.others
    return ["used the corner vertices of the quadratic tetrahedra (midside nodes dropped)"] if quadratic else []


def read_mesh(path: str | os.PathLike, scale: float = 1.0) -> TetMesh:
    """Read a linear tetrahedral mesh: gmsh .msh (format 1, 2.2 and 4.x), .vtu/.vtk, .xdmf, medit .mesh
    and what else meshio reads. Coordinates are multiplied by ``scale`` (0.001 for a file in mm).

    What real files contain is repaired and said in ``mesh.notes``: duplicate vertices merged,
    unreferenced vertices dropped, duplicate tetrahedra dropped, tetrahedra of the other orientation
    turned, several disconnected parts counted (``mesh.parts()``). What cannot be repaired is an
    InvalidMeshError naming the file and the element: a degenerate tetrahedron (with its quality
    figures), no tetrahedra (naming the cell types there are), a syntax error (with its line).
    gmsh physical groups become tags: of tetrahedra (cell tags) and of the vertices of tagged triangles
    (vertex tags). The tetrahedra's other numeric cell data, one number each, become cell fields
    (``mesh.cell_fields``), through the same repairs.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such mesh file")
    if not (isinstance(scale, (int, float)) and np.isfinite(scale) and scale > 0):
        raise InvalidMeshError(f"{path}: scale = {scale!r} must be a positive number")
    cells = _read_cells(path)
    if len(cells.tets) == 0:
        raise InvalidMeshError(
            f"{path}: not a linear tetrahedral mesh (cell types: {cells.others or ['none']}"
            + (", triangle" if len(cells.tris) else "")
            + ")"
        )
    return _clean(path, cells, float(scale))


def _merge_duplicates(points: np.ndarray, tets: np.ndarray, notes: list) -> np.ndarray:
    """Each vertex's representative (N,) int64: the lowest index of its cluster of coincident points
    (within DUPLICATE_TOL of the used vertices' diagonal), itself where it has none; a note when any
    merge."""
    used = np.unique(tets)
    diag = float(np.linalg.norm(np.ptp(points[used], axis=0))) or 1.0
    pairs = cKDTree(points[used]).query_pairs(DUPLICATE_TOL * diag, output_type="ndarray")
    n = len(points)
    if not len(pairs):
        return np.arange(n)
    # clusters of coincident points are the connected components of the coincidence pairs
    graph = coo_matrix((np.ones(len(pairs)), (used[pairs[:, 0]], used[pairs[:, 1]])), shape=(n, n))
    _, label = connected_components(graph, directed=False)
    lowest = np.full(label.max() + 1, n, dtype=np.int64)
    np.minimum.at(lowest, label, np.arange(n))
    rep = lowest[label]
    notes.append(f"merged {int(np.sum(rep != np.arange(n)))} duplicate vertices")
    return rep


def _groups(c: _Cells, tet_tags, tris: np.ndarray, compact: np.ndarray) -> tuple[dict, dict]:
    """The file's groups by name: vertex groups from its tagged triangles, cell groups from its tagged
    tetrahedra (``compact`` maps file vertices to the kept ones, -1 for dropped)."""
    vertex_tags, cell_tags = {}, {}
    if tet_tags is not None:
        for t in np.unique(tet_tags[tet_tags != c.no_group]):
            cell_tags[c.names.get(int(t), str(int(t)))] = np.flatnonzero(tet_tags == t).astype(np.int64)
    if c.tri_tags is not None and len(tris):
        for t in np.unique(c.tri_tags[c.tri_tags != c.no_group]):
            v = compact[np.unique(tris[c.tri_tags == t])]
            vertex_tags[c.names.get(int(t), str(int(t)))] = np.unique(v[v >= 0]).astype(np.int64)
    return vertex_tags, cell_tags


def _clean(path: Path, c: _Cells, scale: float) -> TetMesh:
    """Repairs of a file's raw arrays (see read_mesh), each said in a note."""
    notes = _quadratic_note(c)
    points = c.points * scale
    if not np.all(np.isfinite(points)):
        bad = int(np.argwhere(~np.isfinite(points))[0, 0])
        raise InvalidMeshError(f"{path}: vertex {bad} has a non-finite coordinate {c.points[bad].tolist()}")
    tets, tris = c.tets, c.tris
    if tets.min() < 0 or tets.max() >= len(points):
        bad = int(np.argwhere((tets < 0) | (tets >= len(points)))[0, 0])
        raise InvalidMeshError(f"{path}: tetrahedron {bad} {tets[bad].tolist()} refers to a missing vertex")
    rep = _merge_duplicates(points, tets, notes)
    if np.any(rep != np.arange(len(points))):
        tets, tris = rep[tets], rep[tris] if len(tris) else tris
    # duplicate tetrahedra (the same four vertices twice)
    keys = np.sort(tets, axis=1)
    _, first = np.unique(keys, axis=0, return_index=True)
    tet_tags, fields = c.tet_tags, c.fields
    if len(first) < len(tets):
        keep = np.sort(first)
        notes.append(f"dropped {len(tets) - len(keep)} duplicate tetrahedra")
        tets = tets[keep]
        tet_tags = None if tet_tags is None else tet_tags[keep]
        fields = {name: v[keep] for name, v in fields.items()}
    for name, v in fields.items():
        if not np.all(np.isfinite(v)):
            bad = int(np.flatnonzero(~np.isfinite(v))[0])
            raise InvalidMeshError(f"{path}: cell field {name!r} is {v[bad]} at tetrahedron {bad}")
    # unreferenced vertices
    used = np.unique(tets)
    if len(used) < len(points):
        dropped = len(points) - len(used) - int(np.sum(rep != np.arange(len(points))))
        if dropped > 0:
            notes.append(f"dropped {dropped} vertices that no tetrahedron uses")
    compact = np.full(len(points), -1, dtype=np.int64)
    compact[used] = np.arange(len(used))
    points, tets = points[used], compact[tets]
    # orientation: each tetrahedron turned positive on its own (a rest mesh has no inverted elements,
    # only a vertex order); degenerate ones are left for check_tets to name
    vol = signed_volumes(points, tets)
    negative = vol < 0.0
    if negative.any():
        tets = tets.copy()
        tets[negative] = tets[negative][:, [0, 1, 3, 2]]
        mixed = "" if negative.all() else f" of {len(tets)} (the file mixes both orientations)"
        first = ", ".join(str(int(i)) for i in np.flatnonzero(negative)[:3])
        notes.append(f"turned {int(negative.sum())} tetrahedra{mixed} to positive orientation (tetrahedron {first}...)")
    vertex_tags, cell_tags = _groups(c, tet_tags, tris, compact)
    unused = sorted(set(c.names.values()) - set(cell_tags) - set(vertex_tags))
    if unused:
        # gmsh 2.2 saved with Mesh.SaveAll = 1 keeps $PhysicalNames but writes every element's tag as 0
        notes.append(f"the file names groups that tag no tetrahedron or triangle: {', '.join(unused)}")
    mesh = TetMesh(
        points,
        tets,
        source=str(path),
        vertex_tags=vertex_tags,
        cell_tags=cell_tags,
        notes=tuple(notes),
        cell_fields=fields,
    )
    n_parts, _ = mesh.parts()
    if n_parts > 1:
        object.__setattr__(mesh, "notes", mesh.notes + (f"{n_parts} disconnected parts",))
    return mesh


class OutputPathError(InputError):
    """A file the suite was asked to write cannot be written there (a directory of that name, a parent
    that is a file, no permission, a full disk); ``str()`` names the path and why."""


def _tmp_prefix(pid: int | None = None) -> str:
    """A temporary file's name says which host and process write it: ``.tmp-HOST-PID-RANDOM.SUFFIX``."""
    return f".tmp-{socket.gethostname()}-{os.getpid() if pid is None else pid}-"


def _process_is_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # alive, another user's
        return True
    return True


def remove_orphaned_temporaries(folder: str | os.PathLike) -> list[Path]:
    """Remove the temporary files in ``folder`` that a process of this host left when it was killed
    (SIGKILL, an out-of-memory kill, a power cut: no ``finally`` runs), and return them. A file whose
    writer still runs, or was written on another host sharing the folder, is left alone."""
    removed = []
    ours = f".tmp-{socket.gethostname()}-"
    for tmp in Path(folder).glob(ours + "*"):
        # PID-RANDOM.SUFFIX, where mkstemp's RANDOM is 8 of [a-z0-9_] (a host "ci-2" is not host "ci")
        pid, _, rest = tmp.name[len(ours) :].partition("-")
        if not (pid.isdigit() and re.fullmatch(r"[a-z0-9_]{8}(\..*)?", rest)) or _process_is_alive(int(pid)):
            continue
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
            removed.append(tmp)
    return removed


def atomic_write(path: str | os.PathLike, write) -> Path:
    """Call ``write(tmp)`` with a temporary path beside ``path`` (same suffix), then rename it to
    ``path``: a reader never sees a half-written file, and a failure leaves none behind. ``write`` must
    write exactly ``tmp`` (numpy's savez adds ".npz" to a name without it: use ``atomic_savez``).
    What a killed writer left in the folder is removed first (``remove_orphaned_temporaries``).
    Raises OutputPathError if the file cannot be written there."""
    path = Path(path)
    if path.is_dir():
        raise OutputPathError(f"{path}: is a directory: give the name of a file to write")
    for parent in path.parents:  # nearest first: the first that exists must be a directory
        if parent.exists():
            if not parent.is_dir():
                raise OutputPathError(f"{path}: cannot write it: {parent} is a file, not a directory")
            break
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_orphaned_temporaries(path.parent)
        fd, tmp = tempfile.mkstemp(suffix=path.suffix, dir=path.parent, prefix=_tmp_prefix())
    except OSError as exc:
        raise OutputPathError(f"{path}: cannot write it: {exc.strerror or exc}") from None
    os.close(fd)
    try:
        write(tmp)
        # mkstemp makes the file readable by its owner only; the result gets the permissions any new
        # file gets (a report served by a web server, a result a colleague reads)
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, path)
    except OSError as exc:  # a full disk, a quota, a target turned into a directory meanwhile
        raise OutputPathError(f"{path}: cannot write it: {exc.strerror or exc}") from None
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return path


def atomic_write_text(path: str | os.PathLike, text: str) -> Path:
    """Write ``text`` to ``path`` whole (``atomic_write``)."""
    return atomic_write(path, lambda tmp: Path(tmp).write_text(text))


def atomic_savez(path: str | os.PathLike, compressed: bool = False, **arrays) -> Path:
    """numpy's savez (or savez_compressed) of ``arrays`` to exactly ``path``, through atomic_write (given
    a name, numpy writes NAME.npz when NAME lacks the suffix: the data went to the temporary file's
    twin, left behind, and ``path`` got the empty temporary file)."""
    save = np.savez_compressed if compressed else np.savez

    def write(tmp):
        with open(tmp, "wb") as fh:
            save(fh, **arrays)

    return atomic_write(path, write)


def write_mesh(mesh: TetMesh, path: str | os.PathLike, point_data: dict | None = None) -> Path:
    """Write a mesh (and optional point fields, each (N,) or (N, 3)) atomically: temp file, rename.

    Vertex tags are stored as 0/1 point fields ``tag:NAME`` so that ParaView shows them.
    """
    import meshio

    data = {f"tag:{k}": np.isin(np.arange(mesh.n_vertices), v).astype(np.int32) for k, v in mesh.vertex_tags.items()}
    data.update(point_data or {})
    m = meshio.Mesh(mesh.points, [("tetra", mesh.tets)], point_data=data)
    suffix = Path(path).suffix

    def write(tmp):
        if suffix == ".msh":
            meshio.write(tmp, m, file_format="gmsh22", binary=False)
        elif suffix == ".xdmf":  # inline XML: one self-contained file survives the rename
            meshio.xdmf.write(tmp, m, data_format="XML")
        else:
            meshio.write(tmp, m)

    return atomic_write(path, write)
