"""The reference proves itself: manufactured solutions, analytic states, beam dynamics, MPI, the CLI."""

import json
import math
import os
import shutil
import subprocess
import sys

import numpy as np
import pytest

from meshes import box, structured_box
from meshes.regions import BoxRegion
from realtime import Material
from reference.driver import solve_static as reference_static
from reference.errors import ReferenceSolveError
from reference.fem import ElasticityProblem
from reference.manufactured import manufactured_errors
from reference.problem import Displacement, Fixed, Gravity, Problem
from verification.runs.results import Result
from verification.scene_file import load_scene

from ..conftest import SWING


def fitted(h, e):
    return float(np.polyfit(np.log(h), np.log(e), 1)[0])


@pytest.mark.slow
@pytest.mark.parametrize("law", ["linear", "stvk"])
@pytest.mark.parametrize("degree, sizes", [(1, (4, 8, 16)), (2, (2, 4, 8))])
def test_manufactured_solution_orders(law, degree, sizes):
    """Observed orders within 0.1 of theory: P1 2 (L2) and 1 (H1); P2 3 and 2 (docs/verification.md)."""
    mat = Material(1e4, 0.3, 1.0, law=law)
    runs = [manufactured_errors(law, degree, n, mat) for n in sizes]
    h = [r["h"] for r in runs]
    assert fitted(h, [r["l2"] for r in runs]) == pytest.approx(degree + 1, abs=0.1)
    assert fitted(h, [r["h1"] for r in runs]) == pytest.approx(degree, abs=0.1)


def stretch_scene(tmp_path, s, law="stvk", fiber=None, axis="x"):
    """A unit block on three symmetry planes (rollers), pulled on the far face along ``axis``."""
    k = "xyz".index(axis)
    lo_far = [-1.0] * 3
    lo_far[k] = 1.0 - 1e-9
    fib = f"fiber = {list(fiber)}\nyoung_fiber = 3.0e4\n" if fiber else ""
    value = [0.0, 0.0, 0.0]
    value[k] = s - 1.0
    text = f"""
name = "stretch"
[mesh]
generator = "box"
size = [1.0, 1.0, 1.0]
h = 0.5
[material]
law = "{law}"
young = 1.0e4
poisson = 0.3
density = 1.0
{fib}
[[fixed]]
box = [[-1e-9, -1.0, -1.0], [1e-9, 2.0, 2.0]]
components = ["x"]
[[fixed]]
box = [[-1.0, -1e-9, -1.0], [2.0, 1e-9, 2.0]]
components = ["y"]
[[fixed]]
box = [[-1.0, -1.0, -1e-9], [2.0, 2.0, 1e-9]]
components = ["z"]
[[load]]
kind = "displacement"
box = [{lo_far}, [2.0, 2.0, 2.0]]
components = ["{axis}"]
value = {value}
"""
    p = tmp_path / "stretch.toml"
    p.write_text(text)
    return load_scene(p)


@pytest.mark.parametrize("s", [0.7, 1.2, 1.5])
def test_uniaxial_stretch_of_stvk(tmp_path, s):
    """Nominal stress from the reaction: E s (s^2 - 1) / 2, lateral stretch t^2 = 1 - nu (s^2 - 1)."""
    scene = stretch_scene(tmp_path, s)
    m = scene.material
    sol = reference_static(scene.mesh, m, scene.problem, degree=1, estimate=False, newton_steps=4)
    # homogeneous state: exact in P1; Newton to 1e-10 increments
    assert sol["reaction"][0] == pytest.approx(m.young * s * (s * s - 1) / 2, rel=1e-8)
    t = math.sqrt(1 - m.poisson * (s * s - 1))
    far_y = scene.mesh.points[:, 1] > 1 - 1e-9
    np.testing.assert_allclose(sol["displacement"][far_y, 1], t - 1.0, rtol=1e-8)


def test_rotation_energy_of_the_linear_reference(tmp_path):
    """A 90 degree rotation of a linear body stores 2 (lambda + mu)(cos theta - 1)^2 per unit volume;
    the StVK body none (its reaction is round-off: tests/reference/test_beam_theory_and_locking.py)."""
    mesh = box(size=[0.02, 0.02, 0.02], h=0.01)
    rot = Displacement(
        region=BoxRegion((-1, -1, -1), (1, 1, 1)), axis=(0.0, 0.0, 1.0), center=(0.01, 0.01, 0.0), angle=90.0
    )
    for law, expected in (("linear", None), ("stvk", 0.0)):
        mat = Material(1e4, 0.3, 1.0, law=law)
        ep = ElasticityProblem(mesh, mat, Problem((), (rot,)), degree=1)
        ep.solve(steps=1) if law == "stvk" else ep.solve()
        volume = 0.02**3
        if expected is None:
            expected = 2 * (mat.lam + mat.mu) * (math.cos(math.pi / 2) - 1) ** 2 * volume
            assert ep.energy() == pytest.approx(expected, rel=1e-10)
        else:
            assert abs(ep.energy()) < 1e-20 * mat.young * volume


def test_transversely_isotropic_stiffnesses(tmp_path):
    """Small stretches along and across the fibre: reaction / strain is young_fiber along the fibre
    and the modulus the compliance of the same tensor gives across it (realtime.material docstring)."""
    from realtime.laws import linear_elasticity_tensor

    eps = 1e-6
    along = stretch_scene(tmp_path, 1 + eps, law="linear", fiber=(1.0, 0.0, 0.0), axis="x")
    across = stretch_scene(tmp_path, 1 + eps, law="linear", fiber=(1.0, 0.0, 0.0), axis="y")
    m = along.material
    r_along = reference_static(along.mesh, m, along.problem, degree=1, estimate=False)["reaction"][0]
    r_across = reference_static(across.mesh, m, across.problem, degree=1, estimate=False)["reaction"][1]
    C = linear_elasticity_tensor(m.lam, m.mu, m.fiber_vector, m.dlam, m.dmu).reshape(9, 9)
    S = np.linalg.pinv(C)
    e_y = np.outer([0, 1.0, 0], [0, 1.0, 0]).ravel()
    assert r_along / eps == pytest.approx(3.0e4, rel=1e-8)
    assert r_across / eps == pytest.approx(1.0 / (e_y @ S @ e_y), rel=1e-8)
    assert r_along > 2 * r_across  # the fibre makes the difference


def slender_beam(law="linear"):
    L, b = 0.4, 0.02
    mesh = box(size=[L, b, b], h=0.01)
    mat = Material(5e6, 0.3, 1000.0, law=law)
    prob = Problem(fixed=(Fixed(BoxRegion((-1e-9, -1, -1), (1e-9, 1, 1))),), loads=(Gravity((0.0, 0.0, -9.81)),))
    w1 = 1.8751**2 * math.sqrt(mat.young * b**4 / 12 / (mat.density * b * b * L**4))
    return mesh, mat, prob, 2 * math.pi / w1, np.array([[L, b / 2, b / 2]])


def test_first_bending_frequency_matches_euler_bernoulli():
    """Slender cantilever (L/h = 20) suddenly loaded by gravity, P2, Newmark: the tip oscillates at the
    first bending frequency (beta_1 L = 1.8751) within 2% (measured: 0.08%)."""
    mesh, mat, prob, T, tip = slender_beam()
    ep = ElasticityProblem(mesh, mat, prob, degree=2)
    run = ep.solve_dynamic(T / 100, 3 * T, T / 100, tip)
    times, vals = run.times, run.values
    w = vals[:, 0, 2] - vals[:, 0, 2].mean()
    up = np.flatnonzero((w[:-1] < 0) & (w[1:] >= 0))
    crossings = times[up] - w[up] * (times[up + 1] - times[up]) / (w[up + 1] - w[up])
    assert np.diff(crossings).mean() == pytest.approx(T, rel=0.02)


def test_newmark_is_second_order_in_time():
    """Trajectory error against a run at T1/2560, fitted over T1/80 .. T1/320: order 2 within 0.1.

    A light Rayleigh stiffness damping (b = 2e-3 s: 0.9% of critical on the first mode, overdamped
    above 1 kHz) removes the P1 mesh's highest modes, whose phase error stays O(1) until omega dt << 1
    and otherwise hides the order (undamped, the fit gives 1.5 at these steps).
    """
    mesh, mat, prob, T, tip = slender_beam()
    pts = mesh.points[::7]

    def trajectory(dt):
        ep = ElasticityProblem(mesh, mat, prob, degree=1)
        return ep.solve_dynamic(dt, T / 2, T / 20, pts, rayleigh=(0.0, 2e-3)).values

    fine = trajectory(T / 2560)
    dts = [T / 80, T / 160, T / 320]
    errs = [np.linalg.norm(trajectory(dt) - fine) for dt in dts]
    assert fitted(dts, errs) == pytest.approx(2.0, abs=0.1)


def test_stvk_dynamics_runs_newton_per_step():
    """The slender beam's static sag is 47% of its length (q L^4 / 8 E I = 0.19 m): StVK and linear
    dynamics must part ways, and StVK takes Newton iterations at every step."""
    mesh, mat, prob, T, tip = slender_beam("stvk")
    ep = ElasticityProblem(mesh, mat, prob, degree=1)
    run = ep.solve_dynamic(T / 50, T / 5, T / 50, tip)
    vals, info = run.values, run.info
    linear = ElasticityProblem(mesh, mat.replace(law="linear"), prob, degree=1)
    lin = linear.solve_dynamic(T / 50, T / 5, T / 50, tip).values
    assert info["iterations"] >= 2 * info["steps"]  # Newton: at least one correction and one check per step
    assert np.all(np.isfinite(vals))
    assert np.linalg.norm(vals - lin) / np.linalg.norm(lin) > 0.01


def test_newmark_keeps_its_factorisation_and_its_answer(monkeypatch):
    """In a Newmark step a factorised tangent is kept while each Newton step halves the residual
    (SLOW_DYNAMIC): the trajectory is classic Newton's (a factorisation per iteration) to 1e-8 relative
    (both stop at 1e-10 of the force scale; the effective stiffness's conditioning scales that), with
    fewer factorisations. This beam sags to half its length in ten steps, so the tangent moves a lot
    here: 27 factorisations against 39; on the bench's slender beam (1600 short steps) 4 in 100 steps."""
    from reference import solver

    mesh, mat, prob, T, tip = slender_beam("stvk")
    runs = {}
    for mode, slow in (("classic", math.inf), ("modified", solver.SLOW_DYNAMIC)):
        monkeypatch.setattr(solver, "SLOW_DYNAMIC", slow)
        ep = ElasticityProblem(mesh, mat, prob, degree=1)
        run = ep.solve_dynamic(T / 50, T / 5, T / 50, tip)
        vals, info = run.values, run.info
        runs[mode] = vals, info
    (a, classic), (b, modified) = runs["classic"], runs["modified"]
    assert np.linalg.norm(a - b) <= 1e-8 * np.linalg.norm(a)
    assert classic["factorisations"] >= classic["iterations"] - classic["steps"]  # one per correction
    assert modified["factorisations"] < classic["factorisations"]


def test_iterative_solver_matches_lu():
    scene = load_scene("cantilever").with_material(law="linear")
    lu = ElasticityProblem(scene.mesh, scene.material, scene.problem, degree=2)
    lu.solve()
    it = ElasticityProblem(scene.mesh, scene.material, scene.problem, degree=2)
    it.solve_linear(petsc_options={"ksp_type": "cg", "pc_type": "gamg", "ksp_rtol": 1e-12})
    a, b = lu.evaluate(scene.mesh.points), it.evaluate(scene.mesh.points)
    assert np.linalg.norm(a - b) / np.linalg.norm(a) < 1e-8


def test_newton_failure_names_the_load_fraction():
    scene = load_scene("cantilever-pull")
    ep = ElasticityProblem(scene.mesh, scene.material, scene.problem, degree=1)
    with pytest.raises(ReferenceSolveError, match=r"load fraction [0-9.]+"):
        ep.solve_newton(steps=1, max_it=1, min_increment=0.3)


def test_a_diverging_newton_is_cut_early_and_fails_at_the_same_load(monkeypatch):
    """The cantilever pushed to half its length (the stability study's compression) has no StVK
    equilibrium past a load fraction: Newton there is not slow but diverging, its residual a thousandfold
    above its best within a few steps. Giving up then (DIVERGED) must not move where the solve fails,
    only what it costs: measured at P1, 106 factorisations against 210 when each attempt runs its 25."""
    from reference import solver
    from verification.studies.stability import _far_face_tool

    scene = _far_face_tool(load_scene("cantilever"), "compression")
    count = [0]
    factorise = solver.Newton._factorise

    def counted(self):
        count[0] += 1
        factorise(self)

    monkeypatch.setattr(solver.Newton, "_factorise", counted)
    outcomes = []
    for diverged in (solver.DIVERGED, math.inf):
        monkeypatch.setattr(solver, "DIVERGED", diverged)
        count[0] = 0
        ep = ElasticityProblem(scene.mesh, scene.material, scene.problem, degree=1)
        with pytest.raises(ReferenceSolveError, match=r"beyond load fraction ([0-9.]+)") as exc:
            ep.solve_newton(steps=4, min_increment=1e-2)
        outcomes.append((str(exc.value).split("beyond load fraction ")[1].split()[0], count[0]))
    (cut, n_cut), (patient, n_patient) = outcomes
    assert cut == patient and float(cut) > 0.1  # fails where it did, past a real part of the path
    assert n_cut < 0.75 * n_patient


def tool_env():
    env = dict(os.environ)
    env.update(OMPI_ALLOW_RUN_AS_ROOT="1", OMPI_ALLOW_RUN_AS_ROOT_CONFIRM="1", OMPI_MCA_rmaps_base_oversubscribe="1")
    return env


def cli(*args, mpi=0):
    exe = [sys.executable, "-m", "verification.cli", *args]
    if mpi:
        exe = [shutil.which("mpirun"), "-n", str(mpi), *exe]
    return subprocess.run(exe, capture_output=True, text=True, env=tool_env(), timeout=900)


@pytest.mark.slow
@pytest.mark.mpi
def test_mpirun_two_ranks_equals_serial(tmp_path):
    """A static StVK scene solved on one rank and on two (the mesh distributed by dolfinx)."""
    serial, parallel = tmp_path / "serial.npz", tmp_path / "mpi.npz"
    args = ["reference", "cantilever-pull", "--degree", "2", "--no-estimate", "--no-cache"]
    r = cli(*args, "--out", str(serial))
    assert r.returncode == 0, r.stderr
    r = cli(*args, "--out", str(parallel), mpi=2)
    assert r.returncode == 0, r.stderr
    a, b = Result.load(serial), Result.load(parallel)
    assert b.meta["mpi_ranks"] == 2
    assert np.linalg.norm(a.displacement - b.displacement) / np.linalg.norm(a.displacement) < 1e-8
    assert np.linalg.norm(a.reaction - b.reaction) / np.linalg.norm(a.reaction) < 1e-8


@pytest.mark.slow
@pytest.mark.mpi
def test_mpirun_nested_estimate_equals_serial(tmp_path):
    """With the estimate: on two ranks the refined solve starts from the coarse solution too (every
    rank's nodes gathered and evaluated on the distributed coarse mesh), and the returned solution and
    its bar are the serial ones (1e-8: Newtons stopped at 1e-10 of the force scale)."""
    serial, parallel = tmp_path / "serial.npz", tmp_path / "mpi.npz"
    args = ["reference", "cantilever-pull", "--degree", "1", "--no-cache"]
    for out, mpi in ((serial, 0), (parallel, 2)):
        r = cli(*args, "--out", str(out), mpi=mpi)
        assert r.returncode == 0, r.stderr
    a, b = Result.load(serial), Result.load(parallel)
    assert b.meta["mpi_ranks"] == 2
    for res in (a, b):
        assert res.meta["solves"][1]["load_steps"][0].get("nested")
    assert np.linalg.norm(a.displacement - b.displacement) / np.linalg.norm(a.displacement) < 1e-8
    assert b.meta["ref_err_estimate"] == pytest.approx(a.meta["ref_err_estimate"], rel=1e-6)


def test_cli_reference_writes_the_result_file_with_its_estimate(tmp_path):
    scene = tmp_path / "small.toml"
    text = load_scene("cantilever-pull").path.read_text().replace("h = 0.005", "h = 0.01")
    scene.write_text(text.replace('law = "stvk"', 'law = "linear"'))  # the file format, not Newton, is tested
    out = tmp_path / "ref.npz"
    r = cli("reference", str(scene), "--degree", "2", "--refine", "1", "--out", str(out), "--json")
    assert r.returncode == 0, r.stderr
    summary = json.loads(r.stdout)
    res = Result.load(out)
    assert set(["points", "tets", "times", "displacement", "reaction", "meta"]) <= set(np.load(out).files)
    assert res.meta["ref_err_estimate"] == summary["meta"]["ref_err_estimate"] > 0
    assert res.meta["refine"] == 1 and res.meta["degree"] == 2


def test_structured_box_is_exact_for_homogeneous_states():
    """The Kuhn mesh used above reproduces a linear field exactly (guards the stretch test's premise)."""
    m = structured_box([1, 1, 1], 2)
    assert m.quality()["total_volume_m3"] == pytest.approx(1.0, rel=1e-14)


def _engine_linear_solution(scene):
    """The linear tensor-mass's static answer on a scene with forces only, by a direct sparse solve of
    its rest stiffness (N, 3) m: the settled model without the settling."""
    import scipy.sparse.linalg as spla

    from verification.engines.builtin import scene_model

    model = scene_model(scene, "linear-tm")
    free = model.loading.free.ravel() > 0
    k = model.rest_stiffness().tocsc()[free][:, free]
    u = np.zeros(3 * model.n_vertices)
    u[free] = spla.spsolve(k, model.loading.external_force.ravel()[free])
    return u.reshape(-1, 3)


@pytest.mark.slow
def test_fibres_around_an_axis_engine_and_reference_converge_together():
    """The reference evaluates circumferential fibres at its quadrature points, the engine at each
    tetrahedron's centroid: one problem, two samplings of its coefficient, whose difference must vanish
    as the mesh is refined (with fibres along one direction they solve one linear system)."""
    from verification.studies.seeds.common import seed_scene

    def edit(around):
        def change(data):
            data["material"]["law"] = "linear"
            data["material"]["young_fiber"] = 5.0e5
            if around:
                data["material"]["fiber_around"] = {"axis": [0.0, 0.0, 1.0]}
            else:
                data["material"]["fiber"] = [0.0, 0.0, 1.0]
            data["load"][0]["value"] = [0.002, 0.0, 0.0]
            data["mesh"]["h"] = 0.005

        return change

    def gap(scene):
        p1 = reference_result(scene, degree=1, estimate=False, own_mesh=True).displacement[0]
        return float(np.linalg.norm(_engine_linear_solution(scene) - p1) / np.linalg.norm(p1))

    from verification.runs.reference import reference_result

    axial = seed_scene("tube", "-axial", edit(False))
    # one linear system, LU against a sparse direct solve: round-off times a conditioning of about 1e6
    assert gap(axial) < 1e-9
    coarse, fine = (seed_scene("tube", "-around", edit(True), refine=k) for k in (0, 1))
    g0, g1 = gap(coarse), gap(fine)
    # the centroid rule samples the field to O(h^2): halving h must at least halve the gap
    assert g1 < g0 / 2.0 and g0 < 0.05


@pytest.mark.slow
@pytest.mark.mpi
def test_mpirun_two_ranks_newmark_equals_serial(tmp_path):
    """A dynamic StVK scene with both Rayleigh terms on one rank and on two: a Newmark residual adds its
    inertia and damping as products on each rank's owned entries, and the ghosts' parts of the assembled
    residual must still be added once (1e-8: Newtons stopped at 1e-10 of the force scale, over 20 steps)."""
    scene = tmp_path / "swing.toml"
    scene.write_text(
        SWING
        + """
[time]
mode = "dynamic"
end = 0.01
output_every = 0.002
damping = { mass = 2.0, stiffness = 1e-4 }
"""
    )
    serial, parallel = tmp_path / "serial.npz", tmp_path / "mpi.npz"
    args = ["reference", str(scene), "--degree", "2", "--no-estimate", "--no-cache"]
    for out, mpi in ((serial, 0), (parallel, 2)):
        r = cli(*args, "--out", str(out), mpi=mpi)
        assert r.returncode == 0, r.stderr
    a, b = Result.load(serial), Result.load(parallel)
    assert b.meta["mpi_ranks"] == 2 and len(a.times) == 6
    assert np.linalg.norm(a.displacement - b.displacement) <= 1e-8 * np.linalg.norm(a.displacement)
    assert np.linalg.norm(a.reaction - b.reaction) <= 1e-8 * np.linalg.norm(a.reaction)


def test_a_body_nothing_holds_falls_as_newmark_integrates_a_constant_acceleration():
    """A free P2 block under gravity g: every node moves by g t^2 / 2, which average-acceleration
    Newmark integrates exactly once its initial acceleration, M a0 = f, is g at every node (the mass
    solve's conjugate gradients stop at 1e-13 of the residual, its conditioning in the tens: 1e-10
    relative leaves room for that and the steps' round-off; a0 = 0 would miss by half the answer)."""
    g = np.array([0.0, -3.0, -9.81])
    mesh = box(size=[0.02, 0.01, 0.01], h=0.005)
    ep = ElasticityProblem(
        mesh, Material(1e5, 0.3, 1000.0, law="linear"), Problem(fixed=(), loads=(Gravity(tuple(g)),))
    )
    run = ep.solve_dynamic(1e-3, 0.01, 1e-3, mesh.points)
    exact = 0.5 * g * run.times[:, None, None] ** 2
    assert np.abs(run.values - exact).max() <= 1e-10 * np.abs(exact).max()
    assert np.abs(ep.acceleration.x.array.reshape(-1, 3) - g).max() <= 1e-8 * np.linalg.norm(g)
