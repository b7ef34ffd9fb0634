"""meshes: generators, stored meshes and their hashes, I/O, validation, quality, regions."""

import json
import os
from pathlib import Path

import numpy as np
import pytest

from meshes import InvalidMeshError, TetMesh, generate, read_mesh, stored_mesh, structured_box, write_mesh
from meshes.regions import BoxRegion, SphereRegion, TagRegion
from meshes.store import MANIFEST, STORED, params_key


@pytest.mark.parametrize("name", ["beam", "cylinder", "tube", "liver"])
def test_generators_reproduce_the_stored_meshes(name):
    generator, params = STORED[name]
    entry = json.loads(MANIFEST.read_text())[params_key(generator, params)]
    assert generate(generator, **params).sha256() == entry["sha256"]
    assert stored_mesh(name).sha256() == entry["sha256"]


def test_liver_is_picinbono_sized():
    m = stored_mesh("liver")
    # Picinbono et al. 2003: 1394 vertices, 6342 tetrahedra
    assert 1200 <= m.n_vertices <= 1700 and 5500 <= m.n_tets <= 7000
    assert "surface" in m.vertex_tags


def test_generator_tags():
    assert {"xmin", "xmax", "ymin", "ymax", "zmin", "zmax"} <= set(stored_mesh("beam").vertex_tags)
    assert {"inner", "outer", "top", "bottom"} <= set(stored_mesh("tube").vertex_tags)
    beam = stored_mesh("beam")
    assert np.allclose(beam.points[beam.vertex_tags["xmax"], 0], 0.1)


@pytest.mark.parametrize("ext", ["msh", "vtu", "xdmf"])
def test_io_round_trip(tmp_path, ext):
    m = stored_mesh("beam")
    back = read_mesh(write_mesh(m, tmp_path / f"beam.{ext}"))
    assert np.array_equal(back.points, m.points) and np.array_equal(back.tets, m.tets)
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".tmp")]


@pytest.mark.parametrize(
    "name, fmt",
    [
        ("beam22.msh", "gmsh22"),
        ("beam41.msh", "gmsh"),
        ("beam.vtk", "vtk"),
        ("beam.vtu", "vtu"),
        ("beam.xdmf", "xdmf"),
        ("beam.mesh", "medit"),
    ],
)
def test_every_format_a_user_has_is_read(tmp_path, name, fmt):
    """gmsh 2.2 and 4.1, legacy VTK, VTU, XDMF (HDF5 data) and medit, as other tools write them."""
    import meshio

    m = stored_mesh("beam")
    meshio.write(tmp_path / name, meshio.Mesh(m.points, [("tetra", m.tets)]), file_format=fmt)
    back = read_mesh(tmp_path / name)
    assert np.allclose(back.points, m.points, rtol=0, atol=1e-15) and np.array_equal(back.tets, m.tets)
    assert back.notes == ()


def _gmsh_box(path: Path, version: float, groups: bool, save_all: bool, binary: bool) -> None:
    """A 10 x 2 x 2 cm box meshed and saved by gmsh itself, with the options its users set: the volume
    and the x = 0 face in physical groups ("tissue", "clamp") or none, Mesh.SaveAll, binary."""
    import gmsh

    gmsh.initialize(readConfigFiles=False)
    try:
        gmsh.option.setNumber("General.Terminal", 0)
        gmsh.model.occ.addBox(0, 0, 0, 0.1, 0.02, 0.02)
        gmsh.model.occ.synchronize()
        if groups:
            gmsh.model.setPhysicalName(3, gmsh.model.addPhysicalGroup(3, [1]), "tissue")
            gmsh.model.setPhysicalName(2, gmsh.model.addPhysicalGroup(2, [1]), "clamp")  # the face x = 0
        gmsh.option.setNumber("Mesh.MeshSizeMax", 0.01)
        gmsh.model.mesh.generate(3)
        gmsh.option.setNumber("Mesh.MshFileVersion", version)
        gmsh.option.setNumber("Mesh.SaveAll", int(save_all))
        gmsh.option.setNumber("Mesh.Binary", int(binary))
        gmsh.write(str(path))
    finally:
        gmsh.finalize()


@pytest.mark.parametrize("version", [2.2, 4.1])
@pytest.mark.parametrize(
    "groups, save_all, binary", [(False, False, False), (True, False, False), (True, True, False), (True, True, True)]
)
def test_files_gmsh_itself_writes_are_read_silently(tmp_path, capfd, version, groups, save_all, binary):
    """What gmsh writes, not meshio: with physical groups and Mesh.SaveAll = 1, gmsh 4.1 lists the
    untagged surfaces' elements too, which meshio refuses ("Incompatible cell data"), so gmsh reads
    those itself. Every variant gives the whole box, the named groups as tags (gmsh's group 0 is
    none), and prints nothing (meshio printed a blank line on stdout for every .msh, its ANSYS
    reader's empty error). gmsh 2.2 with SaveAll writes no element's group: a note says so."""
    _gmsh_box(tmp_path / "box.msh", version, groups, save_all, binary)
    m = read_mesh(tmp_path / "box.msh")
    assert capfd.readouterr() == ("", "")
    assert m.n_tets > 100 and np.isclose(m.volumes().sum(), 0.1 * 0.02 * 0.02, rtol=1e-12)
    lost = groups and save_all and version == 2.2  # gmsh writes every element's group as 0 then
    assert m.notes == (("the file names groups that tag no tetrahedron or triangle: clamp, tissue",) if lost else ())
    if groups and not lost:
        assert np.array_equal(m.cell_tags["tissue"], np.arange(m.n_tets))
        clamp = m.vertex_tags["clamp"]
        assert len(clamp) > 4 and np.all(m.points[clamp, 0] == 0.0)
        assert np.array_equal(clamp, np.flatnonzero(m.points[:, 0] == 0.0))
    else:
        assert m.cell_tags == {} and m.vertex_tags == {}


@pytest.mark.parametrize("folder", ["", "a-folder-name-long-enough-that-the-path-fills-more-than-one-80-column-line"])
def test_a_file_no_reader_takes_is_one_quiet_line(tmp_path, capfd, monkeypatch, folder):
    """meshio prints its readers' errors and calls sys.exit(1) for a .msh it cannot place: read_mesh
    says why in its one line and lets nothing else through; a gmsh file that both meshio and gmsh
    fail on names both reasons. meshio's printer (rich) folds its lines at the terminal's width, 80
    columns when there is none (CI): a path longer than that came back cut in two ("notes.ms h")."""
    monkeypatch.setenv("COLUMNS", "80")
    (tmp_path / folder).mkdir(exist_ok=True)
    path = tmp_path / folder / "notes.msh"
    path.write_text("hello\n")
    with pytest.raises(InvalidMeshError) as err:
        read_mesh(path)
    assert capfd.readouterr() == ("", "")
    assert str(err.value) == f"{path}: cannot read it as a mesh (Couldn't read file {path} as either of ansys, gmsh)"
    assert os.environ["COLUMNS"] == "80"  # the reader's own width does not leak
    (tmp_path / "cut.msh").write_text("$MeshFormat\n4.1 0 8\n$EndMeshFormat\n$Nodes\nbroken\n")
    with pytest.raises(InvalidMeshError, match=r"cut\.msh: cannot read it as a mesh \(meshio: .*; gmsh: Could not"):
        read_mesh(tmp_path / "cut.msh")
    assert capfd.readouterr() == ("", "")


def test_quadratic_tetrahedra_give_their_corners(tmp_path):
    """A second-order gmsh mesh: the linear mesh of its corners, said in a note."""
    import meshio

    m = structured_box([0.02, 0.01, 0.01], [2, 1, 1])
    edges = m.edges
    mid = {tuple(e): m.n_vertices + k for k, e in enumerate(edges)}
    pairs = [(0, 1), (1, 2), (0, 2), (0, 3), (2, 3), (1, 3)]  # gmsh's tetra10 order
    t10 = np.array([list(t) + [mid[tuple(sorted((t[a], t[b])))] for a, b in pairs] for t in m.tets])
    points = np.vstack([m.points, m.points[edges].mean(axis=1)])
    meshio.write(tmp_path / "q.msh", meshio.Mesh(points, [("tetra10", t10)]), file_format="gmsh22")
    back = read_mesh(tmp_path / "q.msh")
    assert np.array_equal(back.points, m.points) and np.array_equal(back.tets, m.tets)
    assert any("quadratic" in n for n in back.notes)


SOFA_LIVER = Path(__file__).parents[2] / "verification" / "scenes" / "data" / "sofa-liver2.msh"


def test_gmsh_format_1_real_mesh():
    """SOFA's liver2.msh ($NOD/$ELM), which meshio cannot read (it raised SystemExit)."""
    m = read_mesh(SOFA_LIVER)
    assert (m.n_vertices, m.n_tets) == (507, 1493)
    assert m.parts()[0] == 1 and m.notes == ()
    assert m.volumes().min() > 0
    scaled = read_mesh(SOFA_LIVER, scale=0.1)
    assert np.allclose(scaled.points, 0.1 * m.points, rtol=1e-15)
    assert scaled.quality()["total_volume_m3"] == pytest.approx(1e-3 * m.quality()["total_volume_m3"], rel=1e-12)


def _gmsh1(path, points, tets, labels=None):
    """Write a gmsh format 1 file (node labels arbitrary, as in SOFA's files)."""
    labels = np.arange(1, len(points) + 1) * 7 if labels is None else labels
    lines = ["$NOD", str(len(points))]
    lines += [f"{lab} {x!r} {y!r} {z!r}" for lab, (x, y, z) in zip(labels, points, strict=True)]
    lines += ["$ENDNOD", "$ELM", str(len(tets))]
    lines += [f"{i + 1} 4 1 1 4 " + " ".join(str(labels[v]) for v in t) for i, t in enumerate(tets)]
    lines += ["$ENDELM"]
    path.write_text("\n".join(lines) + "\n")
    return path


def test_what_real_files_contain_is_repaired_and_said(tmp_path):
    """Duplicate vertices, an unreferenced vertex, a duplicate tetrahedron and both orientations in one
    file: the repaired mesh is the clean one, and each repair is named."""
    clean = structured_box([0.02, 0.01, 0.01], [2, 1, 1])
    n = clean.n_vertices
    points = np.vstack([clean.points, clean.points[:3], [[5.0, 5.0, 5.0]]])  # 3 copies, 1 stray vertex
    tets = clean.tets.copy()
    tets[0] = [n, n + 1, n + 2, tets[0][3]] if set(tets[0][:3]) == {0, 1, 2} else tets[0]
    tets[1::2] = tets[1::2][:, [0, 1, 3, 2]]  # every other tetrahedron the other way round
    tets = np.vstack([tets, tets[4:5]])  # one twice
    m = read_mesh(_gmsh1(tmp_path / "messy.msh", points, tets))
    notes = " | ".join(m.notes)
    assert "duplicate tetrahedra" in notes and "turned" in notes and "both orientations" in notes
    assert "(tetrahedron 1, 3, 5...)" in notes  # every other one was written the other way round
    assert "no tetrahedron uses" in notes
    assert (m.n_vertices, m.n_tets) == (n, clean.n_tets)
    assert np.all(m.volumes() > 0) and m.quality()["total_volume_m3"] == pytest.approx(2e-6, rel=1e-12)


def test_coincident_vertices_are_merged(tmp_path):
    """Two halves of a box meshed apart, their shared face's vertices written twice: one body."""
    clean = structured_box([0.02, 0.01, 0.01], [2, 1, 1])
    right = clean.points[:, 0] > 0.015
    face = np.isclose(clean.points[:, 0], 0.01)
    copy = np.flatnonzero(face)
    points = np.vstack([clean.points, clean.points[copy]])
    remap = np.arange(clean.n_vertices)
    remap[copy] = clean.n_vertices + np.arange(len(copy))
    tets = clean.tets.copy()
    in_right = right[tets].any(axis=1)
    tets[in_right] = remap[tets[in_right]]
    m = read_mesh(_gmsh1(tmp_path / "halves.msh", points, tets))
    assert f"merged {len(copy)} duplicate vertices" in m.notes
    assert m.parts()[0] == 1 and m.n_vertices == clean.n_vertices


def test_disconnected_parts_are_counted_and_a_free_one_is_an_error(tmp_path):
    from verification.scene import SceneError
    from verification.scene_file import load_scene

    a = structured_box([0.01, 0.01, 0.01], 1)
    points = np.vstack([a.points, a.points + [0.05, 0.0, 0.0]])
    tets = np.vstack([a.tets, a.tets + a.n_vertices])
    mesh_file = _gmsh1(tmp_path / "two.msh", points, tets)
    m = read_mesh(mesh_file)
    assert m.parts()[0] == 2 and "2 disconnected parts" in m.notes
    (tmp_path / "two.toml").write_text(
        f'[mesh]\ngenerator = "file"\nfile = "{mesh_file.name}"\n'
        '[material]\nlaw = "linear"\nyoung = 1e4\npoisson = 0.3\ndensity = 1000.0\n'
        "[[fixed]]\nbox = [[-1e-9, -1, -1], [1e-9, 1, 1]]\n"
        '[[load]]\nkind = "gravity"\nvalue = [0, 0, -9.81]\n'
    )
    with pytest.raises(
        SceneError, match=r"two\.toml: mesh\.file: part 2 of the mesh's 2 disconnected parts \(8 vertices"
    ):
        _ = load_scene(tmp_path / "two.toml").mesh


def test_degenerate_tetrahedron_in_a_file_is_named_with_its_quality(tmp_path):
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1e-12]], float)
    with pytest.raises(InvalidMeshError, match=r"flat\.msh: tetrahedron 1 .* degenerate .* of a regular tetrahedron's"):
        read_mesh(_gmsh1(tmp_path / "flat.msh", pts, np.array([[0, 1, 2, 3], [0, 1, 2, 4]])))


@pytest.mark.parametrize(
    "text, needle",
    [
        ("$NOD\n2\n1 0 0 0\n", r"\$NOD announces 2 entries but the file ends"),
        ("$NOD\n1\n1 0 zero 0\n$ENDNOD\n$ELM\n0\n$ENDELM\n", r"line 3: cannot read"),
        (
            "$NOD\n1\n1 0 0 0\n$ENDNOD\n$ELM\n1\n1 4 1 1 4 1 2 3 4\n$ENDELM\n",
            r"a tetrahedron refers to node 2, which \$NOD",
        ),
        ("$NOD\n1\n1 0 0 0\n$ENDNOD\n", r"no \$ELM section"),
    ],
)
def test_broken_gmsh_format_1_files(tmp_path, text, needle):
    (tmp_path / "bad.msh").write_text(text)
    with pytest.raises(InvalidMeshError, match=r"bad\.msh: gmsh format 1: " + needle):
        read_mesh(tmp_path / "bad.msh")


def test_every_reader_exception_is_an_input_error(tmp_path, monkeypatch):
    """meshio raises SystemExit for some files, and many other types: each becomes one InvalidMeshError."""
    import meshio

    (tmp_path / "x.vtu").write_text("not xml at all")
    with pytest.raises(InvalidMeshError, match=r"x\.vtu: cannot read it as a mesh"):
        read_mesh(tmp_path / "x.vtu")

    def exits(*args, **kwargs):
        raise SystemExit("unknown file format")

    monkeypatch.setattr(meshio, "read", exits)
    with pytest.raises(InvalidMeshError, match=r"x\.vtu: cannot read it as a mesh \(unknown file format\)"):
        read_mesh(tmp_path / "x.vtu")


def test_non_tetrahedral_file_is_an_error(tmp_path):
    import meshio

    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0]], float)
    meshio.write(tmp_path / "tri.vtu", meshio.Mesh(pts, [("triangle", np.array([[0, 1, 2]]))]))
    with pytest.raises(InvalidMeshError, match=r"tri\.vtu.*not a linear tetrahedral mesh.*triangle"):
        read_mesh(tmp_path / "tri.vtu")


def test_inverted_element_is_named():
    m = structured_box([1, 1, 1], 2)
    tets = m.tets.copy()
    tets[7, [2, 3]] = tets[7, [3, 2]]
    with pytest.raises(InvalidMeshError, match=r"tetrahedron 7 .* inverted"):
        TetMesh(m.points, tets)


def test_degenerate_element_is_named():
    pts = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 1e-12], [0, 0, 1]], float)
    with pytest.raises(InvalidMeshError, match=r"tetrahedron 1 .* degenerate"):
        TetMesh(pts, np.array([[0, 1, 2, 4], [0, 1, 2, 3]]))


def test_uniformly_negative_file_is_reoriented():
    m = structured_box([1, 1, 1], 1)
    flipped = m.tets[:, [0, 1, 3, 2]]
    assert np.all(TetMesh.from_arrays(m.points, flipped).volumes() > 0)


def test_quality_of_structured_box():
    q = structured_box([1, 1, 1], 3).quality()
    assert q["total_volume_m3"] == pytest.approx(1.0, rel=1e-12)
    # Kuhn tetrahedra: dihedral angles 45, 60 and 90 degrees
    assert q["min_dihedral_deg"] == pytest.approx(45.0, abs=1e-9)
    assert q["max_dihedral_deg"] == pytest.approx(90.0, abs=1e-9)


def test_regions_agree_between_vertices_and_points():
    m = stored_mesh("beam")
    for region in (BoxRegion((-1e-9, -1, -1), (1e-9, 1, 1)), SphereRegion((0.1, 0.01, 0.02), 0.006), TagRegion("xmax")):
        idx = region.vertices(m)
        assert len(idx) > 0
        assert np.array_equal(np.flatnonzero(region.contains(m.points, m)), np.sort(idx))
    # a tag region also contains points on its faces that are not vertices (refined meshes, P2 nodes)
    face_mid = m.points[m.vertex_tags["xmax"][:2]].mean(axis=0)
    assert TagRegion("xmax").contains(face_mid[None], m)[0]
    assert not TagRegion("xmax").contains(np.array([[0.05, 0.01, 0.01]]), m)[0]


def test_a_cluster_of_coincident_vertices_becomes_one(tmp_path):
    """Twelve copies of one vertex, each used by another tetrahedron: one vertex."""
    m = structured_box([0.01, 0.01, 0.01], 1)
    centre = np.array([[0.005, 0.005, 0.005]])
    faces = m.boundary
    points = np.vstack([m.points, np.repeat(centre, len(faces), axis=0)])
    tets = np.hstack([faces, (m.n_vertices + np.arange(len(faces)))[:, None]])
    back = read_mesh(_gmsh1(tmp_path / "star.msh", points, tets))
    assert back.n_vertices == m.n_vertices + 1 and back.n_tets == len(faces)
    assert f"merged {len(faces) - 1} duplicate vertices" in back.notes
    assert back.quality()["total_volume_m3"] == pytest.approx(1e-6, rel=1e-12)


def test_written_files_have_the_usual_permissions(tmp_path):
    """Written through a temporary file, a result still gets the permissions of any new file (mkstemp's
    owner-only mode made the reports unreadable to a web server)."""
    import os

    from meshes.io import atomic_write

    umask = os.umask(0o022)
    try:
        path = atomic_write(tmp_path / "r.txt", lambda tmp: Path(tmp).write_text("x"))
    finally:
        os.umask(umask)
    assert path.stat().st_mode & 0o777 == 0o644


def test_atomic_savez_writes_the_name_given_and_atomic_write_says_why_it_cannot(tmp_path):
    """numpy's savez adds ".npz" to a name without it: atomic_savez writes exactly the path; a failing
    writer, a directory in the way or a full disk leave no temporary file behind."""
    from meshes.io import OutputPathError, atomic_savez, atomic_write

    for name in ("r.npz", "r.txt", "r"):
        atomic_savez(tmp_path / name, compressed=name == "r", a=np.arange(3))
        with np.load(tmp_path / name) as z:
            assert np.array_equal(z["a"], np.arange(3))
    (tmp_path / "d").mkdir()
    with pytest.raises(OutputPathError, match=r"/d: is a directory"):
        atomic_write(tmp_path / "d", lambda tmp: Path(tmp).write_text("x"))

    def full(tmp):
        Path(tmp).write_text("half")
        raise OSError(28, "No space left on device")

    with pytest.raises(OutputPathError, match=r"/e\.txt: cannot write it: No space left on device"):
        atomic_write(tmp_path / "e.txt", full)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["d", "r", "r.npz", "r.txt"]


def test_a_temporary_file_a_killed_writer_left_is_removed_by_the_next_write(tmp_path):
    """SIGKILL runs no ``finally``: the temporary file of a killed writer stays until the next write into
    that folder removes it. A live writer's file (this process's) and another host's are left alone."""
    import socket
    import subprocess
    import sys

    from meshes.io import _tmp_prefix, atomic_write

    dead = subprocess.run([sys.executable, "-c", "import os; print(os.getpid())"], capture_output=True, text=True)
    dead_pid = int(dead.stdout)  # exited and reaped: no process has this pid until the kernel reuses it
    killed = tmp_path / f"{_tmp_prefix(dead_pid)}abcd_123.json"
    live = tmp_path / f"{_tmp_prefix()}efgh_456.json"
    elsewhere = tmp_path / f".tmp-{socket.gethostname()}x-{dead_pid}-ijkl_789.json"
    for f in (killed, live, elsewhere):
        f.write_text('{"half')
    atomic_write(tmp_path / "r.json", lambda tmp: Path(tmp).write_text("{}"))
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted(["r.json", live.name, elsewhere.name])


def test_a_renumbered_mesh_is_the_same_mesh_numbered_along_the_body():
    """TetMesh.renumbered (and the stored name with "-renumbered") keeps every vertex, tetrahedron,
    orientation, tag and cell field, only renumbered: the tetrahedra in Morton order, the vertices in
    the order they first appear in them, grouped by the halves that hold them. So the vertices only
    the first half of the tetrahedra touch (a two-thread kernel's first thread) all come before those
    only the second half touches, which the mesh file's own numbering did not do."""
    from realtime.geometry import signed_volumes

    mesh = stored_mesh("liver")
    fields = {"stiffness": np.arange(mesh.n_tets, dtype=float)}
    mesh = TetMesh(mesh.points, mesh.tets, mesh.vertex_tags, {"half": np.arange(0, mesh.n_tets, 2)}, cell_fields=fields)
    new, vertex_order, tet_order = mesh.renumbered()
    assert sorted(vertex_order) == list(range(mesh.n_vertices)) and sorted(tet_order) == list(range(mesh.n_tets))
    assert np.array_equal(new.points, mesh.points[vertex_order])
    assert np.array_equal(new.points[new.tets], mesh.points[mesh.tets[tet_order]])  # the same corners in order
    assert np.array_equal(signed_volumes(new.points, new.tets), signed_volumes(mesh.points, mesh.tets)[tet_order])
    for name, verts in mesh.vertex_tags.items():
        assert np.array_equal(np.sort(vertex_order[new.vertex_tags[name]]), np.sort(verts))
    assert np.array_equal(np.sort(tet_order[new.cell_tags["half"]]), mesh.cell_tags["half"])
    assert np.array_equal(new.cell_fields["stiffness"], fields["stiffness"][tet_order])
    assert stored_mesh("liver-renumbered").sha256() == stored_mesh("liver").renumbered()[0].sha256()

    def split(m):
        """Vertices only the first half of the tetrahedra touch, and only the second half."""
        half = m.n_tets // 2
        a, b = np.unique(m.tets[:half]), np.unique(m.tets[half:])
        return np.setdiff1d(a, b), np.setdiff1d(b, a)

    first, second = split(new)
    assert first.max() < second.min()
    first, second = split(TetMesh(mesh.points, mesh.tets[tet_order]))  # the same order, the file's numbers
    assert first.max() > second.min()


def test_a_vtk_file_is_read_by_what_it_holds_not_by_its_suffix(tmp_path):
    """SOFA ships a tetrahedral UnstructuredGrid in VTK's XML format under a .vtk name (Bunny.vtk), which
    meshio's legacy reader refused ("Couldn't read file as vtk"); it is read as the .vtu it is. A legacy
    file holding a surface (SOFA's liver.vtk, POLYDATA) is named as one, with what to do."""
    import meshio

    box = structured_box([0.01, 0.01, 0.01], 2)
    meshio.write(tmp_path / "box.vtu", meshio.Mesh(box.points, [("tetra", box.tets)]))
    (tmp_path / "box.vtk").write_bytes((tmp_path / "box.vtu").read_bytes())
    m = read_mesh(tmp_path / "box.vtk")
    assert np.array_equal(m.points, box.points) and np.array_equal(m.tets, box.tets)
    (tmp_path / "surface.vtk").write_text(
        "# vtk DataFile Version 3.0\nsurface\nASCII\nDATASET POLYDATA\nPOINTS 3 float\n0 0 0 1 0 0 0 1 0\n"
        "POLYGONS 1 4\n3 0 1 2\n"
    )
    with pytest.raises(InvalidMeshError, match=r"surface\.vtk: a surface \(VTK POLYDATA\), not a volume mesh"):
        read_mesh(tmp_path / "surface.vtk")
