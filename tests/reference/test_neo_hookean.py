"""The compressible neo-Hookean law on the reference's side: its uniaxial stress-stretch curve from 30%
compression to 50% stretch against the closed form, and SOFA's liver under its own weight, which StVK
cannot hold and neo-Hookean can."""

import math

import numpy as np
import pytest
from scipy.optimize import brentq

from reference.errors import ReferenceSolveError
from verification.runs.reference import reference_result
from verification.scene_file import load_scene

E, NU = 1.0e4, 0.3
LAM, MU = E * NU / ((1 + NU) * (1 - 2 * NU)), E / (2 * (1 + NU))
SIDE = 0.01  # m


def uniaxial_stress(stretch: float) -> float:
    """The nominal stress P11 (Pa) of W = mu/2 (I1 - 3) - mu ln J + lam/2 (ln J)^2 under uniaxial stress:
    the lateral stretch s solves P22 = mu (s - 1/s) + lam ln(stretch s^2) / s = 0 (to round-off, by
    bisection on a bracket where P22 changes sign), then P11 = mu (stretch - 1/stretch) + lam ln J /
    stretch with J = stretch s^2."""

    def lateral(s):
        return MU * (s - 1 / s) + LAM * math.log(stretch * s * s) / s

    s = brentq(lateral, 0.2, 5.0, xtol=1e-15, rtol=4 * np.finfo(float).eps)
    return MU * (stretch - 1 / stretch) + LAM * math.log(stretch * s * s) / stretch


def bar_scene(tmp_path, stretch: float, law: str = "neo-hookean"):
    """A 1 cm cube on three rollers (x = 0, y = 0, z = 0 each held in their normal only), its face x = 1 cm
    moved along x to ``stretch`` times the side, free across: uniaxial stress, homogeneous, which P1 holds
    exactly."""
    eps = 1e-9
    text = f"""name = "nh-bar"
[mesh]
generator = "box"
size = [{SIDE}, {SIDE}, {SIDE}]
h = {SIDE / 2}
[material]
law = "{law}"
young = {E}
poisson = {NU}
density = 1000.0
[[fixed]]
box = [[-1, -1, -1], [{eps}, 1, 1]]
components = ["x"]
[[fixed]]
box = [[-1, -1, -1], [1, {eps}, 1]]
components = ["y"]
[[fixed]]
box = [[-1, -1, -1], [1, 1, {eps}]]
components = ["z"]
[[load]]
kind = "displacement"
box = [[{SIDE - eps}, -1, -1], [1, 1, 1]]
value = [{(stretch - 1) * SIDE!r}, 0.0, 0.0]
components = ["x"]
ramp = 0.2
[time]
mode = "static"
"""
    path = tmp_path / f"nh-bar-{law}-{stretch:g}.toml"
    path.write_text(text)
    return load_scene(path)


@pytest.mark.parametrize("stretch", [0.7, 0.85, 1.2, 1.5])
def test_the_reference_follows_the_uniaxial_stress_stretch_curve(tmp_path, stretch):
    """The tool's force on the moved face over the face's rest area is the nominal stress P11 of the closed
    form to 1e-8 (relative): a homogeneous state, which P1 represents exactly, solved by Newton to its
    tolerance; nothing but round-off and Newton's residual stands between them."""
    scene = bar_scene(tmp_path, stretch)
    ref = reference_result(scene, degree=1, refine=0, estimate=False)
    p11 = float(ref.reaction[-1][0]) / SIDE**2
    assert p11 == pytest.approx(uniaxial_stress(stretch), rel=1e-8)
    # the lateral faces are free: the body contracts (stretches) across as the closed form says
    s = brentq(lambda s: MU * (s - 1 / s) + LAM * math.log(stretch * s * s) / s, 0.2, 5.0, xtol=1e-15)
    far = np.isclose(scene.mesh.points[:, 1], SIDE)
    assert ref.displacement[-1][far, 1] == pytest.approx((s - 1) * SIDE, rel=1e-8)


def test_the_closed_form_is_linear_elasticity_at_small_stretch():
    """The law's constants by the experiment that defines them: the slope of the uniaxial curve at rest is
    the Young's modulus, and its lateral contraction the Poisson's ratio."""
    e = 1e-6
    assert uniaxial_stress(1 + e) / e == pytest.approx(E, rel=1e-5)
    s = brentq(lambda s: MU * (s - 1 / s) + LAM * math.log((1 + e) * s * s) / s, 0.2, 5.0, xtol=1e-15)
    assert -(s - 1) / e == pytest.approx(NU, rel=1e-4)


@pytest.mark.parametrize("law", ["neo-hookean", "stable-neo-hookean", "stable-neo-hookean-no-log"])
def test_each_neo_hookean_law_has_the_scenes_youngs_modulus_and_poissons_ratio(tmp_path, law):
    """The constants by the experiment that defines them, on the reference itself: the uniaxial bar at a
    stretch of 1e-5 has the nominal stress E times the strain and the lateral contraction nu times it, for
    each law whose constants are matched to the Lame constants at rest (Smith et al. 2018, section 3.4,
    for the stable ones). Tolerance 1e-4: the next order
    is the strain times a factor of a few, and Newton's residual 1e-10 of a load this small."""
    e = 1e-5
    scene = bar_scene(tmp_path, 1 + e, law)
    ref = reference_result(scene, degree=1, refine=0, estimate=False)
    assert float(ref.reaction[-1][0]) / SIDE**2 / e == pytest.approx(E, rel=1e-4)
    far = np.isclose(scene.mesh.points[:, 1], SIDE)
    assert -ref.displacement[-1][far, 1] / (e * SIDE) == pytest.approx(np.full(far.sum(), NU), rel=1e-4)


def hung_liver(tmp_path, law: str):
    """sofa-liver's body and hold (its mesh, material and back patch) under its own weight alone."""
    liver = load_scene("sofa-liver")
    text = f"""name = "hung-liver-{law}"
[mesh]
generator = "file"
file = "{liver.path.parent / "data" / "sofa-liver2.msh"}"
scale = 0.1
[material]
law = "{law}"
young = 28000.0
poisson = 0.4
density = 1000.0
[[fixed]]
sphere = {{ center = [-0.029, 0.053, -0.013], radius = 0.025 }}
[[load]]
kind = "gravity"
value = [0.0, 0.0, -9.81]
[time]
mode = "static"
"""
    path = tmp_path / f"hung-liver-{law}.toml"
    path.write_text(text)
    return load_scene(path)


@pytest.mark.slow
def test_sofas_liver_under_its_weight_holds_with_neo_hookean_where_stvk_inverts(tmp_path):
    """SOFA's liver hung from the 2.5 cm patch at its back under its own 11 N: StVK's Newton finds no
    equilibrium without inverted elements (StVK softens under compression: P1 stops at 0.90 of the weight,
    P2 at a third), neo-Hookean's does, with every element at J > 0 (its energy is infinite at J = 0). At
    P1 here, 0.1 s a solve; P2 holds the same (26 s, 8808 dofs, 8.5 cm at most), and its solve is the one
    that needs the factorisation analysed afresh after a failure (the test below)."""
    with pytest.raises(ReferenceSolveError, match="invert"):
        reference_result(hung_liver(tmp_path, "stvk"), degree=1, estimate=False)
    scene = hung_liver(tmp_path, "neo-hookean")
    nh = reference_result(scene, degree=1, estimate=False)
    u = nh.displacement[-1][: scene.mesh.n_vertices]
    x = scene.mesh.points[scene.mesh.tets]
    y = (scene.mesh.points + u)[scene.mesh.tets]
    J = np.linalg.det(y[:, 1:] - y[:, :1]) / np.linalg.det(x[:, 1:] - x[:, :1])
    assert J.min() > 0.0
    assert np.abs(u[:, 2]).max() > 0.01  # it hangs: centimetres, not a rigid body


def test_after_a_factorisation_of_nans_the_next_solve_analyses_afresh():
    """A Newton trial point where ln J has no value (the liver's P2 solve meets one: its tangent's
    quadrature samples points its residual's does not) leaves a tangent of NaNs; MUMPS's pivot order drawn
    from it was kept by PETSc for every later factorisation of the same pattern, which all failed (KSP
    reason -11, INFOG(1) = -9), so the liver's neo-Hookean solve stopped at a quarter of its weight. Here:
    the tangent factorised at a cube turned inside out, then a solve from rest, which converges only if
    that analysis is dropped (it fails with the reset taken out: tried)."""
    from meshes.generators import box
    from meshes.regions import TagRegion
    from realtime.material import Material
    from reference.fem import ElasticityProblem
    from reference.problem import Fixed, Gravity, Problem
    from reference.solver import chosen_options

    fixed, weight = (Fixed(TagRegion("zmin")),), (Gravity((0.0, 0.0, -9.81)),)
    material = Material(E, NU, 1000.0, law="neo-hookean")
    ep = ElasticityProblem(box((0.01, 0.01, 0.01), 0.005), material, Problem(fixed, weight), degree=1)
    solver = ep._newton(chosen_options(ep.n_dofs, None, comm=ep.comm)[0])
    x = ep.V.tabulate_dof_coordinates()
    ep.u.x.array[:] = (x * [0.0, 0.0, -2.0]).ravel()  # z -> -z: every element inverted
    solver._factorise()
    assert solver._newton_step() is not None  # the factorisation of NaNs fails
    ep.u.x.array[:] = 0.0
    assert solver.solve(1e-10, 10)["converged"]
