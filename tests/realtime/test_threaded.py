"""The threaded force kernels (realtime.threaded): the serial kernels' forces, split over threads.

Each threaded model is held to its serial twin on a two-material liver with fibres and the volume
penalty: forces, energies and a trajectory agree to round-off (the order of the sums is the only
difference: 64 machine epsilons of the largest force, since a vertex sums at most a few dozen
contributions of either sign), and every call gives the same bits. Their speed is `make bench`'s.
"""

from __future__ import annotations

import numpy as np
import pytest

from meshes import stored_mesh
from realtime import InputError, Loading, Material, Materials, State, SymplecticEuler, build_model
from realtime.threaded import balanced_chunks, check_threading, row_chunks
from realtime.topology import slit, suture

from ..conftest import assert_same_model
from .test_slit_and_suture import block, slit_faces

EPS = np.finfo(float).eps
THREADED_MODELS = ("linear-tm", "stvk-tm", "corotational-tm")


def _liver_materials(mesh, transverse: bool) -> Materials:
    """The liver's tetrahedra above its mean height in a stiffer, denser material."""
    soft = Material(2.8e4, 0.4, 1000.0, law="stvk")
    if transverse:
        soft = Material(2.8e4, 0.4, 1000.0, law="stvk", fiber=(1.0, 0.0, 0.0), young_fiber=6e4, volume_penalty=5e4)
    stiff = Material(2.8e5, 0.45, 1100.0, law="stvk")
    z = mesh.points[mesh.tets].mean(axis=1)[:, 2]
    return Materials((soft, stiff), (z > z.mean()).astype(np.int64))


@pytest.mark.parametrize("threads", [2, 3])
@pytest.mark.parametrize("model_name", THREADED_MODELS)
def test_threaded_forces_equal_the_serial_kernels_to_round_off(model_name, threads, rng):
    mesh = stored_mesh("liver")
    mats = _liver_materials(mesh, transverse=model_name != "corotational-tm")
    serial = build_model(model_name, mesh.points, mesh.tets, mats)
    threaded = build_model(model_name, mesh.points, mesh.tets, mats, threads=threads)
    assert threaded.force_kernel is not serial.force_kernel  # the threaded kernel, not the serial one again
    assert threaded.extra["threads"] == threads
    for scale in (1e-4, 3e-3):  # small and large (non-linear) displacements
        u = scale * rng.standard_normal(mesh.points.shape)
        fs, ft = serial.internal_force(u), threaded.internal_force(u)
        assert np.abs(ft - fs).max() <= 64 * EPS * np.abs(fs).max()
        assert not np.array_equal(ft, np.zeros_like(ft))
        assert np.array_equal(threaded.internal_force(u), ft)  # the same bits every call
        assert threaded.elastic_energy(u) == serial.elastic_energy(u)


@pytest.mark.parametrize("model_name", THREADED_MODELS)
def test_a_threaded_trajectory_follows_the_serial_one(model_name):
    """200 symplectic Euler steps of the liver held at its base under gravity: the threaded run stays
    within round-off of the serial one (the differences grow with the steps, 1e-12 of the motion)."""
    mesh = stored_mesh("liver")
    n = mesh.n_vertices
    free = np.ones((n, 3))
    free[mesh.points[:, 2] < mesh.points[:, 2].min() + 0.01] = 0.0
    mat = Material(2.8e4, 0.4, 1000.0, law="stvk")
    ends = []
    for threads in (1, 2):
        model = build_model(
            model_name,
            mesh.points,
            mesh.tets,
            mat,
            Loading(free=free, external_force=np.zeros((n, 3))),
            threads=threads,
        )
        integ = SymplecticEuler(alpha=20.0)
        integ.set_forces(model, model.mass[:, None] * np.array([0.0, 0.0, -9.81]))
        state = State.at_rest(n)
        integ.step(model, state, 0.5 * integ.critical_dt(model), 200)
        ends.append(state.u)
    assert np.abs(ends[0]).max() > 0
    assert np.abs(ends[1] - ends[0]).max() <= 1e-12 * np.abs(ends[0]).max()


def test_a_slit_and_sutured_threaded_model_stays_threaded_and_equals_the_serial_one(rng):
    """slit adds vertices, so the threaded kernel's rows and per-thread force arrays are laid out again:
    the slit model keeps its threads and equals the serial slit model; suturing returns the original."""
    mesh, materials, loading = block()
    serial = build_model("linear-tm", mesh.points, mesh.tets, materials, loading)
    threaded = build_model("linear-tm", mesh.points, mesh.tets, materials, loading, threads=2)
    slit_s, pairs_s = slit(serial, slit_faces(mesh))
    slit_t, pairs_t = slit(threaded, slit_faces(mesh))
    assert np.array_equal(pairs_s, pairs_t)
    assert slit_t.extra["threads"] == 2 and slit_t.force_kernel is threaded.force_kernel
    u = 1e-3 * rng.standard_normal(slit_s.points.shape)
    fs, ft = slit_s.internal_force(u), slit_t.internal_force(u)
    assert np.abs(ft - fs).max() <= 64 * EPS * np.abs(fs).max()
    back = suture(slit_t, pairs_t)
    assert back.extra["threads"] == 2
    assert_same_model(back, build_model("linear-tm", mesh.points, mesh.tets, materials, loading, threads=2), rng)


def test_chunks_split_the_work_evenly_and_cover_it_once():
    cost = np.random.default_rng(1).integers(1, 20, 1000).astype(float)
    for t in (1, 2, 3, 7):
        c = balanced_chunks(cost, t)
        assert c[0] == 0 and c[-1] == len(cost) and len(c) == t + 1 and np.all(np.diff(c) >= 0)
        shares = np.add.reduceat(cost, c[:-1]) if t > 1 else np.array([cost.sum()])
        assert shares.max() - shares.min() <= 2 * cost.max()  # one unit either side of the even split
    assert len(balanced_chunks(np.ones(2), 8)) == 3  # never more threads than units
    rows = row_chunks(np.array([0, 10, 10, 10, 10, 10]), 2)
    assert list(rows) == [0, 1, 5]  # the first row's ten edges are half the work


def test_two_threads_split_the_sum_and_update_where_their_costs_are_equal():
    """threaded.thread_range cuts two threads' components where each does as much work, a component
    costing one pass and one more read where both spans hold it, and the cut lies inside the spans'
    overlap, so that each reads the other's forces there alone; spans that do not overlap are cut in
    the gap between them. The middle of the overlap, the rule before, failed the first case (liver-x10
    renumbered, linear-tm's spans: 26 432 against 17 788 units). Tolerance: the cut is rounded to a
    cache line, 8 components, each worth at most 2 units."""
    from realtime.threaded import thread_range

    def cost(spans, lo, hi):
        both = max(0, min(hi, 3 * spans[0, 1]) - max(lo, 3 * spans[1, 0]))
        return hi - lo + both

    for spans, n in (
        ([[0, 8811], [5358, 11287]], 3 * 11287),  # linear-tm's on liver-x10 renumbered
        ([[0, 6410], [4996, 11287]], 3 * 11287),  # stvk-tm's
        ([[0, 300], [0, 300]], 900),  # both threads everywhere
        ([[0, 10], [5, 300]], 900),  # an overlap far from the middle
    ):
        spans = np.array(spans)
        (lo0, mid), (mid1, hi1) = (thread_range(spans, n, p, 2) for p in (0, 1))
        assert lo0 == 0 and mid == mid1 and hi1 == n
        assert 3 * spans[1, 0] <= mid <= 3 * spans[0, 1]
        balanced = abs(cost(spans, 0, mid) - cost(spans, mid, n)) <= 2 * 2 * 8
        assert balanced or mid in (3 * spans[1, 0], 3 * spans[0, 1])  # or as near it as the overlap allows
    apart = np.array([[0, 100], [150, 300]])
    assert thread_range(apart, 900, 0, 2) == (0, 448) and thread_range(apart, 900, 1, 2) == (448, 900)
    assert thread_range(apart, 900, 1, 3) == (300, 600)  # three parts: equal ranges


@pytest.mark.parametrize("bad", [0, -1, 1.5, "2", True])
def test_a_bad_thread_count_is_a_one_line_error(bad):
    mesh = stored_mesh("beam")
    with pytest.raises(InputError, match=r"^threads = .*integer >= 1$"):
        build_model("stvk-tm", mesh.points, mesh.tets, Material(1e4, 0.3, 1000.0), threads=bad)


def test_the_threads_run_in_a_layer_two_python_threads_may_enter_at_once():
    """numba's own workqueue layer aborts the process when two Python threads launch parallel kernels
    at once (a haptic and a visual loop); the threaded kernels run in GNU OpenMP (TBB would be safe too,
    but its threads slept between steps), with the spin count the engine sets before OpenMP loads."""
    import os

    assert check_threading() == "omp"
    assert int(os.environ["GOMP_SPINCOUNT"]) >= 1_000_000


def test_threads_on_tbb_say_once_that_they_gain_nothing():
    """Without GNU OpenMP the threaded kernels fall back to TBB, whose threads sleep between steps (no
    speed-up on liver-x10): threads > 1 are still accepted, and one RuntimeWarning, once a process, says
    why and what to install. In a process of its own: numba keeps the first layer it starts, and this
    one has OpenMP's. TBB is there on every machine make test installs (gmsh's OpenCascade depends on
    Debian's libtbb12)."""
    import subprocess
    import sys

    code = (
        "import numba\n"
        "from realtime import threaded\n"
        "threaded.THREADING_LAYERS = ('tbb',)\n"
        "for _ in range(2):\n"
        "    print(threaded.check_threads(2), numba.threading_layer())\n"
    )
    run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert run.returncode == 0, run.stderr
    assert run.stdout.split() == ["2", "tbb", "2", "tbb"]
    said = [line for line in run.stderr.splitlines() if "RuntimeWarning" in line]
    assert len(said) == 1 and "tbb threading layer" in said[0] and "libgomp1" in said[0]


@pytest.mark.parametrize("threads", [2, 3])
@pytest.mark.parametrize("parts", [1, 2, 3])
def test_the_threaded_update_sums_the_threads_forces_with_the_serial_updates_bits(threads, parts):
    """Symplectic Euler's update of a threaded model (steppers.se_sum_update_threads) adds the threads'
    forces F (T, N + pad, 3) as it updates, each thread a range of the components, each F[t] read
    inside its span alone. It must write the force threaded.sum_threads writes and update every
    component exactly as the serial update does after that sum (the same arithmetic on each number:
    equal bits), and count the same components past the bound, NaN included; a range left out or run
    twice would show as a difference. The spans overlap, leave vertices to one thread or to none (a
    vertex of no tetrahedron), and F holds numbers outside them, which neither sum may read. Two
    threads sum their spans' pieces (two_span_cuts), three each span in turn; 3 parts on 2 cores
    checks that the ranges do not depend on the thread count."""
    from realtime.steppers import se_sum_update_threads, se_update
    from realtime.threaded import sum_threads

    rng = np.random.default_rng(3)
    n = 1001
    F = rng.standard_normal((threads, n + 5, 3))
    spans = np.array([[0, 600], [450, 990], [300, 700]])[:threads]  # 990 .. 1000 in no span
    inside = np.zeros((threads, n, 3), bool)
    for t, (a, b) in enumerate(spans):
        inside[t, a:b] = True
    per_dof = np.abs(rng.standard_normal((3 * n, 2)))
    per_dof[::7, :] = 0.0  # constrained components
    u, v = rng.standard_normal(3 * n), rng.standard_normal(3 * n)
    u[5], F[0, 3, 2] = np.nan, 1e12  # one NaN, one past the bound after the step (component 11)
    summed = np.empty((n, 3))
    sum_threads(spans, F, summed)
    expected = np.zeros((n, 3))
    for t in range(threads):
        expected = expected + np.where(inside[t], F[t, :n], 0.0)
    assert np.array_equal(summed, expected)
    serial = [u.copy(), v.copy()]
    threaded = [u.copy(), v.copy()]
    f = np.full(3 * n, np.nan)
    out_serial = se_update(per_dof.reshape(-1), (), *serial, summed.reshape(-1), 1e-3, 0.99, 1e3, 1)
    out_threaded = se_sum_update_threads(per_dof.reshape(-1), (spans, F), *threaded, f, 1e-3, 0.99, 1e3, parts)
    assert out_serial == out_threaded == 2
    assert np.array_equal(f, summed.reshape(-1))
    for a, b in zip(serial, threaded, strict=True):
        assert np.array_equal(a, b, equal_nan=True)
    assert not np.array_equal(serial[0], u, equal_nan=True)  # the update did something
    held = slice(0, None, 7)  # the constrained components: v = 0, u where it was
    assert np.array_equal(serial[0][held], u[held], equal_nan=True)
    assert not serial[1][held].any()


@pytest.mark.parametrize("model_name", THREADED_MODELS)
def test_each_thread_writes_forces_inside_its_span_alone(model_name, rng):
    """A threaded kernel's chunk zeroes its force array inside its span only and the sums read it
    there only (threaded.force_spans): a write outside would be added to nothing and kept to the next
    step. Every F[t] starts filled with NaN; after a force the NaN outside the span are untouched and
    none is left inside, and the force equals the serial one. On the liver numbered along the body the
    two spans of an element model overlap on little more than the interface of the two chunks (the
    vertices both hold): the numbering puts the interface of the mesh's two halves between the halves'
    own vertices, and the chunks, whole blocks, differ from the halves by the corners of fewer than a
    block of tetrahedra."""
    from realtime.blocks import BLOCK
    from realtime.threaded import UNSUMMED

    mesh = stored_mesh("liver-renumbered")
    mat = Material(2.8e4, 0.4, 1000.0, law="stvk")
    serial = build_model(model_name, mesh.points, mesh.tets, mat)
    threaded = build_model(model_name, mesh.points, mesh.tets, mat, threads=2)
    scratch = threaded.new_scratch()
    spans, F = scratch[-2], scratch[-1]
    F[:] = np.nan
    u = 1e-4 * rng.standard_normal(mesh.points.shape)
    f = np.zeros_like(u)
    UNSUMMED[threaded.force_kernel.__name__](threaded.data, scratch, u, f)
    for t, (a, b) in enumerate(spans):
        assert not np.isnan(F[t, a:b]).any()
        assert np.isnan(F[t, :a]).all() and np.isnan(F[t, b:]).all()
    threaded.force_kernel(threaded.data, scratch, u, f)
    fs = serial.internal_force(u)
    assert np.abs(f - fs).max() <= 64 * EPS * np.abs(fs).max()
    if model_name != "linear-tm":
        tets, split = threaded.data.data.tets, BLOCK * threaded.data.chunks[1]
        interface = np.intersect1d(tets[:split], tets[split:])
        assert spans[1, 0] <= interface.min() and interface.max() < spans[0, 1]
        halves = np.intersect1d(mesh.tets[: -(-len(mesh.tets) // 2)], mesh.tets[-(-len(mesh.tets) // 2) :])
        between = abs(split - -(-len(mesh.tets) // 2))
        assert between < BLOCK
        assert spans[0, 1] - spans[1, 0] <= len(halves) + 4 * between


def test_the_threads_forces_are_summed_piece_by_piece():
    """The sum of two threads' forces (threaded.sum_range, each piece between the spans' ends a plain
    loop: one span alone, both, the other alone) adds each component once per span that holds it. How
    many packed additions it compiles to is reported by make bench (verification.bench.codegen)."""
    from realtime import threaded

    F, f = np.ones((2, 900)), np.zeros(900)
    spans = np.array([[0, 200], [150, 300]])
    threaded.sum_range(spans, F, f, 0, 900)
    assert np.array_equal(f, np.r_[np.ones(450), 2 * np.ones(150), np.ones(300)])
