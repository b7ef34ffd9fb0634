"""An engine in another process, another venv, any language: a command that reads an exported scene and
writes its answer (``--engine-cmd``; docs/contributing.md, "An engine").

The command is a template: ``{scene}`` becomes the directory ``engines.export`` wrote the scene into,
``{result}`` the ``.npz`` it must write, ``{model}`` the model's name. It writes ``displacement``
((N, 3) for a static scene, (T, N, 3) at the scene's output instants for a dynamic one) at the scene
mesh's vertices, in metres, and may add ``reaction`` (T, 3) N and ``step_us`` (its own time per step,
us). It runs once, in its own process, with ``timeout`` seconds; the harness reads what it wrote
(``engines.foreign``) and judges it like any model. What goes wrong (it cannot start, exits non-zero,
runs past the timeout, writes nothing or a wrong array) is one line naming the command.
"""

from __future__ import annotations

import shlex
import subprocess
import tempfile
import time
from pathlib import Path

import numpy as np

from realtime.errors import InputError

from .export import export, output_times
from .foreign import EngineResultError, read_result
from .protocol import SceneInputs, Settling

#: Seconds a command may run before it is stopped (a hang is a failure, named).
TIMEOUT = 600.0


class CommandError(InputError):
    """A command engine that failed; ``str()`` names the command and what went wrong."""


class CommandEngine:
    """The engine a command is: one model, ``model``, run by ``command`` (the module docstring)."""

    def __init__(self, command: str, model: str, timeout: float = TIMEOUT):
        if not command.strip():
            raise InputError("--engine-cmd: give the command that runs the engine")
        self.command, self.timeout = command, timeout
        self.name, self.models = f"command {shlex.split(command)[0]}", (model,)

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict):
        return CommandSimulation(self, inputs, model)


class CommandSimulation:
    """A command's answer as a Simulation: the command runs on the first question, and the instants of
    a dynamic scene are read from what it wrote."""

    integrator = "the command's own"
    timing = None  # the command times itself

    def __init__(self, engine: CommandEngine, inputs: SceneInputs, model: str):
        self.engine, self.inputs, self.model = engine, inputs, model
        self._answer = None  # (displacement (T, N, 3) m, reaction (T, 3) N, step_us or None)
        self._k = 0  # the output instant held

    def _run(self) -> None:
        if self._answer is not None:
            return
        e = self.engine
        with tempfile.TemporaryDirectory(prefix="tissuebench-engine-") as work:
            scene_dir, result = Path(work) / "scene", Path(work) / "result.npz"
            export(self.inputs, scene_dir)
            args = [a.format(scene=scene_dir, result=result, model=self.model) for a in shlex.split(e.command)]
            t0 = time.perf_counter()
            try:
                done = subprocess.run(args, capture_output=True, text=True, timeout=e.timeout)
            except FileNotFoundError:
                raise CommandError(f"--engine-cmd {e.command!r}: no such program {args[0]!r}") from None
            except subprocess.TimeoutExpired:
                raise CommandError(
                    f"--engine-cmd {e.command!r}: still running after {e.timeout:g} s, stopped"
                ) from None
            wall = time.perf_counter() - t0
            if done.returncode != 0:
                last = (done.stderr.strip().splitlines() or ["no message"])[-1]
                raise CommandError(f"--engine-cmd {e.command!r}: exited with status {done.returncode}: {last}")
            if not result.exists():
                raise CommandError(f"--engine-cmd {e.command!r}: wrote no {{result}} file (it ran {wall:.3g} s)")
            self._answer = self._read(result)

    def _read(self, path: Path) -> tuple:
        """What the command wrote, checked: on the scene's vertices, at every output instant."""
        try:
            res = read_result(path, self.inputs.points)
        except EngineResultError as exc:
            raise CommandError(f"--engine-cmd {self.engine.command!r}: {exc}") from None
        expected = len(output_times(self.inputs))
        if not np.array_equal(res.points, self.inputs.points) or len(res.displacement) != expected:
            raise CommandError(
                f"--engine-cmd {self.engine.command!r}: its displacement is {res.displacement.shape}, not "
                f"({expected}, {len(self.inputs.points)}, 3) (the output instants, the scene's vertices, xyz)"
            )
        with np.load(path) as z:
            step_us = float(z["step_us"]) if "step_us" in z.files else None
        reaction = res.reaction if res.reaction is not None else np.zeros((expected, 3))
        return res.displacement, reaction, step_us

    def critical_dt(self):
        return None  # its step is its own

    def start(self, dt) -> None:
        self._k = 0

    def advance_to(self, t: float) -> None:
        self._run()
        step = self.inputs.time.output_every
        self._k = int(round(t / step))

    def settle(self, rtol, max_steps, dt, dt_fraction) -> Settling:
        t0 = time.perf_counter()
        self._run()
        wall = time.perf_counter() - t0
        static = {"method": f"the command {self.engine.command!r}", "steps": 1, "residual": None, "wall_s": wall}
        return Settling(1, None, None, None, wall, static)

    def step(self, n: int) -> None:
        pass  # it ran in its own process: the harness does not time it (timing None)

    def step_us(self) -> float | None:
        self._run()
        return self._answer[2]

    def displacement(self) -> np.ndarray:
        self._run()
        return self._answer[0][self._k]

    def tool_force(self) -> np.ndarray:
        self._run()
        return self._answer[1][self._k]
