"""A rigid tool pressed on the body (reference.contact): the truth's gap is the problem's, Hertz's closed
form holds for a sphere pressing a large block with the truth's bar shown beside it, and a tool a
scene cannot use is one line."""

from __future__ import annotations

import json
import sys

import numpy as np
import pytest
import ufl
from dolfinx import fem
from dolfinx import mesh as dmesh
from mpi4py import MPI
from petsc4py import PETSc

from meshes.generators import box
from meshes.regions import TagRegion
from realtime import DivergenceError
from realtime.material import Material
from reference.contact import gap
from reference.fem import ElasticityProblem
from reference.problem import Fixed, Problem, RigidTool
from tests.verification.test_input_errors import assert_one_line, run
from verification.scene_file import load_scene

TOOLS = {
    "sphere": RigidTool("sphere", (0.3, 0.2, 0.9), radius=0.25, travel=(0.1, -0.2, -0.3)),
    "capsule": RigidTool("capsule", (0.1, 0.5, 0.8), radius=0.15, end=(0.9, 0.4, 0.7), travel=(0.0, 0.1, -0.2)),
    "plane": RigidTool(
        "plane", (0.0, 0.0, 0.7), normal=tuple(np.array([0.2, 0.1, -1.0]) / np.linalg.norm([0.2, 0.1, -1.0]))
    ),
}


@pytest.mark.parametrize("shape", sorted(TOOLS))
def test_the_truths_gap_is_the_problems_gap(shape):
    """reference.contact.gap (UFL) against RigidTool.gap (numpy), at the quadrature points of a unit cube's
    cells, the tool moved 0.6 of its travel; both are the same closed form, so round-off (1e-13 of the
    cube's side) separates them. The capsule's points lie before, along and beyond its segment."""
    tool = TOOLS[shape]
    domain = dmesh.create_unit_cube(MPI.COMM_SELF, 3, 3, 3)
    offset = fem.Constant(domain, PETSc.ScalarType(tuple(tool.offset(0.6))))
    x = ufl.SpatialCoordinate(domain)
    points = np.array([[0.1, 0.2, 0.3], [0.25, 0.25, 0.25], [0.6, 0.1, 0.2], [0.3, 0.6, 0.05]])
    cells = np.arange(domain.topology.index_map(3).size_local, dtype=np.int32)
    g = fem.Expression(gap(tool, x, offset), points).eval(cells).ravel()
    y = fem.Expression(x, points).eval(cells).reshape(-1, 3)
    np.testing.assert_allclose(g, tool.gap(y, 0.6), rtol=0, atol=1e-13)
    assert (g < 0).any() and (g > 0).any()  # the tool's surface crosses the cube: both sides are tested


R, E, NU = 0.005, 5.0e3, 0.45  # m, Pa: a 5 mm tool tip on soft tissue
L = 40 * R  # the block's side: its finite size shifts the force by about 0.4 % of Hertz's (L = 20 R: 0.8 %)


def press(h: float) -> dict:
    """A rigid sphere of radius R pressed 0.05 R into a quarter of a block (side L, symmetry planes x = 0
    and y = 0, base held), the mesh graded to edges h under the tool, the force read at five stations of
    the travel (d/R = 0.01 to 0.05): the truth's forces (5,) N and contact areas (5,) m^2 on the whole
    block, and the penalty's relative error measured at the end."""
    mesh = box((L, L, L), L / 4, fine={"point": (0.0, 0.0, L), "h": h, "radius": 0.25 * R})
    fixed = (Fixed(TagRegion("xmin"), ("x",)), Fixed(TagRegion("ymin"), ("y",)), Fixed(TagRegion("zmin")))
    tool = RigidTool("sphere", (0.0, 0.0, L + R), radius=R, travel=(0.0, 0.0, -0.05 * R), stations=5)
    material = Material(law="linear", young=E, poisson=NU, density=1000.0)
    info = ElasticityProblem(mesh, material, Problem(fixed, (), (tool,)), degree=2).solve()
    curve = info["contact_curve"]
    return {
        "depth": np.array([0.05 * R * c["fraction"] for c in curve]),
        "force": np.array([-4.0 * c["force"][0][2] for c in curve]),
        "area": np.array([4.0 * c["area"][0] for c in curve]),  # the first penalty's (verification.runs.reference)
        "penalty": info["penalty_error"]["force"][0] / abs(info["contact"][-1]["force"][0][2]),
    }


@pytest.mark.slow
def test_a_sphere_pressing_a_block_follows_hertz_within_the_truths_bar():
    """Hertz: a rigid sphere pressed d into an elastic half-space takes F = 4/3 E/(1 - nu^2) sqrt(R) d^1.5
    over a contact radius sqrt(R d). The truth is P2 on a graded block at edges of 0.08 R and 0.04 R under
    the tool, its force read at d/R = 0.01, 0.02 ... 0.05 along one travel; its bar on a force is the
    difference between the two meshes plus the penalty's error. Asked: the fitted exponent within 0.03 of
    1.5 and the prefactor (F / d^1.5 fitted with Hertz's exponent) within 3 % of Hertz's, both counting
    the bar; measured: 1.500 +- 0.008 and +0.5 % +- 1.1 %. Two effects Hertz leaves out are smaller than that: the exact sphere (Sneddon) takes 0.1 to
    0.5 % less force than Hertz's paraboloid, the finite block about 0.4 % more. (At nu = 0.3, the
    frictionless sphere's radial push on the surface adds 0.17 a / R through the 1 - 2 nu coupling, which
    Hertz's first-order theory drops: 3.7 % at d/R = 0.05; nu = 0.45 is tissue's and keeps it under 1 %.)
    The contact area, printed, is 0.93 to 0.95 of pi R d from d/R = 0.02 (the exact sphere's: 0.98 to
    0.99); it converges slowly, as the penetrated region's edge is where the pressure falls to zero."""
    coarse, fine = press(0.08 * R), press(0.04 * R)
    depths, force = fine["depth"], fine["force"]
    bar = np.abs(force - coarse["force"]) + fine["penalty"] * force
    hertz = 4.0 / 3.0 * E / (1.0 - NU**2) * np.sqrt(R) * depths**1.5
    print("d/R, F/Hertz, bar/Hertz, area/(pi R d):")
    for d, f, b, h, a in zip(depths, force, bar, hertz, fine["area"], strict=True):
        print(f"  {d / R:.4f} {f / h:.4f} {b / h:.1e} {a / (np.pi * R * d):.3f}")
    exponent = np.polyfit(np.log(depths), np.log(force), 1)[0]
    # the exponent's bar: the fit's slope moved by the bars at the two ends, the worst way
    spread = np.log((force[-1] + bar[-1]) / (force[0] - bar[0])) - np.log((force[-1] - bar[-1]) / (force[0] + bar[0]))
    spread /= np.log(depths[-1] / depths[0])
    prefactor = np.sum(force * depths**1.5) / np.sum(depths**3)  # least squares of F = C d^1.5
    hertz_prefactor = 4.0 / 3.0 * E / (1.0 - NU**2) * np.sqrt(R)
    prefactor_bar = np.max(bar / hertz)
    print(
        f"exponent {exponent:.4f} +- {spread / 2:.4f}; prefactor / Hertz's {prefactor / hertz_prefactor:.4f} +- {prefactor_bar:.4f}"
    )
    assert abs(exponent - 1.5) + spread / 2 <= 0.03
    assert abs(prefactor / hertz_prefactor - 1.0) + prefactor_bar <= 0.03
    assert fine["penalty"] < 1e-3  # the penalty is not what the bar is made of


BLOCK = """name = "press"
[mesh]
generator = "box"
size = [0.04, 0.04, 0.02]
h = 0.01
[material]
law = "linear"
young = 5.0e3
poisson = 0.45
density = 1000.0
[[fixed]]
tag = "zmin"
[[tool]]
"""


@pytest.mark.parametrize(
    "tool, needles",
    [
        ('shape = "sphere"\ncenter = [0.02, 0.02, 0.021]\nradius = 0.005', ("tool[0]", "starts inside", "m inside it")),
        (
            'shape = "sphere"\ncenter = [0.02, 0.02, 0.01]\nradius = 0.001',
            ("tool[0]", "its center", "lies in the body"),
        ),
        (
            'shape = "sphere"\ncenter = [0.02, 0.02, 0.03]\nradius = 0.005\ntravel = [0.0, 0.0, -0.004]',
            ("tool[0]", "never touches", "0.001"),
        ),
        (
            'shape = "capsule"\ncenter = [0.0, 0.0, 0.03]\nend = [0.0, 0.0, 0.03]\nradius = 0.005',
            ("tool[0].end", "length 0"),
        ),
        ('shape = "cone"\ncenter = [0.0, 0.0, 0.03]', ("tool[0].shape", "cone", "sphere")),
        ('shape = "plane"\ncenter = [0.0, 0.0, 0.03]\nnormal = [0.0, 0.0, 0.0]', ("tool[0].normal", "non-zero")),
        (
            'shape = "sphere"\ncenter = [0.02, 0.02, 0.025]\nradius = 0.005\ntravel = [0.0, 0.0, -0.001]\n'
            '[time]\nmode = "dynamic"\nend = 0.1\noutput_every = 0.01',
            ("tool", "static scene", "a dynamic scene"),
        ),
    ],
    ids=[
        "surface-inside",
        "center-inside",
        "never-touches",
        "zero-length-capsule",
        "unknown-shape",
        "zero-normal",
        "dynamic",
    ],
)
def test_a_tool_the_scene_cannot_use_is_one_line_and_exit_2(tmp_path, capsys, tool, needles):
    path = tmp_path / "press.toml"
    path.write_text(BLOCK + tool + "\n")
    code, _, err = run(["check", str(path)], capsys)
    assert code == 2
    assert_one_line(err, str(path), *needles)


def test_a_python_plug_in_on_a_contact_scene_is_refused_in_one_line(tmp_path, capsys):
    """The export carries a rigid tool to the adapters and to a command engine (``rigid_tools``); a Python
    plug-in's Simulation has no call for its force yet, so a command naming one is refused by name, before
    any truth is solved, not run without its tool."""
    path = tmp_path / "press.toml"
    path.write_text(
        BLOCK + 'shape = "sphere"\ncenter = [0.02, 0.02, 0.025]\nradius = 0.005\ntravel = [0.0, 0.0, -0.001]\n'
    )
    plug_in = "tests.verification.test_engine_seam:DirectP1"
    code, _, err = run(["compare", str(path), "--model", "direct-p1", "--engine", plug_in], capsys)
    assert code == 2
    assert_one_line(err, str(path), "tool", plug_in, "is not given a rigid tool")


def test_the_reference_command_states_each_tools_force_and_area_with_their_bars(tmp_path, capsys):
    """tissuebench reference on a contact scene: the tool's force (it pushes the block down) and contact
    area, each with its bar from the two levels and the penalty, and the force at four stations of the
    travel, growing; on this coarse P1 block the bars are large, and they are stated, not zero."""
    path = tmp_path / "press.toml"
    path.write_text(
        BLOCK
        + 'shape = "sphere"\ncenter = [0.02, 0.02, 0.025]\nradius = 0.005\ntravel = [0.0, 0.0, -0.001]\nstations = 4\n'
    )
    code, out, err = run(["reference", str(path), "--degree", "1", "--json"], capsys)
    assert code == 0, err
    (row,) = __import__("json").loads(out)["contact"]
    # the force-indentation curve: a point at each quarter of the travel, the last the answer's own
    curve = row["curve"]
    assert [c["fraction"] for c in curve] == [0.25, 0.5, 0.75, 1.0]
    pushes = [-c["force"][2] for c in curve]
    assert all(b > a > 0.0 for a, b in zip(pushes, pushes[1:], strict=False)) and all(c["force_bar"] > 0 for c in curve)
    # pressed down; sideways a little, as this coarse mesh under a tool its own size is not symmetric (11 %)
    assert row["force"][2] < 0.0 and abs(row["force"][2]) > 5 * np.abs(row["force"][:2]).max()
    assert 0.0 < row["area"] and row["force_bar"] > 0.0 and row["area_bar"] > 0.0


def test_a_fine_region_too_fine_to_mesh_is_one_line_before_gmsh_runs(tmp_path, capsys):
    """[mesh] fine with edges of a micrometre would ask gmsh for about 1e11 tetrahedra: refused by the
    estimate, naming the key, before any meshing (the same limit as a box's own h)."""
    path = tmp_path / "press.toml"
    text = BLOCK.replace("h = 0.01\n", "h = 0.01\nfine = { point = [0.02, 0.02, 0.02], h = 1e-6, radius = 0.002 }\n")
    path.write_text(
        text + 'shape = "sphere"\ncenter = [0.02, 0.02, 0.025]\nradius = 0.005\ntravel = [0.0, 0.0, -0.001]\n'
    )
    code, _, err = run(["check", str(path)], capsys)
    assert code == 2
    assert_one_line(err, str(path), "mesh.fine", "tetrahedra (the limit is")


#: A plane 0.1 mm above the block pressed 0.4 mm into it, the truth read at four stations: the scene of the
#: two tests below (the second finds the first's truth in the cache).
PLANE = 'shape = "plane"\ncenter = [0.0, 0.0, 0.0201]\nnormal = [0.0, 0.0, -1.0]\ntravel = [0.0, 0.0, -0.0005]\nstations = 4\n'


def test_compare_judges_a_built_in_models_contact_force_and_area_against_the_truths(tmp_path, capsys):
    """tissuebench compare on a contact scene: the built-in model's rigid tool pushes the block as the
    truth's does, its tool force is judged (reaction_rel_err, a number with the truth's bar, 0.085
    measured: P1 on 1 cm cells against the refined truth) and so is its contact area: the plane presses the
    whole top, 0.0016 m^2, on both sides (measured 6e-5 apart: the truth's Gauss points against the
    engine's interpolated gaps)."""
    path = tmp_path / "press.toml"
    path.write_text(BLOCK + PLANE)
    code, out, err = run(["compare", str(path), "--model", "linear-tm", "--degree", "1", "--json"], capsys)
    assert code == 0, err
    row = __import__("json").loads(out)
    assert 0.0 < row["reaction_rel_err"] < 0.2 and 0.0 < row["rel_l2"] < 0.2, row
    (area,) = row["contact"]
    assert area["area"] == pytest.approx(0.04 * 0.04, rel=1e-3) and area["ref_area"] == pytest.approx(0.0016, rel=1e-3)
    assert area["area_rel_err"] == pytest.approx(abs(area["area"] / area["ref_area"] - 1.0))


def test_the_reports_contact_curve_puts_each_model_beside_the_truths_stations(tmp_path):
    """The report's force along the travel (verification.report.contact): a plane 0.1 mm above the block
    pressed 0.4 mm into it. The truth's four stations (P1 and its refinement, for speed) with their bars,
    rising; linear-tm settled at each station, rising with it, 8.8 % above it at each (P1 on the scene's
    coarse mesh against the truth's refined level: the bound is 15 %) and by the same factor at every
    station to 1e-4 (once the plane touches the whole top, the problem is linear: the ratio measured equal
    to eight digits); the plot drawn. A model with no curve is named with why: a row that diverged, and
    an engine whose station runs state no tool force (newton's XPBD) or fail (one that diverges there)."""
    from verification.report import contact
    from verification.report.contact import contact_html
    from verification.runs.reference import reference_result
    from verification.runs.row import Row
    from verification.scene_file import load_scene

    path = tmp_path / "press.toml"
    path.write_text(BLOCK + PLANE)
    scene = load_scene(path)
    ref = reference_result(scene, degree=1)
    area = {"tool": 0, "area": 4.2e-4, "ref_area": 4e-4, "area_rel_err": 0.05, "ref_area_bar": 0.01}
    row = Row("press", "linear-tm", "symplectic-euler", "ok", dt=1e-4, fraction=0.9, contact=(area,))
    blown = Row("press", "stvk-tm", "symplectic-euler", "diverged", dt=1e-3, fraction=4.0)
    text, data = contact_html(scene, ref, [row, blown])
    assert "data:image/png;base64," in text and data["travel_m"] == pytest.approx([1.25e-4, 2.5e-4, 3.75e-4, 5e-4])
    assert data["not_drawn"] == {"stvk-tm": "diverged"} and "stvk-tm (diverged)" in text
    assert "<td>linear-tm</td><td>0.00042</td><td>0.05</td>" in text  # the row's area beside the truth's
    truth, engine = np.array(data["reference"]), np.array(data["models"]["linear-tm"])
    assert np.all(np.diff(truth) > 0) and np.all(np.diff(engine) > 0) and all(b > 0 for b in data["reference_bar"])
    ratio = engine / truth
    assert np.all(np.abs(ratio - 1.0) < 0.15) and np.ptp(ratio) < 1e-4 * ratio.mean(), ratio

    def silent(*args, **kwargs):  # an engine that states no tool force: NaN
        res = run_model(*args, **kwargs)
        res.reaction[:] = np.nan
        return res

    def failing(*args, **kwargs):
        raise DivergenceError("newton-xpbd", 7, 1e-3, 2e-4, "xpbd")

    run_model = contact.run_model
    for stub, why in (
        (silent, "its engine states no tool force"),
        (failing, "at 0.25 of the travel: newton-xpbd with xpbd diverged"),
    ):
        contact.run_model = stub
        try:
            _, data = contact_html(scene, ref, [row])
        finally:
            contact.run_model = run_model
        assert data["models"] == {} and data["not_drawn"]["linear-tm"].startswith(why), data["not_drawn"]


def test_a_runs_contact_area_is_its_equilibriums(tmp_path):
    """A settled run's contact area (the row's, from the result's meta) is the one of the displacement it
    returns, read with it before any timed step, and well below the rest shape's overlap with the tool at
    the end of its travel (what a run that did not move would report)."""
    from verification.engines.builtin import scene_model
    from verification.runs.simulate import run_model
    from verification.scene_file import load_scene

    path = tmp_path / "press.toml"
    path.write_text(
        BLOCK + 'shape = "sphere"\ncenter = [0.02, 0.02, 0.025]\nradius = 0.005\ntravel = [0.0, 0.0, -0.002]\n'
    )
    scene = load_scene(path)
    res = run_model(scene, "linear-tm")
    model = scene_model(scene, "linear-tm")
    (area,) = res.meta["contact_area"]
    assert area == pytest.approx(model.rigid_areas(res.displacement[-1])[0], rel=1e-9)
    assert area < 0.5 * model.rigid_areas(np.zeros_like(res.displacement[-1]))[0]


def test_a_command_engine_on_a_contact_scene_states_each_rigid_tools_force(tmp_path, capsys):
    """The export carries the rigid tool to a command engine (scene.json ``rigid_tools``); its result must
    state the tool's force (``rigid_force``, (K, 3) N), the sign that it met the tool. A command that
    answers without it, as one that never read the tool would, is one line and exit 2; with it, the answer
    is judged (here a body left where it was: every error 1)."""
    path = tmp_path / "press.toml"
    path.write_text(BLOCK + PLANE)
    n = len(load_scene(path).mesh.points)
    write = "import numpy as n, sys; n.savez(sys.argv[1], displacement=n.zeros(({n}, 3)){extra})"
    args = ["compare", str(path), "--degree", "1", "--json", "--model", "still"]
    silent = f"{sys.executable} -c '{write.format(n=n, extra='')}' {{result}}"
    code, _, err = run([*args, "--engine-cmd", silent], capsys)
    assert code == 2
    assert_one_line(err, "rigid tool", "states no rigid_force", "(1, 3) N")
    stated = f"{sys.executable} -c '{write.format(n=n, extra=', rigid_force=n.zeros((1, 3))')}' {{result}}"
    code, out, err = run([*args, "--engine-cmd", stated], capsys)
    assert code == 0, err
    row = json.loads(out)
    assert row["rel_l2"] == pytest.approx(1.0) and row["reaction_rel_err"] is None


def test_a_law_whose_rest_stress_is_round_off_solves_before_its_tool_touches(tmp_path, capsys):
    """The stable neo-Hookean's rest stress cancels to round-off only (k_mu - k_mu/4 + k_lam (1 - alpha)).
    Before a rigid tool touches, nothing else loads the body: every force scale of Newton's test is that
    round-off, which rtol times it never reaches, and the reference failed at every load down to 6e-5 of
    the travel (the liver under a sphere, newton's own law). The residual's round-off floor
    (reference.solver.roundoff_floor) accepts it there; the pressed block then solves like the others. Its
    eight load steps keep the tool off the block for the first two (it starts 0.5 mm above, travels 2 mm)."""
    path = tmp_path / "press.toml"
    sphere = 'shape = "sphere"\ncenter = [0.02, 0.02, 0.0255]\nradius = 0.005\ntravel = [0.0, 0.0, -0.002]\n'
    path.write_text(BLOCK.replace('law = "linear"', 'law = "stable-neo-hookean"') + sphere)
    code, out, err = run(["reference", str(path), "--degree", "1", "--no-estimate", "--load-steps", "8"], capsys)
    assert code == 0, err
    assert "tool[0]: force" in out
