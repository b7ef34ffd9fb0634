"""Contract tests every real-time model passes, and each model's own promise (docs/promises.md)."""

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from meshes import stored_mesh, structured_box
from realtime import MODELS, InputError, Material, Materials, State, build_model
from realtime.models import SPECS
from realtime.models.linear_tm import cut
from reference.fem import ElasticityProblem
from reference.problem import Problem

from ..conftest import match_nodes

ISO = Material(2.8e4, 0.4, 1000.0, law="stvk")
FIBRE = Material(2.8e4, 0.4, 1000.0, law="stvk", fiber=(1.0, 0.5, 0.2), young_fiber=6e4, fiber_shear=3e3)
PENALTY = Material(2.8e4, 0.4, 1000.0, law="stvk", volume_penalty=5e4)
#: Circumferential fibres around a line through the test meshes (not through any centroid).
AROUND = Material(
    2.8e4,
    0.4,
    1000.0,
    law="stvk",
    fiber_axis=(0.1, 0.2, 1.0),
    fiber_point=(1e-3, 2e-3, 0.0),
    young_fiber=6e4,
    fiber_shear=3e3,
)
DYNAMIC = [m for m in MODELS if not SPECS[m].quasi_static]
#: The models with mechanics (ffd has none: tests/realtime/test_ffd.py holds its promises).
PHYSICAL = [m for m in MODELS if SPECS[m].mechanics]


def cylinder():
    return stored_mesh("cylinder")


def trial_state(model, rng, amplitude=1e-3):
    """A random displacement (N, 3) m of ``model``'s vertices, ``amplitude`` per component (1e-3 on the
    cylinder, whose edges are 4.4 mm: about 70 of its 2465 tetrahedra inverted, where the non-linear
    terms dominate). For a law whose energy is infinite at an inverted element (neo-Hookean) the same
    direction, halved until no tetrahedron inverts (on the cylinder: a quarter of it, strains of 10%)."""
    u = amplitude * rng.standard_normal(model.points.shape)
    while not np.isfinite(model.elastic_energy(u)):
        u *= 0.5
    return u


def rotation(angle_deg, axis=(0.0, 0.0, 1.0)):
    k = np.asarray(axis, float) / np.linalg.norm(axis)
    th = math.radians(angle_deg)
    K = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + math.sin(th) * K + (1 - math.cos(th)) * K @ K


def mixed(n_tets):
    """ISO on the first half of the tetrahedra, fibres with the volume penalty on the rest: the blocks of
    one body take both of stvk-tm's element loops (the isotropic one and the general one)."""
    fibred = Material(2.8e4, 0.4, 1000.0, law="stvk", fiber=(1.0, 0.5, 0.2), young_fiber=6e4, volume_penalty=5e4)
    return Materials((ISO, fibred), (np.arange(n_tets) >= n_tets // 2).astype(np.int64))


ENERGY_CASES = [(m, ISO, {}) for m in PHYSICAL] + [
    ("linear-tm", AROUND, {}),
    ("stvk-tm", AROUND, {}),
    ("stvk-tm", PENALTY, {}),
    ("stvk-tm", mixed, {}),
    ("hybrid-tm", AROUND, {"threshold": 2e-3}),  # u below has both sides of the threshold
]
ENERGY_IDS = {id(ISO): "iso", id(AROUND): "around", id(PENALTY): "penalty", id(mixed): "mixed"}


@pytest.mark.parametrize(
    "name, material, options",
    ENERGY_CASES,
    ids=[f"{m}-{ENERGY_IDS[id(mat)]}" for m, mat, _ in ENERGY_CASES],
)
def test_force_is_minus_energy_gradient(name, material, options, rng):
    mesh = cylinder()
    if callable(material):
        material = material(mesh.n_tets)
    model = build_model(name, mesh.points, mesh.tets, material, **options)
    u = trial_state(model, rng)
    f = model.internal_force(u)
    h = 1e-8
    for k in rng.choice(mesh.n_vertices, 4, replace=False):
        for c in range(3):
            d = np.zeros_like(u)
            d[k, c] = h
            fd = -(model.elastic_energy(u + d) - model.elastic_energy(u - d)) / (2 * h)
            # central difference: truncation h^2 W''' ~ 1e-12 f; round-off eps W / h ~ 1e-8 |f|max
            assert fd == pytest.approx(f[k, c], rel=1e-5, abs=1e-6 * np.abs(f).max())


@pytest.mark.parametrize("name", PHYSICAL)
def test_stiffness_is_derivative_of_force(name, rng):
    """The tangent stiffness applied by finite differences of the force is symmetric (a potential
    force), and equals the assembled matrix for the linear models."""
    mesh = cylinder()
    model = build_model(name, mesh.points, mesh.tets, ISO)
    u = trial_state(model, rng)
    a, b = rng.standard_normal((2, *mesh.points.shape))
    h = 1e-7

    def K(v):
        return -(model.internal_force(u + h * v) - model.internal_force(u - h * v)) / (2 * h)

    ka, kb = K(a), K(b)
    scale = np.linalg.norm(ka) * np.linalg.norm(b)
    assert abs(np.sum(ka * b) - np.sum(kb * a)) < 1e-6 * scale
    if "tensors" in model.extra and name in ("linear-tm", "precomputed", "condensed"):
        Km = model.extra["tensors"].matrix()
        np.testing.assert_allclose(ka.ravel(), Km @ a.ravel(), rtol=1e-6, atol=1e-8 * np.abs(ka).max())


@pytest.mark.parametrize("name", PHYSICAL)
def test_self_equilibrated_and_translation_free(name, rng):
    mesh = cylinder()
    model = build_model(name, mesh.points, mesh.tets, ISO)
    u = trial_state(model, rng)
    f = model.internal_force(u)
    scale = np.abs(f).max() * mesh.n_vertices
    assert np.abs(f.sum(axis=0)).max() < 1e-13 * scale
    # torque about the origin, in the configuration where the model's forces live
    x = mesh.points if model.linear else mesh.points + u
    assert np.abs(np.cross(x, f).sum(axis=0)).max() < 1e-13 * scale * np.abs(x).max()
    t = np.tile([0.3, -0.2, 0.1], (mesh.n_vertices, 1))
    assert np.abs(model.internal_force(t)).max() < 1e-10 * np.abs(f).max()


def test_a_condensed_body_nothing_holds_has_forces_but_no_static_answer():
    """condensed on a body with no fixed or tool vertex: it builds, a rigid translation gives it no force
    (to round-off of a 1e-3 strain's), and a static answer, which does not exist (every rigid motion is
    free), is refused in one line, whatever the
    BLAS's round-off makes of the singular Cholesky factorisation (Debian's reference BLAS passed it)."""
    from realtime.quasistatic import Condensed

    mesh = cylinder()
    model = build_model("condensed", mesh.points, mesh.tets, ISO)
    u = 1e-3 * np.tile([1.0, 0.0, 0.0], (mesh.n_vertices, 1))
    assert np.abs(model.internal_force(u)).max() < 1e-10 * ISO.young * 0.004**2 * 1e-3
    solver = model.extra["quasistatic"]
    assert isinstance(solver, Condensed)
    with pytest.raises(InputError, match=r"^condensed: .*rigid motion") as err:
        solver.update(np.zeros(0))
    assert "\n" not in str(err.value)


@pytest.mark.parametrize("name", ["corotational-tm", "stvk-tm", "mass-spring", "hybrid-tm"])
def test_rigid_rotation_gives_zero_force(name):
    mesh = cylinder()
    model = build_model(name, mesh.points, mesh.tets, ISO)
    R = rotation(90.0, (1.0, 1.0, 0.0))
    u = mesh.points @ R.T - mesh.points
    f = model.internal_force(u)
    # force scale of a unit strain: E h^2 with h the edge length (4 mm): ~0.45 N; round-off is 1e-15 of it
    assert np.abs(f).max() < 1e-11 * ISO.young * 0.004**2


def test_linear_models_do_not_rotate():
    mesh = cylinder()
    model = build_model("linear-tm", mesh.points, mesh.tets, ISO)
    u = mesh.points @ rotation(90.0).T - mesh.points
    # the spurious energy 2 (lambda + mu)(cos theta - 1)^2 per unit volume (here theta = 90 degrees)
    assert model.elastic_energy(u) == pytest.approx(2 * (ISO.lam + ISO.mu) * mesh.volumes().sum(), rel=1e-10)
    assert np.abs(model.internal_force(u)).max() > 1.0


@pytest.mark.parametrize("material", [ISO, FIBRE, PENALTY], ids=["isotropic", "transverse", "penalty"])
def test_stvk_tm_equals_dolfinx_p1_residual(material, rng):
    mesh = stored_mesh("beam")
    model = build_model("stvk-tm", mesh.points, mesh.tets, material)
    ep = ElasticityProblem(mesh, material, Problem((), ()), degree=1)
    _, coords = ep.stiffness_matrix()
    node = match_nodes(coords, mesh.points)
    u = 2e-3 * rng.standard_normal(mesh.points.shape)  # 40% of the edge length: strongly non-linear
    U = np.zeros((len(coords), 3))
    U[node] = u
    r = ep.residual_vector(U)[node]  # internal minus external force; no load here
    f = model.internal_force(u)
    # two evaluations of the same integrals in different orders: round-off
    assert np.linalg.norm(f + r) / np.linalg.norm(r) < 1e-10


def test_volume_penalty_resists_inversion():
    """Squash a block flat (uniaxial strain): StVK's restoring force peaks at the stretch 1/sqrt(3) and
    vanishes as the block flattens (P33 = (lam + 2 mu) s (s^2 - 1) / 2); the penalty's keeps growing."""
    mesh = structured_box([0.01, 0.01, 0.01], 2)
    top = mesh.points[:, 2] > 0.01 - 1e-9
    plain = build_model("stvk-tm", mesh.points, mesh.tets, ISO)
    pen = build_model("stvk-tm", mesh.points, mesh.tets, PENALTY)

    def push_back(model, s):
        u = np.zeros_like(mesh.points)
        u[:, 2] = (s - 1.0) * mesh.points[:, 2]
        return model.internal_force(u)[top, 2].sum()  # > 0: the block pushes the top face back up

    stretches = [0.9, 1 / math.sqrt(3), 0.3, 0.05]
    p = [push_back(plain, s) for s in stretches]
    q = [push_back(pen, s) for s in stretches]
    # the exact P1 value on a homogeneous state: P33 times the face area
    s0 = 1 / math.sqrt(3)
    assert p[1] == pytest.approx(-(ISO.lam + 2 * ISO.mu) * s0 * (s0**2 - 1) / 2 * 1e-4, rel=1e-10)
    assert p[1] > p[0] and p[3] < p[2] < p[1]  # StVK softens past 1/sqrt(3)
    assert q[3] > q[2] > q[1] > q[0]  # the penalty resists more the flatter it gets


def test_hybrid_limits(rng):
    mesh = cylinder()
    u = 1e-3 * rng.standard_normal(mesh.points.shape)
    stvk = build_model("stvk-tm", mesh.points, mesh.tets, FIBRE).internal_force(u)
    lin = build_model("linear-tm", mesh.points, mesh.tets, FIBRE).internal_force(u)
    h0 = build_model("hybrid-tm", mesh.points, mesh.tets, FIBRE, threshold=0.0).internal_force(u)
    hinf = build_model("hybrid-tm", mesh.points, mesh.tets, FIBRE, threshold=np.inf).internal_force(u)
    # threshold 0: linear force plus (StVK - linear) per element, which cancels to round-off
    assert np.linalg.norm(h0 - stvk) / np.linalg.norm(stvk) < 1e-12
    assert np.array_equal(hinf, lin)  # threshold infinity: the very same kernel path


def test_hybrid_vertices_remember_their_law_within_the_band():
    """hybrid-tm's hysteresis: a vertex turns non-linear past the threshold and back to linear only
    within RELEASE times it. One vertex is displaced 0.75 thresholds (inside the band): from rest (a
    fresh scratch) its tetrahedra are linear; after it went 1.5 thresholds out, the same u gives the
    StVK force on them; back at 0.25 thresholds it is linear again, bit for bit the force from rest."""
    from realtime.hybrid import RELEASE

    mesh = cylinder()
    thr = 1e-3
    assert RELEASE < 0.75 < 1.0 and 0.25 < RELEASE
    model = build_model("hybrid-tm", mesh.points, mesh.tets, ISO, threshold=thr)
    lin = build_model("linear-tm", mesh.points, mesh.tets, ISO)
    k = mesh.n_vertices // 2
    d = np.array([0.6, -0.48, 0.64])  # a unit vector

    def at(r):
        u = np.zeros_like(mesh.points)
        u[k] = r * thr * d
        return u

    scratch = model.new_scratch()
    inside = at(0.75)
    assert np.array_equal(model.force_with(scratch, inside), lin.internal_force(inside))
    model.force_with(scratch, at(1.5))
    remembered = model.force_with(scratch, inside)
    # the StVK correction at a 7.5e-4 m displacement of one vertex on 4 mm edges (strain ~0.2): well
    # above round-off of the force (1e-12 relative)
    assert np.linalg.norm(remembered - lin.internal_force(inside)) > 1e-3 * np.linalg.norm(remembered)
    assert np.array_equal(model.force_with(scratch, at(0.25)), model.internal_force(at(0.25)))


def test_mass_spring_calibration():
    """Van Gelder's springs on a structured block in uniaxial tension: measured E and nu.

    E_eff = 1.034 E on the Kuhn lattice (the calibration is for the modulus), and nu_eff = 0.035 whatever
    the material's nu: a central-spring network cannot represent Poisson's ratio. Both are asserted, so a
    change of calibration must change this test and its docstring.
    """
    L = 0.04
    mesh = structured_box([L, 0.02, 0.02], [8, 4, 4])
    model = build_model("mass-spring", mesh.points, mesh.tets, Material(1e4, 0.3, 1000.0))
    x = mesh.points
    n = mesh.n_vertices
    h = 1e-7

    def K_col(v):
        return -(model.internal_force(h * v) - model.internal_force(-h * v)).ravel() / (2 * h)

    K = np.column_stack([K_col(np.eye(3 * n)[:, j].reshape(n, 3)) for j in range(3 * n)])
    left, right = x[:, 0] < 1e-9, x[:, 0] > L - 1e-9
    held = np.zeros((n, 3), bool)
    held[left, 0] = held[right, 0] = True
    corner = np.flatnonzero(left & (x[:, 1] < 1e-9) & (x[:, 2] < 1e-9))[0]
    held[corner] = True
    held[np.flatnonzero(left & (x[:, 1] > 0.02 - 1e-9) & (x[:, 2] < 1e-9))[0], 2] = True
    held[np.flatnonzero(left & (x[:, 1] < 1e-9) & (x[:, 2] > 0.02 - 1e-9))[0], 1] = True
    delta = 1e-5
    u = np.zeros((n, 3))
    u[right, 0] = delta
    held, u = held.ravel(), u.ravel()
    u[~held] = np.linalg.solve(K[np.ix_(~held, ~held)], -K[np.ix_(~held, held)] @ u[held])
    force = (K @ u).reshape(n, 3)[right, 0].sum()
    E_eff = force / (0.02 * 0.02) / (delta / L)
    u = u.reshape(n, 3)
    mid = np.abs(x[:, 0] - L / 2) < 1e-9
    top, bottom = mid & (x[:, 1] > 0.02 - 1e-9), mid & (x[:, 1] < 1e-9)
    nu_eff = -(u[top, 1].mean() - u[bottom, 1].mean()) / 0.02 / (delta / L)
    assert E_eff / 1e4 == pytest.approx(1.0345, abs=0.002)
    assert nu_eff == pytest.approx(0.0346, abs=0.002)


def test_cutting_equals_rebuild():
    mesh = stored_mesh("liver")
    mat = FIBRE
    model = build_model("linear-tm", mesh.points, mesh.tets, mat)
    centre = mesh.points.mean(axis=0)
    first = np.flatnonzero(np.linalg.norm(mesh.points[mesh.tets].mean(axis=1) - centre, axis=1) < 0.015)
    second = np.flatnonzero(np.abs(mesh.points[mesh.tets].mean(axis=1)[:, 1] - 0.03) < 0.003)
    second = np.setdiff1d(second, first)
    cut_model = cut(cut(model, first), second)
    keep = np.setdiff1d(np.arange(mesh.n_tets), np.concatenate([first, second]))
    fresh = build_model("linear-tm", mesh.points, mesh.tets[keep], mat)
    A, B = cut_model.extra["tensors"].matrix(), fresh.extra["tensors"].matrix()
    # removal subtracts what assembly added, in another order: round-off of the largest entry
    assert abs(A - B).max() < 1e-12 * abs(B).max()
    alive = np.unique(mesh.tets[keep])
    np.testing.assert_allclose(cut_model.mass[alive], fresh.mass[alive], rtol=1e-12)
    orphans = np.setdiff1d(np.arange(mesh.n_vertices), alive)
    assert np.all(cut_model.loading.free[orphans] == 0.0)
    with pytest.raises(ValueError, match="already removed"):
        cut_model.extra["tensors"].remove(first[:1])
    with pytest.raises(ValueError, match="already removed"):
        cut(cut_model, first[:1])
    # numpy would take -1 as the last tetrahedron, and truncate 0.5 to the first: both refused
    m = mesh.n_tets
    for which, message in (
        ([m], rf"cut: which: {m} is outside 0..{m - 1}"),
        ([-1], rf"cut: which: -1 is outside 0..{m - 1}"),
        ([0.5], r"cut: which: must be whole-number indices, got 0.5"),
        ([[0, 1]], r"cut: which: must be a list of indices, got shape \(1, 2\)"),
    ):
        with pytest.raises(InputError, match=message):
            cut(cut_model, which)


def test_each_cut_model_keeps_its_own_tetrahedra_and_masses_after_later_cuts():
    """A cut's model makes its tetrahedra when first read (the cut itself costs what it touches): read
    after two later cuts, the first model's are still its own (the mesh less the first cut), the last
    one's the mesh less all three, and each model's vertices that lost every tetrahedron are held with
    a unit mass, the others' masses those of a model built on its tetrahedra."""
    mesh = stored_mesh("liver")
    model = build_model("linear-tm", mesh.points, mesh.tets, ISO)
    around = np.flatnonzero(np.any(mesh.tets == 0, axis=1))  # every tetrahedron of vertex 0
    one = cut(model, around)
    two = cut(one, [int(np.setdiff1d(np.arange(mesh.n_tets), around)[0])])
    three = cut(two, [mesh.n_tets - 1])
    for m, gone in ((three, 3), (one, 1), (two, 2)):  # read out of order, after every cut
        removed = np.concatenate([around, np.setdiff1d(np.arange(mesh.n_tets), around)[:1], [mesh.n_tets - 1]][:gone])
        keep = np.setdiff1d(np.arange(mesh.n_tets), removed)
        assert np.array_equal(m.tets, mesh.tets[keep])
        fresh = build_model("linear-tm", mesh.points, mesh.tets[keep], ISO)
        used = np.unique(mesh.tets[keep])
        np.testing.assert_allclose(m.mass[used], fresh.mass[used], rtol=1e-12)
        assert m.mass[0] == 1.0 and np.all(m.loading.free[0] == 0.0)  # vertex 0 has no tetrahedron left


def test_corotational_refuses_fibres():
    mesh = cylinder()
    for material in (FIBRE, AROUND):
        with pytest.raises(ValueError, match="isotropic"):
            build_model("corotational-tm", mesh.points, mesh.tets, material)


@pytest.mark.parametrize("name", ["linear-tm", "stvk-tm"])
def test_fibres_around_an_axis_are_each_tetrahedron_s_own(name, rng):
    """A model whose fibres turn around an axis is, tetrahedron by tetrahedron, the model with one
    fibre direction: the one at that tetrahedron's centroid. Summing one-tetrahedron models of the
    constant-fibre law rebuilds the field model's force, which checks the kernels' per-element fibres
    (their block layout and Morton order) against the path that has one fibre for all."""
    mesh = structured_box([0.02, 0.02, 0.02], 2)
    model = build_model(name, mesh.points, mesh.tets, AROUND)
    u = 2e-3 * rng.standard_normal(mesh.points.shape)
    directions = AROUND.fiber_directions(mesh.points[mesh.tets].mean(axis=1))
    total = np.zeros_like(u)
    for tet, a in zip(mesh.tets, directions, strict=True):
        one = AROUND.replace(fiber_axis=None, fiber=tuple(a))
        total += build_model(name, mesh.points, tet[None], one).internal_force(u)
    # the same element integrals summed in another order: round-off
    assert np.linalg.norm(model.internal_force(u) - total) < 1e-12 * np.linalg.norm(total)


@pytest.mark.parametrize("name", ["precomputed", "condensed"])
def test_quasi_static_models_equal_the_static_linear_solution(name):
    """Cotin's superposition and Bro-Nielsen's condensation against a direct sparse solve of K u = f
    with the tool's dofs prescribed (a displacement load on surface vertices): precomputed at every
    vertex, condensed at the surface vertices, to 1e-8 (both are exact algebra: round-off)."""
    import scipy.sparse.linalg as spla

    from realtime.quasistatic import QuasiStatic
    from verification.inputs import build_loading
    from verification.scene_file import load_scene

    scene = load_scene("cantilever-pull").with_material(law="linear")
    mesh = scene.mesh
    loading = build_loading(mesh, scene.material.density, scene.problem)
    assert np.all(np.isin(loading.tool_vertex, mesh.surface_vertices))
    model = build_model(name, mesh.points, mesh.tets, scene.material, loading)
    u, reaction = QuasiStatic().equilibrium(model)
    K = model.extra["tensors"].matrix()
    held = loading.free.ravel() == 0.0
    exact = np.zeros(3 * mesh.n_vertices)
    prescribed = np.zeros((mesh.n_vertices, 3))
    prescribed[loading.tool_vertex] = model.tool_displacement(np.inf) * loading.tool_mask
    exact[held] = prescribed.ravel()[held]
    rhs = loading.external_force.ravel()[~held] - K[~held][:, held] @ exact[held]
    exact[~held] = spla.spsolve(K[~held][:, ~held].tocsc(), rhs)
    exact = exact.reshape(-1, 3)
    where = np.arange(mesh.n_vertices) if name == "precomputed" else mesh.surface_vertices
    assert np.linalg.norm(u[where] - exact[where]) / np.linalg.norm(exact[where]) < 1e-8
    assert np.linalg.norm(reaction - model.reaction(exact)) / np.linalg.norm(reaction) < 1e-8
    # the state a step leaves (condensed: the surface only, the interior at zero) gives the same
    # reaction through the model's own method (it was 586% off for condensed)
    state = State.at_rest(mesh.n_vertices)
    tools = QuasiStatic().step(model, state, 1e6, 1)  # past the ramp
    assert np.linalg.norm(model.reaction(state.u) - reaction) / np.linalg.norm(reaction) < 1e-8
    assert np.linalg.norm(tools.sum(axis=0) - reaction) / np.linalg.norm(reaction) < 1e-8  # what step returns


def test_precomputed_tool_force_equals_the_full_update():
    """The haptic one-vertex update gives the same force as the full superposition."""
    from realtime.quasistatic import Precomputed

    mesh = stored_mesh("beam")
    free = np.ones((mesh.n_vertices, 3))
    free[mesh.points[:, 0] < 1e-9] = 0.0
    from realtime import Loading

    model = build_model(
        "linear-tm",
        mesh.points,
        mesh.tets,
        ISO.replace(law="linear"),
        Loading(free=free, external_force=np.zeros_like(free)),
    )
    pc = Precomputed(model)
    k = int(mesh.surface_vertices[np.argmax(mesh.points[mesh.surface_vertices, 0])])
    d = np.array([0.0, 0.001, -0.002])
    _, F = pc.solve(3 * k + np.arange(3), d)
    np.testing.assert_allclose(pc.tool_force(k, d), F, rtol=1e-10)


#: The only array reads the force kernels may index with a signed integer: once per block of tetrahedra
#: (stvk-tm's material row) and twice per vertex row (linear-tm's row bounds), outside the loops over
#: edges and tetrahedra, whose every access takes an unsigned offset.
SIGNED_ALLOWED = {
    "linear-tm": {"for e in range(np.uint64(row_start[i]), np.uint64(row_start[i + 1])):"},
    "stvk-tm": {"stvk_block(W, geo, np.uint64(b) * GEO_ROWS_U, prm[b], False)"},
    "mass-spring": set(),
}


@pytest.mark.parametrize("model_name", sorted(SIGNED_ALLOWED))
def test_the_indexed_loops_index_with_unsigned_offsets(model_name):
    """The indexed loops (linear-tm's edges, the element kernels' gather and scatter, the springs) read
    flat views with unsigned offsets: numba wraps a signed index around when it is negative, at every
    access (an arithmetic shift, an and and an add on x86-64), which also lets a corrupt negative index
    read the array's far end instead of out of it. Read from numba's typed IR, the same on every
    machine; corotational-tm and hybrid-tm share stvk-tm's gather and scatter. make bench reports what
    the loops compile to on the machine it runs on (verification.bench.codegen)."""
    from verification.bench import codegen

    found = codegen.signed_indexing(codegen._force_kernel(model_name))
    unexpected = [line for line in found if line.split(": ", 1)[1] not in SIGNED_ALLOWED[model_name]]
    assert not unexpected, "a signed index in the force kernel: " + "; ".join(unexpected)


def test_the_signed_index_check_finds_a_signed_gather():
    """The check above can fail: a gather whose loop counter and index array are int64 is named, with its
    line's source; the same gather with uint64 ones is not."""
    import numba

    from verification.bench import codegen

    def signed_gather(a, idx):
        s = 0.0
        for k in range(idx.shape[0]):
            s += a[idx[k]]
        return s

    def unsigned_gather(a, idx):
        s = 0.0
        for k in range(np.uint64(idx.shape[0])):
            s += a[idx[k]]
        return s

    signed = numba.njit(cache=False)(signed_gather)
    signed(np.ones(4), np.arange(4, dtype=np.int64))
    assert [line.split(": ", 1)[1] for line in codegen.signed_indexing(signed)] == ["s += a[idx[k]]"]
    unsigned = numba.njit(cache=False)(unsigned_gather)
    unsigned(np.ones(4), np.arange(4, dtype=np.uint64))
    assert codegen.signed_indexing(unsigned) == []


def _corotational_force_by_svd(mesh, u):
    """The corotational force (N, 3) N at u (N, 3) m from numpy's SVD of every element's F, with the
    sign of the smallest singular direction flipped for inverted ones (R stays a rotation), and the
    rotated stress R sigma(sym(R^T F) - I) as SOFA writes it."""
    from realtime.geometry import shape_gradients

    g, vol = shape_gradients(mesh.points, mesh.tets)
    F = np.eye(3) + np.einsum("eai,eaj->eij", u[mesh.tets], g)
    U, _, Vt = np.linalg.svd(F)
    U[np.linalg.det(U) * np.linalg.det(Vt) < 0, :, 2] *= -1
    R = U @ Vt
    S = np.einsum("eki,ekj->eij", R, F) - np.eye(3)
    S = 0.5 * (S + S.transpose(0, 2, 1))
    sigma = 2 * ISO.mu * S + ISO.lam * np.trace(S, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    P = R @ sigma
    f = np.zeros_like(u)
    np.add.at(f, mesh.tets, -vol[:, None, None] * np.einsum("eij,eaj->eai", P, g))
    return f, F


@pytest.mark.parametrize("scale, bound", [(5e-3, 1e-13), (3e-4, 1e-13), (3e-5, 1e-12)])
def test_corotational_rotations_against_numpy_svd(scale, bound, rng):
    """The block kernel's polar rotations against numpy's SVD of every element's F. At 5e-3 m (half
    the edge length) some elements invert (the SVD, one element at a time); at 3e-4 m every block is
    strained beyond the bounded iteration's five steps and takes the adaptive one (Newton on the whole
    block, its last few unconverged lanes one at a time, stopping at |dR| < 1e-6, whose error is about
    its square); at 3e-5 m every block takes the bounded iteration, four or five steps counted before
    it starts (realtime.corotational.newton_gaps). The forces agree to round-off: the bound 1e-13 is
    about 500 eps, for sums over 2465 elements; at 3e-5 m the stress, of the size of F - R, is ten
    times smaller and the same round-off in R, numpy's SVD's included, ten times larger a part of it
    (1e-12). Measured 1.1e-14, 8e-14 and 1.3e-13 (the adaptive iteration: 4.3e-13 at 3e-5 m). A step
    too few would leave 1e-9 of R or more, 1e-6 of the force."""
    mesh = cylinder()
    model = build_model("corotational-tm", mesh.points, mesh.tets, ISO)
    u = scale * rng.standard_normal(mesh.points.shape)
    f, F = _corotational_force_by_svd(mesh, u)
    if scale > 1e-3:
        assert np.sum(np.linalg.det(F) <= 0) > 10  # the SVD path is exercised
    assert np.linalg.norm(model.internal_force(u) - f) / np.linalg.norm(f) < bound


def test_the_polar_iterations_step_count_is_what_the_iteration_takes():
    """newton_gaps's bounds, by the experiment that defines them: an F with one singular value at the
    end of the interval a gap allows (the worst case: the end farthest from 1 after the first step)
    reaches its rotation within tol in k unscaled steps for a gap just inside the k-step bound, and
    needs k + 1 just outside it. With one singular value off 1, the iterate's error |X - R|_F is that
    value's error alone; rotations on both sides, so that it is measured against numpy's SVD rather
    than read off a diagonal. The error after k steps goes as the gap to the power 2^(k - 1), so a
    margin of 0.1 / 2^(k - 1) of the gap moves it by about 10% of tol (5e-14), far above the
    rotations' round-off (1e-15)."""
    from realtime.corotational import _POLAR_GAPS, _POLAR_TOL, _unscaled_step

    rng = np.random.default_rng(3)
    q1, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q2, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q1 *= np.sign(np.linalg.det(q1))
    q2 *= np.sign(np.linalg.det(q2))
    R = q1 @ q2.T

    def steps_to_converge(s):
        x = tuple((q1 @ np.diag(s) @ q2.T).ravel())
        for k in range(1, 12):
            x = _unscaled_step(x)
            if np.linalg.norm(np.reshape(x, (3, 3)) - R) <= _POLAR_TOL:
                return k
        return None

    for k, gap in enumerate(_POLAR_GAPS, start=1):
        takes = []
        for margin in (-0.1 / 2 ** (k - 1), 0.1 / 2 ** (k - 1)):
            delta = math.sqrt(gap * (1 + margin))
            takes.append(max(steps_to_converge((math.sqrt(1 + sign * delta), 1.0, 1.0)) for sign in (-1, 1)))
        assert takes == [k, k + 1], (k, gap, takes)


@pytest.mark.parametrize(
    "stretches",
    [(1e3, 1.0, 1.0), (1e-6, 1.0, 1.0), (30.0, 0.05, 2.0), (1.0 + 1e-9, 1.0, 1.0 - 1e-9), (2.5, 0.4, 1.0)],
)
def test_corotational_polar_iteration_converges_at_extreme_stretches(stretches):
    """The polar iteration starts unscaled and scales only while a step changes R by more than 1
    (realtime.corotational): an element stretched a thousandfold, or squashed to a millionth of its
    volume but not inverted, must still reach numpy's SVD rotation within its 30 steps, and so must
    the strains a simulation meets. An affine displacement gives every element the same F = Q1
    diag(stretches) Q2^T (random rotations Q1, Q2). The force is compared in the norm of its terms
    (each vertex's forces from its elements), since an affine field's interior forces cancel. Measured
    4e-15 of that scale, 7e-14 at a stretch of 1e3 (F's own round-off, scaled by the stretch); an
    unscaled first step at a millionth of the volume gave 1.8e-12, above the bound of 1e-12."""
    from realtime.geometry import shape_gradients

    rng = np.random.default_rng(7)
    q1, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q2, _ = np.linalg.qr(rng.standard_normal((3, 3)))
    q1 *= np.sign(np.linalg.det(q1))
    q2 *= np.sign(np.linalg.det(q2))
    Fa = q1 @ np.diag(stretches) @ q2.T
    mesh = cylinder()
    model = build_model("corotational-tm", mesh.points, mesh.tets, ISO)
    u = mesh.points @ (Fa - np.eye(3)).T
    f, F = _corotational_force_by_svd(mesh, u)
    assert np.allclose(F, Fa, rtol=0, atol=1e-9 * max(stretches))
    g, vol = shape_gradients(mesh.points, mesh.tets)
    scale = np.abs(vol).max() * np.abs(g).max() * ISO.lam * max(stretches)
    assert np.abs(model.internal_force(u) - f).max() < 1e-12 * scale


def test_the_engines_numba_cache_is_cleared_when_any_of_its_sources_changes(tmp_path):
    """numba checks a cached function against its own file only; the step loops take the kernels as
    arguments, so their index kept one pickled copy of every version of every kernel (59 after a few
    edits) and saving it then failed with "underlying object has vanished". The engine's cache files
    are kept under a stamp of all its sources: a change anywhere clears them, and nothing else."""
    from realtime import jitcache

    src = tmp_path / "src"
    src.mkdir()
    kernel = src / "kernel.py"
    kernel.write_text("x = 1\n")
    cache = tmp_path / "cache"
    assert not jitcache.clear_if_stale(cache, [kernel])  # first use: stamped, nothing to clear
    for name in ("steppers.run-10.py311.nbi", "steppers.run-10.py311.1.nbc", "other.txt"):
        (cache / name).write_text("compiled")
    assert not jitcache.clear_if_stale(cache, [kernel])  # same sources: kept
    files = lambda: sorted(p.name for p in cache.iterdir() if p.name != jitcache.LOCK)  # noqa: E731
    assert len(files()) == 4
    kernel.write_text("x = 2\n")
    assert jitcache.clear_if_stale(cache, [kernel])
    assert files() == ["other.txt", jitcache.STAMP]
    # importing the engine stamps the directory numba caches its step loops in
    import realtime  # noqa: F401
    from realtime.steppers import _run_symplectic_euler

    stamp = Path(_run_symplectic_euler._cache.cache_path) / jitcache.STAMP
    sources = sorted(Path(jitcache.__file__).parent.glob("*.py"))
    assert stamp.read_text() == jitcache.sources_digest(sources)


def test_a_cache_index_numba_cannot_pickle_again_costs_the_caching_not_the_run():
    """Two processes sharing the cache (the report's settling workers) met numba's "underlying object has
    vanished" when saving a step loop's index that the other had written. Such a save is skipped: the
    function compiles and runs. Without the guard the same save fails the call (checked)."""
    import numba as nb

    from realtime import jitcache
    from realtime.steppers import _run_symplectic_euler

    assert _run_symplectic_euler._cache.save_overload.tolerates_vanished  # the engine's functions are guarded

    def vanished(sig, data):
        raise ReferenceError("underlying object has vanished")

    for guarded in (False, True):
        f = nb.njit(cache=True)(lambda x: x + 1)
        f._cache._save_overload = vanished
        if guarded:
            jitcache.tolerate_vanished(f)
            assert f(1) == 2
        else:
            with pytest.raises(ReferenceError):
                f(1)


_STEP_IN_A_FRESH_PROCESS = """
import json
import numpy as np
from meshes import structured_box
from realtime import Material, State, SymplecticEuler, build_model
from realtime.steppers import _run_symplectic_euler, step_work
mesh = structured_box((0.02, 0.01, 0.01), (2, 1, 1))
model = build_model("linear-tm", mesh.points, mesh.tets, Material(young=3e3, poisson=0.3, density=1e3))
SymplecticEuler(alpha=1.0).step(model, State.at_rest(mesh.n_vertices), 1e-5, 3)
counts = [(sum(f.stats.cache_hits.values()), sum(f.stats.cache_misses.values()))
          for f in (_run_symplectic_euler, step_work)]
print(json.dumps(counts))
"""


@pytest.mark.slow
def test_a_step_loop_compiled_in_one_process_is_loaded_from_the_cache_in_the_next():
    """A step loop takes the model's kernel as an argument, and its cached specialisation is keyed by
    that kernel's dispatcher, which numba pickles under an identity of its own. With numba's random
    identities no process found another's step loops: the report's main process compiled them again in
    every run (16 s of its cantilever section) and so did every settling worker. The engine's functions
    now carry identities drawn from their names (jitcache.stable_identities): a second process loads the
    step loop the first one compiled, and the constructor of the workspace object it takes."""
    import json
    import subprocess
    import sys

    runs = []
    for _ in range(2):  # in the suite's numba cache: an empty one would cost the test 50 s of compiling
        out = subprocess.run(
            [sys.executable, "-c", _STEP_IN_A_FRESH_PROCESS], capture_output=True, text=True, check=True
        )
        runs.append(json.loads(out.stdout.strip().splitlines()[-1]))
    assert [sum(c) for c in runs[0]] == [1, 1]  # the first compiled each and saved it, or loaded it
    assert runs[1] == [[1, 0], [1, 0]]  # the second loaded both: the loop and its workspace's constructor


@pytest.mark.parametrize("model_name", ["linear-tm", "stvk-tm", "corotational-tm", "mass-spring"])
def test_a_model_on_the_renumbered_mesh_is_the_same_model(model_name, rng):
    """realtime.renumber changes only the numbers: the force at the same displacement is the same
    vector at every vertex (to the round-off of a different order of the sums: 64 machine epsilons of
    the largest force), the energy the same (a sum of 6249 element terms in another order: 1e-12, under
    the 6249 eps that bound its round-off) and the lumped masses (each a sum of a few dozen terms in
    another order: 1e-14, about 45 eps)."""
    from realtime import renumber

    mesh = stored_mesh("liver")
    mat = Material(2.8e4, 0.45, 1000.0, law="stvk")
    points, tets, order = renumber(mesh.points, mesh.tets)
    old = build_model(model_name, mesh.points, mesh.tets, mat)
    new = build_model(model_name, points, tets, mat)
    u = 3e-3 * rng.standard_normal(mesh.points.shape)
    f_old, f_new = old.internal_force(u), new.internal_force(u[order])
    assert np.abs(f_new - f_old[order]).max() <= 64 * np.finfo(float).eps * np.abs(f_old).max()
    assert new.elastic_energy(u[order]) == pytest.approx(old.elastic_energy(u), rel=1e-12)
    assert np.allclose(new.mass, old.mass[order], rtol=1e-14, atol=0.0)  # the same lumped masses


@pytest.mark.parametrize("name", [m for m in MODELS if SPECS[m].mechanics and not SPECS[m].quasi_static])
def test_what_a_model_claims_to_represent_changes_its_force_and_nothing_else_does(name):
    """A spec's ``represents`` (realtime.models) is what every result says a model ran without: checked here by the
    force itself. At a compressed, sheared state, adding the volume penalty (or fibres) to the material
    changes the force of a model that claims the term and leaves it bit for bit the same in one that
    does not (the quasi-static models are linear-tm's tensors). corotational-tm and neohookean-tm refuse
    fibres."""
    from realtime.models import unrepresented

    mesh = structured_box((0.02, 0.01, 0.01), (2, 1, 1))
    x = mesh.points
    u = np.column_stack([-0.05 * x[:, 0] + 0.02 * x[:, 1], -0.03 * x[:, 1], 0.01 * x[:, 0]])
    base = Material(1e4, 0.3, 1000.0, law="stvk")
    variants = {
        "penalty": dataclasses.replace(base, volume_penalty=5e4),
        "fibres": dataclasses.replace(base, fiber=(1.0, 0.0, 0.0), young_fiber=6e4),
    }
    f0 = build_model(name, mesh.points, mesh.tets, base).internal_force(u)
    for term, material in variants.items():
        if term == "fibres" and name in ("corotational-tm", "neohookean-tm"):  # they refuse fibres at build
            with pytest.raises(InputError, match="isotropic materials only"):
                build_model(name, mesh.points, mesh.tets, material)
            continue
        f = build_model(name, mesh.points, mesh.tets, material).internal_force(u)
        claimed = term in SPECS[name].represents
        assert (not np.array_equal(f, f0)) == claimed, f"{name}: {term} claimed {claimed}"
        assert bool(unrepresented(name, material)) == (not claimed)
