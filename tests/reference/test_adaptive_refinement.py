"""The adaptive reference (reference/adaptive.py): Dorfler's marking, a refinement that stays conforming,
a bar reached with fewer dofs than uniform refinement where the error lives in a corner, the same answer
on two ranks, its levels in ParaView, and its answer evaluated anywhere in the body after a restart."""

import json

import numpy as np
import pytest
from mpi4py import MPI

from reference.adaptive import distributed, doerfler, mesh_arrays, refine_marked
from verification.cli import main
from verification.runs import reference as runs_reference
from verification.runs.reference import reference_at, reference_result
from verification.runs.results import Result
from verification.scene_file import load_scene

from ..conftest import SWING
from .test_manufactured_and_analytic import cli


def test_doerfler_marks_the_fewest_cells_that_hold_the_share():
    eta2 = np.array([1.0, 5.0, 3.0, 1.0])
    assert doerfler(eta2, 0.5).tolist() == [False, True, False, False]  # 5 of 10: one cell is enough
    assert doerfler(eta2, 0.6).tolist() == [False, True, True, False]
    assert doerfler(np.full(4, 2.0), 0.5).tolist() == [True, True, False, False]  # ties by index
    assert not doerfler(np.zeros(3)).any()  # nothing to mark where nothing is estimated


def _volume_and_boundary(x, cells):
    """The mesh's volume (m^3) and its boundary's area (m^2): faces met once are the boundary."""
    e = x[cells]
    volume = np.abs(np.einsum("ij,ij->i", np.cross(e[:, 1] - e[:, 0], e[:, 2] - e[:, 0]), e[:, 3] - e[:, 0])).sum() / 6
    faces = np.sort(cells[:, [[1, 2, 3], [0, 2, 3], [0, 1, 3], [0, 1, 2]]].reshape(-1, 3), axis=1)
    unique, count = np.unique(faces, axis=0, return_counts=True)
    assert count.max() <= 2  # no face is shared by three cells
    b = x[unique[count == 1]]
    area = np.linalg.norm(np.cross(b[:, 1] - b[:, 0], b[:, 2] - b[:, 0]), axis=1).sum() / 2
    return volume, area


def test_a_marked_cell_is_cut_and_the_mesh_stays_conforming():
    """One corner cell of the unit cube marked: its six edges' midpoints become vertices, and the refined
    mesh has the cube's volume and surface (1 and 6, to round-off): a hanging node would leave faces met
    once inside the body and add their area to the boundary's."""
    from dolfinx import mesh as dmesh

    x, cells = mesh_arrays(dmesh.create_unit_cube(MPI.COMM_SELF, 2, 2, 2))
    marked = np.zeros(len(cells), dtype=bool)
    marked[np.argmin(x[cells].mean(axis=1).sum(axis=1))] = True
    fine_x, fine_cells = refine_marked(x, cells, marked)
    assert len(cells) < len(fine_cells) < 8 * len(cells)  # more cells, far fewer than a uniform cut
    c = cells[marked][0]
    midpoints = np.array([(x[a] + x[b]) / 2 for i, a in enumerate(c) for b in c[i + 1 :]])
    assert np.all(np.min(np.linalg.norm(fine_x[None] - midpoints[:, None], axis=2), axis=1) < 1e-14)
    volume, area = _volume_and_boundary(fine_x, fine_cells)
    assert volume == pytest.approx(1.0, abs=1e-14) and area == pytest.approx(6.0, abs=1e-13)


def test_a_distributed_adapted_mesh_is_the_one_made_on_rank_0():
    from dolfinx import mesh as dmesh

    x, cells = mesh_arrays(dmesh.create_unit_cube(MPI.COMM_SELF, 1, 1, 1))
    again = mesh_arrays(distributed(x, cells, MPI.COMM_SELF))
    key = lambda xc: np.sort(np.round(xc[0][xc[1]].mean(axis=1), 12), axis=0)  # noqa: E731
    assert np.array_equal(key((x, cells)), key(again))


def _clamp_corner():
    from verification.studies.effectivity import CASES, case_scene

    return case_scene(CASES["clamp corner"])


def test_where_the_error_lives_in_a_corner_the_adapted_truth_is_as_sharp_with_fewer_dofs():
    """The coarse clamped beam pulled at its end (the effectivity table's clamp corner): the P3 bar that
    uniform refinement reaches with P2 refined once (8 times the cells), the adapted truth reaches with
    fewer P2 dofs, and it stops when it is there."""
    scene = _clamp_corner()
    uniform = reference_result(scene, estimate="p3", use_cache=False)
    target = uniform.meta["ref_err_estimate"]
    adapted = reference_result(scene, estimate="adaptive", adapt={"target": target}, use_cache=False)
    levels = adapted.meta["adaptive"]["levels"]
    assert adapted.meta["ref_err_estimate"] <= target and "is within" in adapted.meta["adaptive"]["stop"]
    assert levels[-1]["n_dofs"] < uniform.meta["solves"][0]["n_dofs"], levels
    assert [lv["bar"] for lv in levels] == sorted((lv["bar"] for lv in levels), reverse=True)
    # the returned P2 solution and its bar: the bar is twice its distance to P3 on the last mesh
    assert adapted.meta["estimator"] == "adaptive" and adapted.meta["ref_err_estimate"] == levels[-1]["bar"]


def test_an_adapted_truth_is_evaluated_anywhere_in_the_body_after_a_restart(tmp_path, monkeypatch):
    """The swing beam adapted once: its answer at other points (where another engine wrote its result)
    is the solve kept beside the cached result, rebuilt on its adapted mesh in a process that did not
    solve it, and equals the same solve evaluated there."""
    monkeypatch.setenv("TISSUEBENCH_CACHE", str(tmp_path / "cache"))
    p = tmp_path / "swing.toml"
    p.write_text(SWING)
    scene = load_scene(p)
    opts = {"estimate": "adaptive", "adapt": {"max_levels": 1}}
    reference_result(scene, **opts)
    points = scene.mesh.points[::3] * 0.999 + 0.001 * scene.mesh.points.mean(axis=0)
    solved = reference_at(scene, points, **opts)
    runs_reference._SOLVED.clear()  # as a new process finds it: only the files
    restored = reference_at(scene, points, **opts)
    # the same dofs evaluated at the same points: only the order of round-off may differ
    assert np.abs(restored.displacement - solved.displacement).max() <= 1e-12 * np.abs(solved.displacement).max()


def test_the_reference_command_writes_the_adapted_levels_for_paraview(tmp_path, monkeypatch, capsys):
    """``reference --estimate adaptive --vtk``: one step a level, each with its displacement at the vertices
    and its cells' indicator; --target without the adaptive estimate is one line naming it."""
    import meshio

    monkeypatch.setenv("TISSUEBENCH_CACHE", str(tmp_path / "cache"))
    p = tmp_path / "swing.toml"
    p.write_text(SWING)
    args = ["reference", str(p), "--estimate", "adaptive", "--levels", "1", "--json", "--vtk", str(tmp_path / "vtk")]
    assert main(args) == 0
    meta = json.loads(capsys.readouterr().out)["meta"]
    grids = [meshio.read(tmp_path / "vtk" / f"swing-reference-levels_{k:06d}.vtu") for k in range(2)]
    assert [len(g.cells_dict["tetra"]) for g in grids] == [lv["n_cells"] for lv in meta["adaptive"]["levels"]]
    eta2 = grids[0].cell_data["eta2"][0]
    assert eta2.min() >= 0 and eta2.max() > 0 and grids[1].point_data["displacement"].shape[1] == 3
    assert main(["reference", str(p), "--target", "0.01"]) == 2
    err = capsys.readouterr().err.strip()
    assert "--target and --budget steer --estimate adaptive" in err and "\n" not in err


@pytest.mark.slow
@pytest.mark.mpi
def test_mpirun_adapted_truth_equals_serial(tmp_path):
    """Adapted twice on one rank and on two: the meshes are made on rank 0 and the indicator gathered
    there by the cells' midpoints, so the levels, the answer and its bar are the serial ones (1e-8:
    Newtons stopped at 1e-10 of the force scale). The swing beam: its levels end at 52 000 P3 dofs
    where cantilever-pull's end at 107 000 (8 s for both runs here, 32 s with cantilever-pull)."""
    scene = tmp_path / "swing.toml"
    scene.write_text(SWING)
    out = {n: tmp_path / f"{n}.npz" for n in (1, 2)}
    args = ["reference", str(scene), "--estimate", "adaptive", "--levels", "2", "--no-cache"]
    for n, path in out.items():
        r = cli(*args, "--out", str(path), mpi=n if n > 1 else 0)
        assert r.returncode == 0, r.stderr
    a, b = Result.load(out[1]), Result.load(out[2])
    assert b.meta["mpi_ranks"] == 2
    assert [lv["n_cells"] for lv in a.meta["adaptive"]["levels"]] == [
        lv["n_cells"] for lv in b.meta["adaptive"]["levels"]
    ]
    assert np.linalg.norm(a.displacement - b.displacement) <= 1e-8 * np.linalg.norm(a.displacement)
    assert b.meta["ref_err_estimate"] == pytest.approx(a.meta["ref_err_estimate"], rel=1e-6)
