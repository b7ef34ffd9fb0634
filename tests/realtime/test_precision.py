"""The float32 path (build_model's ``precision``): what it computes in, how far it lies from float64, and
what it refuses (docs/engine-internals.md)."""

import dataclasses
import re

import numba as nb
import numpy as np
import pytest

from meshes import stored_mesh, structured_box
from realtime import MODELS, InputError, Material, State, build_model, make_integrator
from realtime.blocks import HOT
from realtime.model import Loading
from realtime.models import SPECS
from realtime.models.linear_tm import cut

FLOAT32_MODELS = [s.name for s in SPECS.values() if s.float32]

#: float32's unit round-off, 2^-24 (numpy's eps is 2^-23, the spacing at 1).
U32 = 2.0**-24
MATERIAL = Material(3.0e3, 0.45, 1000.0, law="stvk", volume_penalty=1.0e3)


def beam():
    """A 10 cm beam of 10 x 2 x 2 cubes, clamped at x = 0, loaded by gravity."""
    mesh = structured_box((0.1, 0.02, 0.02), (10, 2, 2))
    free = np.ones((mesh.n_vertices, 3))
    free[mesh.points[:, 0] < 1e-9] = 0.0
    gravity = np.zeros((mesh.n_vertices, 3))
    gravity[:, 2] = -9.81 * 1000.0 * 0.1 * 0.02 * 0.02 / mesh.n_vertices
    return mesh, Loading(free=free, external_force=gravity)


@pytest.mark.parametrize("name", FLOAT32_MODELS)
@pytest.mark.parametrize("strain", [1e-4, 0.1])
def test_a_float32_force_lies_within_a_few_round_offs_of_float64(name, strain, rng):
    """The force of a float32 model at a displacement float32 holds exactly, against float64's.

    Each kernel forms the differences u_j - u_i first (and J - 1 from them, and a spring's stretch):
    every quantity then carries a few rounding errors relative to itself, so the force does too,
    whatever the strain. Bound: 16 u (the rounded data, about ten operations per term, and sums of
    up to twenty terms at a vertex, which mostly cancel in the norm). The kernels that formed
    det F - 1 and |X_j + u_j - X_i - u_i| - L lost digits to cancellation as the strain fell: 1.6e-5
    and 1.2e-3 at a strain of 1e-3 on this mesh, 130 u and 1e4 u. The one that formed K u from vertex
    tensors lost them as u grew smooth, not small: 4e-7 here (the noise keeps K u large), 2.9e-5 in
    a run (test_a_float32_run_follows_the_float64_run).
    """
    mesh = stored_mesh("cylinder")
    size = float(np.ptp(mesh.points, axis=0).max())
    smooth = mesh.points @ np.array([[0.3, -0.2, 0.1], [0.2, 0.4, -0.3], [-0.1, 0.3, 0.5]])
    noise = 0.05 * size * rng.standard_normal(mesh.points.shape)
    model = build_model(name, mesh.points, mesh.tets, MATERIAL)
    # at a strain of 0.1 the noise inverts two tetrahedra, where a law with no value there (neo-Hookean)
    # has no force: for it, the noise is halved until none inverts
    while not np.isfinite(model.elastic_energy(strain * (smooth + noise))):
        noise *= 0.5
    u = (strain * (smooth + noise)).astype(np.float32).astype(np.float64)
    f64 = model.internal_force(u)
    f32 = build_model(name, mesh.points, mesh.tets, MATERIAL, precision="float32").internal_force(u)
    assert f32.dtype == np.float32
    assert np.linalg.norm(f32 - f64) <= 16 * U32 * np.linalg.norm(f64)


@pytest.mark.parametrize("name", FLOAT32_MODELS)
def test_a_float32_models_energy_is_its_float64_energy_to_round_off(name, rng):
    """Model.elastic_energy of a float32 model: the energy kernel reads the float32 data and sums in
    float64. stvk-tm's failed to compile at all (a float32 fibre met a float64 strain in laws.stvk_energy's
    E @ a, a numba TypingError), found by the API fuzz on float32 models. At a displacement float32
    holds exactly, the only differences are the data's rounding to float32, and every term of the sum
    is non-negative, so the total's relative error is at most the largest term's: its coefficient and
    volume (1 u each) and the two rounded geometric factors of its quadratic form (2 u). Bound 4 u;
    measured at most 0.11 u on three draws (the terms' roundings do not align)."""
    mesh = stored_mesh("cylinder")
    fibred = Material(3.0e3, 0.45, 1000.0, law="stvk", fiber=(0.0, 0.0, 1.0), young_fiber=9e3, volume_penalty=1e3)
    u = (1e-3 * float(np.ptp(mesh.points)) * rng.standard_normal(mesh.points.shape)).astype(np.float32)
    if "fibres" not in SPECS[name].represents:  # neohookean-tm refuses them; mass-spring has no use for them
        fibred = dataclasses.replace(fibred, fiber=None, young_fiber=None)
    for material in (MATERIAL, fibred):
        e64 = build_model(name, mesh.points, mesh.tets, material).elastic_energy(u)
        e32 = build_model(name, mesh.points, mesh.tets, material, precision="float32").elastic_energy(u)
        assert e64 > 0.0 and abs(e32 - e64) <= 4 * U32 * e64


@pytest.mark.parametrize("name", FLOAT32_MODELS)
def test_a_translation_gives_exactly_no_force(name, rng):
    """Differences first: a rigid translation's differences are exact zeros in either precision, and
    so is the force (the vertex-tensor form left round-off of |K| |u| behind)."""
    mesh = stored_mesh("cylinder")
    for precision in ("float64", "float32"):
        model = build_model(name, mesh.points, mesh.tets, MATERIAL, precision=precision)
        u = np.broadcast_to(rng.standard_normal(3) * 1e-2, mesh.points.shape)
        assert np.all(model.internal_force(u) == 0.0), precision


@pytest.mark.parametrize("name", FLOAT32_MODELS)
def test_a_float32_kernel_computes_in_float32(name):
    """No double-precision arithmetic and no widening in the float32 kernel: numba types a literal as
    float64, so a constant written as 0.5 in a kernel would widen every product with it. The kernel is
    compiled afresh (cached code cannot be inspected)."""
    mesh = structured_box((0.02, 0.02, 0.02), (2, 2, 2))
    model = build_model(name, mesh.points, mesh.tets, MATERIAL, precision="float32")
    fresh = nb.njit(**{**HOT, "cache": False})(model.force_kernel.py_func)
    u = np.zeros((mesh.n_vertices, 3), np.float32)
    fresh(model.data, model.new_scratch(), u, np.empty_like(u))
    ir = fresh.inspect_llvm(fresh.signatures[0])
    assert not re.findall(r"= f(?:add|sub|mul|div)\b[^\n]*\bdouble\b", ir)
    assert "fpext" not in ir
    assert re.search(r"= f(?:add|sub|mul)\b[^\n]*\bfloat\b", ir)


@pytest.mark.parametrize("name", FLOAT32_MODELS)
@pytest.mark.parametrize("integrator", ["symplectic-euler", "central-difference"])
def test_a_float32_run_follows_the_float64_run(name, integrator):
    """3000 steps of a clamped beam sagging under gravity, lightly damped, float32 against float64. The
    state stays float32. Measured: stvk-tm and mass-spring 1e-7 to 1.7e-7, a few u (each step rounds
    u, v and f, and damping forgets old errors); linear-tm 4.2e-6, which is what rounding its
    assembled edge tensors to float32 does to the beam's static solution (4.4e-6, solved exactly with
    the rounded tensors): an entrywise rounding of K moves the soft modes by about u |K| / lambda_min,
    where rounding each element's geometry moves each element's energy by a relative u. Bound 1e-5,
    above linear-tm's operator rounding; the vertex-tensor kernel gave 2.9e-5 on a cube."""
    mesh, loading = beam()
    out = {}
    for precision in ("float64", "float32"):
        model = build_model(name, mesh.points, mesh.tets, MATERIAL, loading, precision=precision)
        integ = make_integrator(integrator, alpha=20.0)
        state = model.rest_state()
        integ.step(model, state, 0.5 * integ.critical_dt(model), 3000)
        assert state.u.dtype == state.v.dtype == model.dtype
        out[precision] = state.u.astype(np.float64)
    assert np.linalg.norm(out["float32"] - out["float64"]) <= 1e-5 * np.linalg.norm(out["float64"])


def test_a_threaded_float32_model_matches_its_serial_kernel(rng):
    """Two threads, float32: the same force as one thread's to the order of the sums (8 u)."""
    mesh = stored_mesh("cylinder")
    u = 1e-3 * rng.standard_normal(mesh.points.shape)
    for name in ("linear-tm", "stvk-tm"):
        one = build_model(name, mesh.points, mesh.tets, MATERIAL, precision="float32").internal_force(u)
        two = build_model(name, mesh.points, mesh.tets, MATERIAL, precision="float32", threads=2).internal_force(u)
        assert two.dtype == np.float32
        assert np.linalg.norm(two - one) <= 8 * U32 * np.linalg.norm(one)


def test_what_float32_refuses_is_a_one_line_error():
    mesh, loading = beam()
    for name in MODELS:
        if name not in FLOAT32_MODELS:
            with pytest.raises(InputError, match=f"precision = 'float32': {name} runs in float64 only"):
                build_model(name, mesh.points, mesh.tets, MATERIAL, loading, precision="float32")
    with pytest.raises(InputError, match="precision = 'float16': must be one of float64, float32"):
        build_model("stvk-tm", mesh.points, mesh.tets, MATERIAL, loading, precision="float16")
    model = build_model("linear-tm", mesh.points, mesh.tets, MATERIAL, loading, precision="float32")
    n = mesh.n_vertices
    with pytest.raises(InputError, match=rf"State.u: must be .* \({n}, 3\) float32 array, got a \({n}, 3\) float64"):
        make_integrator("symplectic-euler").step(model, State.at_rest(n), 1e-5)
    with pytest.raises(InputError, match="implicit-euler: linear-tm was built with precision = 'float32'"):
        make_integrator("implicit-euler").step(model, model.rest_state(), 1e-5)
    with pytest.raises(InputError, match="cut: linear-tm was built with precision = 'float32'"):
        cut(model, [0])
