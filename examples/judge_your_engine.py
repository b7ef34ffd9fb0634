"""Judge your own engine's answer against the ground truth, on a scene it never saw before.

    .venv/bin/python examples/judge_your_engine.py [SCENE] [--engine "COMMAND {scene} {result}"]
                                                   [--scale 1.0] [--out DIR]

SCENE is a built-in scene's name or a scene file (default: block-press, a cube pressed by a plate).
The script

1. exports the scene as data any engine reads, whatever its language: ``scene.json`` (units, material
   constants, time, tools), ``arrays.npz`` (points, tetrahedra, what is held, the load vector, the
   tools' prescribed displacements), ``mesh.vtu`` and ``mesh.msh``;
2. runs your engine on it in a process of its own: any command that reads the folder ``{scene}`` and
   writes its answer to ``{result}``. By default ``examples/direct_p1.py`` stands in for yours: linear
   P1 elasticity in numpy and scipy, which imports nothing of this project;
3. judges what it wrote: its error against the truth with the truth's own bar, how that splits between
   its mesh and its model, and the checks that catch the usual slips (a result in millimetres, a held
   face that moved, a tool force of the wrong sign), each named in one line.

An engine on a mesh of its own writes a ``.vtu``, ``.pvd`` or ``.xdmf`` instead of an ``.npz``; the
judge reads those too and evaluates the truth at its points (``tissuebench judge SCENE RESULT``).
"""

from __future__ import annotations

import argparse
import shlex
import subprocess
import sys
import tempfile
from pathlib import Path

from verification.engines.export import export
from verification.engines.foreign import EngineResultError
from verification.inputs import scene_inputs
from verification.scene import SceneError
from verification.scene_file import load_scene
from verification.studies.judge import format_judgement, judge

HERE = Path(__file__).resolve().parent
STAND_IN = f"{shlex.quote(sys.executable)} {shlex.quote(str(HERE / 'direct_p1.py'))} {{scene}} {{result}}"

# %% 1. The scene, as data
#
# ``scene_inputs`` is the one place a scene becomes an engine's input (plain arrays in SI units), the
# same the built-in models are built from; ``export`` writes it with a description of every array.


def export_scene(scene, folder: Path) -> Path:
    directory = folder / "scene"
    export(scene_inputs(scene), directory)
    print(f"exported {scene.name} to {directory} ({scene.mesh.n_vertices} vertices, {scene.mesh.n_tets} tetrahedra)")
    return directory


# %% 2. Your engine, in its own process
#
# It is given the two paths and nothing else: what it knows of the scene it read from the folder.


def run_engine(command: str, directory: Path, result: Path) -> None:
    argv = [a.replace("{scene}", str(directory)).replace("{result}", str(result)) for a in shlex.split(command)]
    done = subprocess.run(argv, capture_output=True, text=True)
    if done.returncode != 0:
        last = (done.stderr.strip().splitlines() or ["(no message)"])[-1]
        raise EngineResultError(f"{argv[0]}: exit {done.returncode}: {last}")
    print(f"your engine wrote {result}")


# %% 3. The judgement
#
# ``judge`` reads the result (``scale``: metres per unit of your file), solves or reads the truth on
# the same scene, and returns the metrics of docs/metrics.md; ``format_judgement`` prints them as
# ``tissuebench judge`` does.


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default="block-press")
    ap.add_argument("--engine", default=STAND_IN, help="a command with {scene} and {result} in it")
    ap.add_argument("--scale", type=float, default=1.0, help="metres per length unit of the result")
    ap.add_argument("--out", type=Path, default=None, help="where to keep the export and the result")
    args = ap.parse_args(argv)
    with tempfile.TemporaryDirectory() as scratch:
        folder = args.out or Path(scratch)
        try:
            scene = load_scene(args.scene)
            directory = export_scene(scene, folder)
            result = folder / "result.npz"
            run_engine(args.engine, directory, result)
            print(format_judgement(judge(scene, str(result), scale=args.scale)))
        except (SceneError, EngineResultError, OSError) as exc:
            print(f"judge_your_engine: {exc}", file=sys.stderr)
            return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
