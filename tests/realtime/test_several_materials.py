"""Several materials in one body (issue 12): the engine's per-tetrahedron materials.

A body's elastic energy, force, stiffness and masses are sums over its tetrahedra, so a model of two
materials must equal, term by term, the sum of two one-material models, each built on its own
tetrahedra. That is the test of every model here; it checks the per-block coefficients of the element
kernels, the per-tetrahedron tensors of tensor-mass and the springs' calibration without trusting any of
their formulas. The closed-form check (layers in series) is in tests/verification/test_scene_files.py's layered slab.
"""

import numpy as np
import pytest

from meshes import stored_mesh
from realtime import Material, MaterialError, Materials, build_model
from realtime.models.linear_tm import cut

from ..conftest import assert_same_model

HOST = Material(3.0e3, 0.45, 1000.0, law="stvk")
#: 100 times stiffer than HOST, another Poisson's ratio and density, fibres around an axis and the
#: volume penalty: every coefficient differs between the two parts.
STIFF = Material(
    3.0e5,
    0.3,
    1300.0,
    law="stvk",
    fiber_axis=(0.1, 0.2, 1.0),
    fiber_point=(1e-3, 2e-3, 0.0),
    young_fiber=6e5,
    fiber_shear=2e4,
    volume_penalty=1e5,
)
STIFF_ISO = Material(3.0e5, 0.3, 1300.0, law="stvk")

#: Two sums of the same terms in another order differ by round-off: a few hundred ulps of the largest
#: term, which the stiff part's force sets.
ROUND_OFF = 1e-12


def two_parts():
    """The cylinder with the tetrahedra whose centroid has z above the middle given material 1."""
    mesh = stored_mesh("cylinder")
    z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    index = (z > np.median(z)).astype(np.int64)
    return mesh, index


CASES = [
    ("linear-tm", STIFF, {}),
    ("stvk-tm", STIFF, {}),
    ("corotational-tm", STIFF_ISO, {}),
    ("hybrid-tm", STIFF, {"threshold": 2e-3}),  # u below has both sides of the threshold
    ("mass-spring", STIFF, {}),
]


@pytest.mark.parametrize("name, stiff, options", CASES, ids=[c[0] for c in CASES])
def test_two_materials_are_the_sum_of_two_bodies(name, stiff, options, rng):
    mesh, index = two_parts()
    both = build_model(name, mesh.points, mesh.tets, Materials((HOST, stiff), index), **options)
    parts = [build_model(name, mesh.points, mesh.tets[index == k], m, **options) for k, m in enumerate((HOST, stiff))]
    u = 1e-3 * rng.standard_normal(mesh.points.shape)  # 10% of the edge length: the non-linear terms count
    f = both.internal_force(u)
    f_sum = sum(p.internal_force(u) for p in parts)
    scale = np.abs(f_sum).max()
    assert np.abs(f - f_sum).max() <= ROUND_OFF * scale
    # the stiff part's force dominates: a model that gave every tetrahedron one material fails by far
    assert np.abs(parts[1].internal_force(u)).max() > 10 * np.abs(parts[0].internal_force(u)).max()
    energy = both.elastic_energy(u)
    assert energy == pytest.approx(sum(p.elastic_energy(u) for p in parts), rel=ROUND_OFF)
    np.testing.assert_allclose(both.mass, sum(p.mass for p in parts), rtol=ROUND_OFF)
    K = both.rest_stiffness()
    K_sum = sum(p.rest_stiffness() for p in parts)
    assert abs(K - K_sum).max() <= ROUND_OFF * abs(K_sum).max()
    # the element bound is a max over elements: the stiffer part's
    bound = both.element_eigenvalue_bound()
    assert bound == pytest.approx(max(p.element_eigenvalue_bound() for p in parts), rel=ROUND_OFF)


@pytest.mark.parametrize("name", ["linear-tm", "stvk-tm", "mass-spring"])
def test_one_material_twice_is_one_material(name, rng):
    mesh, index = two_parts()
    one = build_model(name, mesh.points, mesh.tets, HOST)
    twice = build_model(name, mesh.points, mesh.tets, Materials((HOST, HOST), index))
    assert_same_model(twice, one, rng, ROUND_OFF)


def test_cutting_a_body_of_two_materials_equals_rebuilding_it(rng):
    mesh, index = two_parts()
    materials = Materials((HOST, STIFF), index)
    model = build_model("linear-tm", mesh.points, mesh.tets, materials)
    removed = np.flatnonzero(
        np.linalg.norm(mesh.points[mesh.tets].mean(axis=1) - mesh.points.mean(axis=0), axis=1) < 4e-3
    )
    assert 0 < len(removed) < len(mesh.tets) // 4
    after = cut(model, removed)
    keep = np.setdiff1d(np.arange(len(mesh.tets)), removed)
    rebuilt = build_model("linear-tm", mesh.points, mesh.tets[keep], materials.subset(keep), after.loading)
    assert_same_model(after, rebuilt, rng, ROUND_OFF)
    assert np.array_equal(after.materials.index, index[keep])


def test_bad_materials_are_one_line_errors():
    mesh, index = two_parts()
    with pytest.raises(MaterialError, match=r"materials.index\[\d+\] = 2: tetrahedron \d+ names no material"):
        Materials((HOST, STIFF), np.where(index == 1, 2, 0))
    with pytest.raises(MaterialError, match=f"materials.index: {len(index) - 1} entries for a mesh of {len(index)}"):
        build_model("stvk-tm", mesh.points, mesh.tets, Materials((HOST, STIFF), index[1:]))
    with pytest.raises(MaterialError, match="non-empty sequence of Material"):
        Materials((), index)
    with pytest.raises(Exception, match="isotropic materials only"):
        build_model("corotational-tm", mesh.points, mesh.tets, Materials((HOST, STIFF), index))


# ---- scenes of several materials: the [[material]] tables, the reference, the closed form ----

TWO = """
name = "two"
[mesh]
generator = "grid"
size = [0.02, 0.01, 0.01]
h = 0.005
[[material]]
all = true
law = "linear"
young = 5.0e3
poisson = 0.45
density = 1000.0
[[material]]
box = [[0.01, -1.0, -1.0], [1.0, 1.0, 1.0]]
law = "linear"
young = 5.0e5
poisson = 0.3
density = 1200.0
[[fixed]]
box = [[-1e-9, -1.0, -1.0], [1e-9, 1.0, 1.0]]
[[load]]
kind = "gravity"
value = [0.0, 0.0, -9.81]
"""


def p_wave_modulus(young, poisson):
    """lambda + 2 mu, the stress over the strain in uniaxial strain: written here from Hooke's law in
    uniaxial strain (eps_xx = eps_yy = 0), not taken from realtime.material."""
    return young * (1.0 - poisson) / ((1.0 + poisson) * (1.0 - 2.0 * poisson))


def layered_closed_form(scene):
    """u (N, 3) of the layered slab: u_z(z) = -p int_0^z dz' / M(z'), u_x = u_y = 0 (layers in series in
    uniaxial strain; the side walls are rollers and the floor holds z)."""
    from meshes.regions import BoxRegion

    p = -scene.problem.loads[0].value[2]
    layers = []  # (z from, z to, M) from the scene's own tables
    for region, m in scene.zones:
        lo, hi = (0.0, 0.03) if not isinstance(region, BoxRegion) else (max(region.lo[2], 0.0), min(region.hi[2], 0.03))
        layers.append((lo, hi, p_wave_modulus(m.young, m.poisson)))
    breaks = sorted({b for lo, hi, _ in layers for b in (lo, hi)})

    def modulus(z):  # the last table that holds z wins, as for the tetrahedra
        return [m for lo, hi, m in layers if lo <= z <= hi][-1]

    u = np.zeros_like(scene.mesh.points)
    for i, z in enumerate(scene.mesh.points[:, 2]):
        cuts = [0.0] + [b for b in breaks if 0.0 < b < z] + [z]
        # 1/M is constant between breaks: the integral is an exact sum
        u[i, 2] = -p * sum((b - a) / modulus(0.5 * (a + b)) for a, b in zip(cuts[:-1], cuts[1:], strict=True))
    return u


def test_layered_slab_is_exact_in_the_p1_reference_and_the_settled_linear_tensor_mass():
    from realtime import solve_static
    from verification.engines.builtin import scene_model
    from verification.runs.reference import reference_result
    from verification.scene_file import load_scene

    scene = load_scene("layered-slab")
    exact = layered_closed_form(scene)
    # the closed form is piecewise linear in z with kinks on grid planes: P1 holds it exactly
    scale = np.abs(exact).max()
    assert scale > 0.0 and len(set(np.round(exact[:, 2] / scale, 6))) > 5
    ref = reference_result(scene, degree=1, refine=0, estimate=False)
    # a direct LDL^T solve of a 525-dof system: round-off, amplified by a condition number near 1e3
    assert np.abs(ref.displacement[-1] - exact).max() <= 1e-12 * scale
    settled = solve_static(scene_model(scene, "linear-tm"), rtol=1e-12)
    # dynamic relaxation stops at a residual of 1e-12 of the load; the error follows by the same factor
    assert np.abs(settled.state.u - exact).max() <= 1e-10 * scale
    # and the slab tells the layers apart: one material everywhere is far off
    one = load_scene("layered-slab").with_material()
    one.zones = None
    wrong = solve_static(scene_model(one, "linear-tm"), rtol=1e-8)
    assert np.abs(wrong.state.u - exact).max() > 0.5 * scale


def test_p1_reference_and_linear_tensor_mass_solve_one_system_around_an_inclusion():
    """A sphere 100 times stiffer inside an unstructured gmsh block: the reference tags its cells by the
    scene tetrahedron holding their midpoints, the engine takes the tetrahedra's materials; on the scene's
    mesh both solve one linear system."""
    from realtime import solve_static
    from verification.engines.builtin import scene_model
    from verification.runs.reference import reference_result
    from verification.scene_file import load_scene

    scene = load_scene("stiff-inclusion").with_material(law="linear")
    assert len(np.unique(scene.body_material().index)) == 2
    ref = reference_result(scene, degree=1, refine=0, estimate=False)
    model = scene_model(scene, "linear-tm")
    settled = solve_static(model, rtol=1e-12)
    d = ref.displacement[-1]
    # dynamic relaxation to 1e-12 of the load against a direct solve: 1e-9 allows the condition number
    assert np.linalg.norm(settled.state.u - d) <= 1e-9 * np.linalg.norm(d)
    np.testing.assert_allclose(model.reaction(settled.state.u), ref.reaction[-1], rtol=1e-8, atol=1e-12)


def test_a_refined_scene_keeps_each_tetrahedron_s_material():
    from meshes.regions import locate
    from verification.scene_file import load_scene

    scene = load_scene("stiff-inclusion")
    fine = scene.refined(1)
    parent = locate(scene.mesh, fine.mesh.points[fine.mesh.tets].mean(axis=1))
    assert np.all(parent >= 0)
    assert np.array_equal(fine.body_material().index, scene.body_material().index[parent])
    assert fine.densities().sum() > 0 and len(fine.densities()) == fine.mesh.n_tets


def _scene_file(tmp_path, text):
    path = tmp_path / "scene.toml"
    path.write_text(text)
    return path


BAD_TABLES = [
    ("all = true\n", "box = [[0.005, -1.0, -1.0], [1.0, 1.0, 1.0]]\n", r"material: 24 tetrahedra have no material"),
    ("box = [[0.01,", "box = [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]\nxbox = [[0.01,", r"unknown key"),
    ('law = "linear"\nyoung = 5.0e5', 'law = "stvk"\nyoung = 5.0e5', r"material\[1\].law: 'stvk' differs"),
    ("poisson = 0.3", "poisson = 0.5", r"material\[1\].poisson"),
    ("all = true\n", 'tag = "xmin"\n', r"material\[0\].tag: 'xmin' is not a volume group"),
    (
        "box = [[0.01, -1.0, -1.0], [1.0, 1.0, 1.0]]",
        "box = [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]",
        r"holds no tetrahedron",
    ),
]


@pytest.mark.parametrize("old, new, message", BAD_TABLES, ids=[b[2][:30] for b in BAD_TABLES])
def test_bad_material_tables_are_one_line_errors(tmp_path, capsys, old, new, message):
    from verification.cli import main
    from verification.scene import SceneError
    from verification.scene_file import load_scene

    assert old in TWO
    path = _scene_file(tmp_path, TWO.replace(old, new, 1))
    with pytest.raises(SceneError, match=message):
        load_scene(path).mesh  # noqa: B018  (tables are checked against the mesh)
    assert main(["check", str(path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err


def test_two_material_scene_runs_and_reports_its_tables(tmp_path, capsys):
    from verification.cli import main

    path = _scene_file(tmp_path, TWO)
    assert main(["check", str(path), "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert [z["tets"] for z in out["materials"]] == [48, 48]
    assert [z["young_pa"] for z in out["materials"]] == [5.0e3, 5.0e5]


def test_a_material_drawn_from_a_cell_field_of_the_mesh_file(tmp_path, capsys):
    """[[material]] field = { name, min, max }: the tetrahedra whose value of a cell field of the mesh
    file (here a VTU's "zone", 1 where the box region of TWO lies) is in range. It gives TWO's
    materials tetrahedron for tetrahedron, through the reader's repairs (a duplicate tetrahedron, with
    its own value, dropped) and a refinement; a field the mesh lacks names the ones it has."""
    import meshio

    from meshes.generators import grid
    from verification.cli import main
    from verification.scene import SceneError
    from verification.scene_file import load_scene

    mesh = grid((0.02, 0.01, 0.01), 0.005)
    zone = (mesh.points[mesh.tets].mean(axis=1)[:, 0] > 0.01).astype(float)
    tets = np.concatenate([mesh.tets, mesh.tets[:1]])  # a duplicate, which the reader drops
    meshio.write(
        tmp_path / "two.vtu", meshio.Mesh(mesh.points, [("tetra", tets)], cell_data={"zone": [np.append(zone, 0.0)]})
    )
    mesh_table = '[mesh]\ngenerator = "grid"\nsize = [0.02, 0.01, 0.01]\nh = 0.005\n'
    text = TWO.replace(mesh_table, '[mesh]\ngenerator = "file"\nfile = "two.vtu"\n').replace(
        "box = [[0.01, -1.0, -1.0], [1.0, 1.0, 1.0]]", 'field = { name = "zone", min = 0.5, max = 1.5 }'
    )
    assert text.count("field =") == 1 and "two.vtu" in text
    from_field = load_scene(_scene_file(tmp_path, text))
    (tmp_path / "box").mkdir()
    from_box = load_scene(_scene_file(tmp_path / "box", TWO))
    assert np.array_equal(from_field.mesh.tets, from_box.mesh.tets)
    assert "dropped 1 duplicate tetrahedra" in " ".join(from_field.mesh.notes)
    assert np.array_equal(from_field.body_material().index, from_box.body_material().index)
    assert np.array_equal(from_field.refined(1).body_material().index, from_box.refined(1).body_material().index)
    assert from_field.mesh.sha256() != from_box.mesh.sha256()  # the field is part of what the mesh is
    assert main(["check", str(tmp_path / "scene.toml"), "--json"]) == 0
    import json

    out = json.loads(capsys.readouterr().out)
    assert [z["tets"] for z in out["materials"]] == [48, 48]
    assert "field" in out["materials"][1]["region"]
    for bad, message in (
        ('name = "zone"', r"material\[1\]\.field\.name: 'zones' is not a cell field of the mesh \(its fields: zone\)"),
        ("min = 0.5", r"material\[1\]\.field\.min: 2\.0 exceeds max 1\.5"),
    ):
        wrong = text.replace(bad, 'name = "zones"' if "name" in bad else "min = 2.0")
        with pytest.raises(SceneError, match=message):
            load_scene(_scene_file(tmp_path, wrong)).mesh  # noqa: B018


def test_a_mesh_file_whose_tags_alone_change_is_not_served_its_old_reference(tmp_path):
    """A material drawn by a volume group: the same vertices and tetrahedra with the groups drawn
    elsewhere are another body. The mesh's hash is its geometry (the manifest and the gates record
    it) and stays; the scene's hash, which keys every cached reference, holds the tags and changes."""
    import meshio

    from meshes import structured_box
    from verification.runs.reference import reference_key
    from verification.scene_file import load_scene

    box = structured_box((0.02, 0.01, 0.01), (4, 2, 2))
    x = box.points[box.tets].mean(axis=1)[:, 0]
    path = tmp_path / "two.msh"

    def write(cut):
        group = np.where(x < cut, 1, 2)
        meshio.write(
            path,
            meshio.Mesh(
                box.points,
                [("tetra", box.tets)],
                cell_data={"gmsh:physical": [group], "gmsh:geometrical": [group]},
                field_data={"soft": np.array([1, 3]), "stiff": np.array([2, 3])},
            ),
            file_format="gmsh22",
            binary=False,
        )

    scene_text = TWO.replace(
        'generator = "grid"\nsize = [0.02, 0.01, 0.01]\nh = 0.005', f'generator = "file"\nfile = "{path}"'
    )
    scene_text = scene_text.replace("box = [[0.01, -1.0, -1.0], [1.0, 1.0, 1.0]]", 'tag = "stiff"')
    toml = _scene_file(tmp_path, scene_text)
    write(0.01)
    before = load_scene(toml)
    key = reference_key(before, 2, 0, True)
    write(0.015)
    after = load_scene(toml)
    assert after.mesh.sha256() == before.mesh.sha256()
    assert not np.array_equal(after.body_material().index, before.body_material().index)
    assert after.sha256() != before.sha256() and reference_key(after, 2, 0, True) != key
