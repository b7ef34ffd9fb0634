"""The benchmark's machinery (never its speed: `make bench` reports that): the roofline it measures and
the table it prints."""

import re

import numpy as np
import pytest


def test_the_compiled_code_report_counts_what_it_names():
    """make bench reports what the hot loops compile to (verification.bench.codegen), since the counts differ
    by target. Its patterns must count packed double instructions on 256- and 512-bit registers and
    nothing scalar or single-precision: lines as LLVM prints them for AVX2 and AVX-512."""
    from verification.bench import codegen

    asm = """
        vfmadd231pd	%zmm1, %zmm2, %zmm3
        vfmadd213pd	(%rax), %ymm4, %ymm5
        vfmadd231sd	%xmm1, %xmm2, %xmm3
        vfmadd231ps	%ymm1, %ymm2, %ymm3
        vaddpd	%ymm0, %ymm1, %ymm1
        vaddsd	%xmm0, %xmm1, %xmm1
        vmovupd	%zmm0, 64(%rdi)
        sarq	$63, %rcx
        sarq	$3, %rcx
        imulq	%rdx, %rcx
    """
    assert codegen._count(codegen.PACKED_FMA, asm) == 2
    assert codegen._count(codegen.PACKED_ADD, asm) == 1
    assert codegen._count(codegen.PACKED, asm) == 4
    assert codegen._count(codegen.SIGN_SHIFT, asm) == 1
    assert codegen._count(codegen.STRIDE_MUL, asm) == 1


@pytest.mark.parametrize("parts", [1, 2, 3])
def test_the_threaded_ceiling_loops_do_all_of_the_one_thread_loops_work(parts):
    """thread_loops times the ceilings' loops on one thread and on several: the threaded triad must
    write every element (a slice left out or run twice would show: n is not a multiple of the parts)
    and the threaded FMA loop must run every thread's chains (its sum is T times one thread's)."""
    from verification.bench import roofline

    n = 1001
    b, c = np.arange(n, dtype=float), np.full(n, 3.0)
    a = np.zeros(n)
    roofline._triad_threads(a, b, c, 0.5, 2, parts)
    assert np.array_equal(a, b + 0.5 * c)
    x = np.full((parts, roofline._CHAINS, 64), 0.5)
    assert roofline._polynomials_threads(x, 2) == pytest.approx(parts * roofline._polynomials(x[0], 2), rel=1e-15)


@pytest.mark.slow
def test_the_benchmark_places_every_fixed_work_row_on_the_roofline():
    """A short benchmark on the stored beam: the rows whose work is a fixed count (linear-tm, stvk-tm,
    mass-spring, scipy's product) carry their flops, bytes, bound and achieved fraction, and the table
    prints them beside the measured ceilings; the others carry none."""
    from realtime.models import SPECS
    from verification.bench.suite import CALL_ROW, CALLS, CUTS, run
    from verification.bench.table import format_table

    out = run(meshes=("beam",), repeats=1, steps=2)
    roof = out["machine"]["roofline"]
    assert roof["fma_gflops"] > 0 and all(v > 0 for v in roof["triad_gbs"].values())
    assert roof["vector_bits"] in (128, 256, 512)
    rows = {r["name"]: r for r in out["results"]}
    haptic = {f"{m}, one step a call (haptic loop)" for m in ("linear-tm", "stvk-tm")}
    phases = {"stvk-tm, element arithmetic alone", "stvk-tm, gather and scatter alone"}
    placed = {"linear-tm", "stvk-tm", "mass-spring", "scipy-bsr-matvec"} | haptic | phases
    for name in placed:
        r = rows[name]
        assert (
            r["flops"] > 0 and r["bytes"] > 0 and r["roofline_us"] > 0 and r["roofline_limit"] in ("compute", "memory")
        )
        assert r["roofline_fraction"] == pytest.approx(r["roofline_us"] / r["step_us"])
    assert "roofline_us" not in rows["corotational-tm"] and "roofline_us" not in rows["stvk-tm (transverse + penalty)"]
    cut = rows["linear-tm, cut one tetrahedron"]  # microseconds per cut, timed like every row
    assert cut["n"] == CUTS and cut["step_us"] > 0 and "roofline_us" not in cut
    call = rows[CALL_ROW]  # the haptic call's own cost, per call: no step's work, so no roofline
    assert call["n"] == CALLS and call["step_us"] > 0
    assert "roofline_us" not in call
    for m in (
        s.name for s in SPECS.values() if s.float32
    ):  # beside their float64 rows, with no roofline (the peak measured is float64's)
        r = rows[f"{m}, float32"]
        assert r["precision"] == "float32" and "roofline_us" not in r
        assert r["speedup"] == pytest.approx(rows[m]["step_us"] / r["step_us"])
    threaded = [r for r in out["results"] if r.get("threads")]
    for name in phases:  # each phase of stvk-tm's force beside the whole, where the whole was timed
        r = rows[name]
        assert r["part_of"] == "stvk-tm, force alone"
        if threaded:
            assert r["share"] == pytest.approx(r["step_us"] / rows[r["part_of"]]["step_us"])
    for r in threaded:  # the step and the force alone, each beside its one-thread row of the same rounds
        assert r["speedup"] == pytest.approx(rows[r["versus"]]["step_us"] / r["step_us"])
        assert r["versus"] == r["name"].replace(f", {r['threads']} threads", "")
    assert {r["versus"] for r in threaded} == (
        {f"{m}{alone}" for m in ("linear-tm", "stvk-tm", "corotational-tm") for alone in ("", ", force alone")}
        if threaded
        else set()
    )
    ceilings = out["machine"]["thread_scaling"]  # what the machine gains from the same threads
    assert set(ceilings) == ({"beam"} if threaded else set())
    assert all(c["fma"] > 0 and c["triad"] > 0 and c["bytes"] > 0 for c in ceilings.values())
    assert not any(r["name"].startswith(("fma", "triad")) for r in out["results"])  # ceilings, not rows
    table = format_table(out)
    gains = r"the machine's own gain from \d threads: FMA \d\.\d\dx, triad on [\d.]+ MB \d\.\d\dx"
    assert len(re.findall(gains, table)) == len(ceilings)
    assert "FMA peak" in table and f"({roof['vector_bits']}-bit vectors" in table and "triad GB/s by data size" in table
    assert len(re.findall(r"roofline [\d.]+ us \((compute|memory)\): \d+% of it", table)) == len(placed)
    assert len(re.findall(r"\d\.\d\dx its float64 row", table)) == sum(s.float32 for s in SPECS.values())
    # what the hot loops compile to on this target: counted, printed, never asserted (verification.bench.codegen)
    assert "compiled code (numba target" in table and out["compiled_code"]["stvk"]["general_packed"] >= 0
    _the_benchmarks_page_keeps_one_section_per_machine(out)


def _the_benchmarks_page_keeps_one_section_per_machine(out):
    """make bench writes docs/benchmarks.md: this machine's section (date, commit, a row per model)
    replaces its previous one, another machine's stays."""
    import copy
    import tempfile
    from pathlib import Path

    from verification.bench.table import write_markdown

    other = copy.deepcopy(out)
    other["machine"]["cpu"] = "Another CPU"
    with tempfile.TemporaryDirectory() as tmp:
        page = Path(tmp) / "benchmarks.md"
        write_markdown(page, out)
        write_markdown(page, other)
        again = copy.deepcopy(out)
        again["machine"]["date"] = "2099-01-01T00:00:00Z"
        write_markdown(page, again)
        text = page.read_text()
    assert text.startswith("# tissuebench: benchmarks")
    headings = re.findall(r"^## (.*)$", text, flags=re.M)
    assert headings == [
        f"Another CPU, {out['machine']['cores']} cores",
        f"{out['machine']['cpu']}, {out['machine']['cores']} cores",
    ]
    assert "Measured 2099-01-01T00:00:00Z" in text and text.count(f"at commit {out['machine']['commit']}") == 2
    assert text.count("| beam | linear-tm |") == 2


@pytest.mark.parametrize("threads", [1, 2])
def test_the_force_alone_rows_compute_the_models_force(threads):
    """The rows "M, force alone" time the force kernel from a compiled loop: what the loop leaves in f
    must be the model's internal force (a loop that called nothing would time nothing)."""
    from meshes import stored_mesh
    from realtime import Material, build_model
    from verification.bench.suite import _force_loop

    mesh = stored_mesh("beam")
    model = build_model("stvk-tm", mesh.points, mesh.tets, Material(1e5, 0.3, 1000.0, law="stvk"), threads=threads)
    u = 1e-3 * np.random.default_rng(1).standard_normal(mesh.points.shape)
    f = np.zeros_like(u)
    _force_loop(model.force_kernel, model.data, model.new_scratch(), u, f, 2)
    assert np.array_equal(f, model.internal_force(u)) and np.abs(f).max() > 0


def test_the_phase_rows_do_the_phases_of_stvk_tms_force():
    """The rows "stvk-tm, element arithmetic alone" and "stvk-tm, gather and scatter alone" time loops of
    their own; each must do its phase of the kernel (a loop that called nothing would time nothing). On
    a box of one block (48 tetrahedra): the gather, then the arithmetic loop, then the scatter give the
    model's force; and the gather-and-scatter loop leaves in f the scatter of the displacement
    differences themselves as the scatter reads them (the gather writes corner a's component r where
    the scatter reads corner r's component a: f_{a+1, r} -= u_{r+1, a} - u_{0, a}, f_0 += their sum),
    as numpy adds them (to round-off: the order of the sums)."""
    from meshes import structured_box
    from realtime import Material, build_model
    from realtime.blocks import BLOCK, gather, scatter_block
    from verification.bench.suite import _gather_scatter_loop, _stvk_arithmetic_loop

    mesh = structured_box((0.02, 0.02, 0.02), (2, 2, 2))
    model = build_model("stvk-tm", mesh.points, mesh.tets, Material(1e5, 0.3, 1000.0, law="stvk"))
    tets = model.data.tets
    assert len(tets) == BLOCK
    u = 1e-3 * np.random.default_rng(2).standard_normal(mesh.points.shape)
    (W,) = model.new_scratch()
    f = np.zeros_like(u)
    gather(tets.reshape(-1), 0, u.reshape(-1), W)
    _stvk_arithmetic_loop(model.data, W, 1)
    scatter_block(tets.reshape(-1), 0, W, f.reshape(-1), model.data.everywhere)
    expected = model.internal_force(u)
    assert np.abs(f - expected).max() <= 16 * np.finfo(float).eps * np.abs(expected).max()
    _gather_scatter_loop(model.data, W, u, f, 2)
    d = (u[tets[:, 1:]] - u[tets[:, :1]]).transpose(0, 2, 1)  # (P, 3, 3): [a, r] = u_{r+1, a} - u_{0, a}
    moved = np.zeros_like(u)
    np.add.at(moved, tets[:, 1:], -d)
    np.add.at(moved, tets[:, 0], d.sum(axis=1))
    assert np.abs(moved).max() > 0
    assert np.abs(f - moved).max() <= 16 * np.finfo(float).eps * np.abs(u).max()


def test_bench_peers_without_the_peers_says_how_to_get_them(capsys):
    """The suite's venv has neither peer (they live in .venv-peers): the command names the missing one
    and the make target in one line, and exits 2, instead of a traceback from an import."""
    import importlib.util

    if importlib.util.find_spec("newton") and importlib.util.find_spec("pbatoolkit"):
        pytest.skip("both peers are installed here")
    from verification.bench.peers import main

    assert main([]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is not installed: run `make bench-peers`" in err[0]


def test_the_structured_cube_is_the_peers_benchmark_mesh():
    """11 cells a side, six positive tetrahedra a cell filling the unit cube: 1728 vertices, 7986
    tetrahedra of volume 1 / 7986 each (to round-off), every interior face shared by two of them."""
    from meshes.generators import structured_cube
    from realtime.geometry import signed_volumes

    mesh = structured_cube(11)
    assert (mesh.n_vertices, mesh.n_tets) == (1728, 7986)
    vol = signed_volumes(mesh.points, mesh.tets)
    np.testing.assert_allclose(vol, 1.0 / 7986, rtol=1e-12)
    faces = np.sort(mesh.tets[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    _, counts = np.unique(faces, axis=0, return_counts=True)
    assert counts.max() == 2 and np.sum(counts == 1) == 6 * 11 * 11 * 2  # the boundary: two triangles a square


def test_the_solvers_bench_solves_the_livers_first_newton_system_and_names_debians_solvers():
    """One case and one preconditioner through ``bench --solvers``'s rows: GAMG converges (PETSc's reason
    positive) in some iterations on P2, the row says the dofs and memory, and the table names the
    preconditioners Debian's PETSc was built with. Its seconds are the benchmark's, never asserted."""
    from verification.bench.solvers import format_table, run

    out = run(preconditioners=["gamg"], cases=["liver P2 refined 0, nu 0.4"])
    (row,) = out["rows"]
    assert row["case"] == "liver P2 refined 0, nu 0.4" and row["n_dofs"] > 10_000
    assert row["reason"] > 0 and 0 < row["iterations"] < 500 and row["peak_memory_bytes"] > 0
    assert "hypre" in format_table(out) and "mumps" in format_table(out)


def test_the_advice_bench_counts_a_decision_only_where_the_advice_decided():
    """``bench --advice`` measures whether the advisor decides on the organs users bring: a pick decides;
    "no model" decides only with a truth whose bar is at most a third of the tolerance and no candidate
    left undecided; "cannot decide", an unknown bar or a wide one do not."""
    from verification.bench.advice import decided

    pick = {"model": "stvk-tm", "integrator": "symplectic-euler", "refine": 2, "undecided": []}
    assert decided(pick, 0.05) == (True, "stvk-tm (symplectic-euler) on the mesh refined 2 times")
    none = {"model": None, "undecided": [], "reference": {"bar": 0.016}}
    assert decided(none, 0.05) == (True, "no model")
    assert not decided({**none, "reference": {"bar": 0.017}}, 0.05)[0]  # over a third of 5%
    assert not decided({**none, "reference": {"bar": None}}, 0.05)[0]  # unknown: never a decision
    assert decided({**none, "undecided": ["linear-tm ..."]}, 0.05) == (False, "cannot decide")


def test_the_advice_bench_asks_about_scenes_a_truth_converges_on():
    """Its scenes load, and each tool holds a face of the mesh: a tool held at points has no converging
    truth (``scene.point_held``), and the bench would time a question nothing can decide. The user's 5 mm
    tool holds four vertices of sofa-liver2.msh, one of them inside the body."""
    from verification.bench.advice import CASES
    from verification.scene import point_held
    from verification.scene_file import load_scene

    for _, name, _, _ in CASES:
        scene = load_scene(name)
        assert point_held(scene) == [], name
    user = load_scene(CASES[1][1])
    assert user.mesh.n_vertices == 507 and len(user.problem.loads[0].region.vertices(user.mesh)) == 4
