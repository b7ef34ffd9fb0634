"""meshes: generators, stored meshes and their hashes, I/O, validation, quality, regions."""

import json

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
