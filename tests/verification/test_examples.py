"""The literate examples (examples/, docs/contributing.md) run as a user runs them, in a process of their
own, and say what they promise: a model compared on a mesh the user brings, a user's engine judged on
a scene it never saw, a model gated in CI (passing, then failing on a tightened bound). Their bad input
is one line and exit 2."""

import re
import subprocess
import sys
import tomllib
from pathlib import Path

import pytest

from meshes import structured_box
from meshes.io import write_mesh
from verification.scene_file import load_scene

EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


def _run(script: str, *args, cwd: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [sys.executable, str(EXAMPLES / script), *map(str, args)], cwd=cwd, capture_output=True, text=True
    )


@pytest.mark.slow
def test_a_model_compared_on_the_users_own_mesh(tmp_path):
    """A box written as gmsh 2.2 in millimetres stands in for the user's organ: the scene file the example
    writes reads again (its mesh found beside it, scaled to metres), and the comparison prints the error
    with the truth's bar and the split between the mesh and the model. A linear model on a 5% press has
    a model part (the geometric non-linearity) and a mesh part (P1 on these tetrahedra) both above zero."""
    mesh = structured_box((40.0, 30.0, 20.0), (4, 3, 2))
    write_mesh(mesh, tmp_path / "organ.msh")
    out = _run("compare_on_your_mesh.py", "organ.msh", "--model", "linear-tm", "--scale", "0.001", cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    scene = load_scene(tmp_path / "scenes" / "organ.toml")
    assert scene.mesh.n_tets == mesh.n_tets and scene.mesh.points.max() == pytest.approx(0.04)
    text = out.stdout
    assert "linear-tm on organ: relative L2 error" in text and "by the truth's own bar" in text
    parts = re.search(r"the mesh's part (\S+), the model's (\S+)\n", text)
    mesh_part, model_part = float(parts.group(1)), float(parts.group(2))
    assert mesh_part > 0 and model_part > 0
    assert "reference: " in out.stderr  # the truth's progress, on stderr


def test_a_mesh_that_is_not_tetrahedral_is_one_line_and_exit_2(tmp_path):
    (tmp_path / "surface.obj").write_text("v 0 0 0\nv 1 0 0\nv 0 1 0\nf 1 2 3\n")
    out = _run("compare_on_your_mesh.py", "surface.obj", cwd=tmp_path)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert "surface.obj" in out.stderr and "Traceback" not in out.stderr


@pytest.mark.slow
def test_a_users_engine_is_judged_on_a_scene_it_read_from_the_export(tmp_path):
    """The stand-in engine (examples/direct_p1.py: linear P1 in numpy and scipy) on block-press, a 1%
    press: its error is P1's on that mesh, which the judgement's budget puts on the mesh (the model's
    part, linear against the StVK truth at 1% strain, is under a tenth of it)."""
    out = _run("judge_your_engine.py", "block-press", "--out", tmp_path, cwd=tmp_path)
    assert out.returncode == 0, out.stderr[-2000:]
    assert (tmp_path / "scene" / "scene.json").is_file() and (tmp_path / "result.npz").is_file()
    budget = next(ln for ln in out.stdout.splitlines() if "error budget" in ln)
    mesh_part = float(budget.split("mesh ")[1].split()[0])
    model_part = float(budget.split("model ")[1].split()[0])
    assert model_part < 0.1 * mesh_part
    rel_l2 = float(next(ln for ln in out.stdout.splitlines() if ln.strip().startswith("rel_l2")).split()[1])
    assert rel_l2 == pytest.approx(mesh_part, rel=0.1)  # the two parts nearly orthogonal, the model's small


def test_an_engine_that_fails_is_one_line_naming_it_and_exit_2(tmp_path):
    failing = f"{sys.executable} -c 'import sys; sys.exit(\"no solver\")' {{scene}} {{result}}"
    out = _run("judge_your_engine.py", "block-press", "--engine", failing, cwd=tmp_path)
    assert out.returncode == 2 and len(out.stderr.strip().splitlines()) == 1
    assert "no solver" in out.stderr and "exit 1" in out.stderr


@pytest.mark.slow
def test_a_gate_passes_with_its_baseline_and_fails_when_its_bound_is_tightened(tmp_path):
    """The example exits 0 only when the gate passed and its tightened copy failed; the gates file keeps
    the bound as written and the baseline with its provenance."""
    out = _run("gate_a_model_in_ci.py", "--out", tmp_path / "gates.toml", cwd=tmp_path)
    assert out.returncode == 0, out.stdout[-2000:] + out.stderr[-2000:]
    assert "1 passed, 0 failed" in out.stdout and "0 passed, 1 failed" in out.stdout
    assert "exceeds the bound" in out.stdout
    gate = tomllib.loads((tmp_path / "gates.toml").read_text())["gate"][0]
    assert gate["bound"] == 0.02 and gate["model"] == "linear-tm"
    base = gate["baseline"]
    assert 0 < base["value"] < 0.02 and len(base["mesh_sha256"]) == 64 and base["commit"] and base["date"]
