"""Compare one model on your own mesh: what does a real-time model give up on *this* organ?

    .venv/bin/python examples/compare_on_your_mesh.py MESH [--model stvk-tm] [--scale 1.0]
                                                      [--press 0.05] [--young 3000] [--out DIR]

MESH is any tetrahedral mesh file the project reads (gmsh .msh of any version, VTK .vtu, XDMF, Medit
.mesh ...), in metres, or in other units with ``--scale`` (0.001 for millimetres). The script

1. reads the mesh and says what it repaired (merged vertices, turned tetrahedra);
2. places a load on it, as a first guess you will edit: the lowest tenth of the body held, a tool
   pressing the top of it down by ``--press`` of the body's height;
3. writes this as a scene file, ``DIR/<mesh>.toml``, the one the command line reads too
   (``tissuebench compare DIR/<mesh>.toml --model linear-tm``): edit its regions, material and load
   to match your case and run it again;
4. solves the ground truth on that scene (dolfinx, P2, with its own error estimate) and runs the model
   through the same harness the studies use;
5. prints the model's error against the truth with the truth's bar, how the error splits between the
   mesh (P1 on your tetrahedra) and the model (what its shortcut costs), and its rate.

The ground truth is solved once and cached (``~/.cache/tissuebench``): a second model on the same
scene costs only its own run.
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path

import numpy as np

from meshes.io import atomic_write_text, read_mesh
from realtime.models import SPECS, stvk_tm
from verification.runs.compare import compare
from verification.scene import SceneError
from verification.scene_file import load_scene
from verification.studies.frame import reference_bar, true_range

# %% 1. The mesh, as the harness will read it
#
# ``read_mesh`` repairs what real files contain and says so in ``mesh.notes``; what it cannot repair (a
# degenerate tetrahedron, a file of triangles only) is one line naming the file and the element.


def read(path: Path, scale: float):
    mesh = read_mesh(path, scale=scale)
    lo, hi = mesh.points.min(axis=0), mesh.points.max(axis=0)
    print(f"{path.name}: {mesh.n_vertices} vertices, {mesh.n_tets} tetrahedra, {hi - lo} m across")
    for note in mesh.notes:
        print(f"  repaired: {note}")
    return mesh, lo, hi


# %% 2. and 3. A scene: the mesh, a material, what is held and what is pressed
#
# A scene file is plain TOML (docs/scenes.md). Regions are boxes or spheres in the mesh's coordinates
# after ``scale``: here a slab through the lowest tenth of the body is held, and a sphere a fifth of the
# body wide around the top vertex nearest the middle is the tool. A relative mesh path is read from
# the scene file's folder. The tool is ramped in over a fifth of the
# (pseudo-)time, which is how the reference's Newton steps in for a non-linear law.


def top_centre(points: np.ndarray, lo: np.ndarray, hi: np.ndarray) -> np.ndarray:
    """The vertex of ``points`` (N, 3) m where the tool presses: of those in the top twentieth of the
    height, the nearest to the body's middle seen from above."""
    top = points[points[:, 2] >= hi[2] - 0.05 * (hi[2] - lo[2])]
    middle = 0.5 * (lo[:2] + hi[:2])
    return top[np.argmin(np.linalg.norm(top[:, :2] - middle, axis=1))]


def scene_text(name: str, mesh_file: Path, scale: float, lo, hi, young: float, press: float, top) -> str:
    size = float(np.max(hi - lo))
    held_top = lo[2] + 0.1 * (hi[2] - lo[2])
    below, above = [*(lo - size).tolist()[:2], lo[2] - size], [*(hi + size).tolist()[:2], held_top]
    return f"""name = "{name}"
description = "{mesh_file.name}: its lowest tenth held, a tool pressing its top {100 * press:g}% of its height down"

[mesh]
generator = "file"
file = "{mesh_file}"
scale = {scale!r}

[material]
law = "stvk"
young = {young!r}
poisson = 0.45
density = 1000.0

[[fixed]]
box = [{below}, {above}]

[[load]]
kind = "displacement"
sphere = {{ center = {list(map(float, top))}, radius = {0.1 * size!r} }}
value = [0.0, 0.0, {-press * float(hi[2] - lo[2])!r}]
ramp = 0.2

[time]
mode = "static"
"""


# %% 4. and 5. The truth and the model on the same scene, and what the numbers say
#
# ``compare`` solves (or reads) the reference, runs the model to equilibrium through the engine seam,
# and returns a Row (docs/metrics.md). ``budget=True`` splits the error: the mesh's part is P1 on your
# tetrahedra against the truth, the model's part the model against P1 on the same tetrahedra.


def report(scene, model: str) -> int:
    row = compare(scene, model, budget=True)
    if not row.ok:
        print(f"{model}: {row.status}: {row.message}")
        return 1
    bar = true_range(row.rel_l2, reference_bar(row, "rel_l2"))
    print(f"{model} on {scene.name}: relative L2 error {row.rel_l2:.3g} ({bar}, by the truth's own bar)")
    if row.reaction_rel_err is not None:
        print(f"  the tool's force is off by {row.reaction_rel_err:.3g} (relative)")
    parts = row.error_budget or {}
    if parts.get("mesh") is not None:
        print(f"  of which the mesh's part {parts['mesh']:.3g}, the model's {parts['model']:.3g}")
    print(f"  {row.rate_hz:.0f} steps a second ({row.step_us:.3g} us a step); {row.realtime_factor:.3g} x real time")
    for term in row.unrepresented:
        print(f"  ran without {term}: the errors above include what that costs")
    return 0


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("mesh", type=Path)
    ap.add_argument("--model", default=stvk_tm.NAME, choices=list(SPECS))
    ap.add_argument("--scale", type=float, default=1.0, help="metres per unit of the file")
    ap.add_argument("--press", type=float, default=0.05, help="the tool's travel, a fraction of the height")
    ap.add_argument("--young", type=float, default=3000.0, help="Young's modulus, Pa (liver: about 3 kPa)")
    ap.add_argument("--out", type=Path, default=Path("scenes"), help="where the scene file is written")
    args = ap.parse_args(argv)
    try:
        mesh, lo, hi = read(args.mesh, args.scale)
        top = top_centre(mesh.points, lo, hi)
        name = args.mesh.stem
        mesh_file = Path(os.path.relpath(args.mesh.resolve(), args.out.resolve()))  # beside the scene
        text = scene_text(name, mesh_file, args.scale, lo, hi, args.young, args.press, top)
        path = atomic_write_text(args.out / f"{name}.toml", text)
        print(f"the scene: {path} (edit it to match your case)")
        return report(load_scene(path), args.model)
    except (SceneError, ValueError, OSError) as exc:
        print(f"compare_on_your_mesh: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
