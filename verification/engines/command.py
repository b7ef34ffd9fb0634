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
import threading
import time
from pathlib import Path

import numpy as np

from realtime.errors import InputError

from .export import export, output_times, tool_motions
from .foreign import GAP, POSITION_ROUNDOFF, SHAPE_MATCH, UNITS, EngineResultError, read_result
from .protocol import SceneInputs, Settling, foreign_spec

#: Seconds a command may run before it is stopped (a hang is a failure, named).
TIMEOUT = 600.0


#: A command's points may differ from the scene's vertices by this share of the body's size: a file
#: written in float32 rounds them to 6e-8.
POINTS_MATCH = 1e-6


class CommandError(InputError):
    """A command engine that failed; ``str()`` names the command and what went wrong."""


class CommandEngine:
    """The engine a command is: one model, ``model``, run by ``command`` (the module docstring)."""

    isolated = True  # it runs in a process of its own: the harness need not fork one for it

    def __init__(self, command: str, model: str, timeout: float = TIMEOUT):
        if not command.strip():
            raise InputError("--engine-cmd: give the command that runs the engine")
        self.command, self.timeout = command, timeout
        self.name = f"command {shlex.split(command)[0]}"
        self.models = {model: foreign_spec(model, f"what {shlex.split(command)[0]} runs")}
        self.rigid = (model,)  # a scene's rigid tools reach it in the export; its result must state their force

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict):
        return CommandSimulation(self, inputs, model)


class CommandSimulation:
    """A command's answer as a Simulation: the command runs on the first question, and the instants of
    a dynamic scene are read from what it wrote."""

    integrator = "the command's own"
    timing = None  # the command times itself

    def __init__(self, engine: CommandEngine, inputs: SceneInputs, model: str):
        self.engine, self.inputs, self.model = engine, inputs, model
        self._answer = None  # (displacement (T, N, 3) m, reaction (T, 3) N, step_us or None, {steps, dt} stated)
        self._k = 0  # the output instant held

    @property
    def label(self) -> str:
        """How its errors name it."""
        return f"--engine-cmd {self.engine.command!r}"

    def command(self, scene_dir: Path, result: Path) -> list[str]:
        """The command line: the template with the scene's directory, the result's path and the model."""
        return [a.format(scene=scene_dir, result=result, model=self.model) for a in shlex.split(self.engine.command)]

    def relay(self, line: str) -> None:
        """A line the command wrote on stderr, as it comes (a command engine's are kept for its error)."""

    def _run(self) -> None:
        if self._answer is not None:
            return
        with tempfile.TemporaryDirectory(prefix="tissuebench-engine-") as work:
            scene_dir, result = Path(work) / "scene", Path(work) / "result.npz"
            export(self.inputs, scene_dir)
            args = self.command(scene_dir, result)
            t0 = time.perf_counter()
            status, last = self._call(args, work)
            wall = time.perf_counter() - t0
            if status != 0:
                self.failed(status, last)
            if not result.exists():
                raise CommandError(f"{self.label}: wrote no {{result}} file (it ran {wall:.3g} s)")
            self._answer = self._read(result)

    def _call(self, args: list[str], cwd: str) -> tuple[int, str]:
        """The command run in ``cwd``: its exit status and last stderr line (``_call``)."""
        return _call(args, self.engine.timeout, self.relay, self.label, cwd)

    def failed(self, status: int, last: str) -> None:
        """The command exited with ``status`` (not 0), ``last`` its last stderr line: CommandError."""
        raise CommandError(f"{self.label}: exited with status {status}: {last or 'no message'}")

    def _read(self, path: Path) -> tuple:
        """What the command wrote, checked: on the scene's vertices, at every output instant."""
        try:
            res = read_result(path, self.inputs.points)
        except EngineResultError as exc:
            raise CommandError(f"{self.label}: {exc}") from None
        expected = len(output_times(self.inputs))
        own = self.inputs.points
        if res.displacement.shape != (expected, len(own), 3):
            raise CommandError(
                f"{self.label}: its displacement is {res.displacement.shape}, not "
                f"({expected}, {len(own)}, 3) (the output instants, the scene's vertices, xyz)"
            )
        gap = np.linalg.norm(res.points - own, axis=1)
        if gap.max() > POINTS_MATCH * float(np.ptp(own, axis=0).max()):  # float32 points pass, others do not
            v = int(np.argmax(gap))
            raise CommandError(
                f"{self.label}: its points are not the scene's vertices: point {v} is {gap[v]:.3g} m from vertex "
                f"{v} {own[v].tolist()}; write the answer on the exported mesh's vertices, in its order, in metres"
            )
        on_scene(self.inputs, self.label, res.displacement)
        with np.load(path) as z:
            step_us = float(z["step_us"]) if "step_us" in z.files else None
            settled = self._settled(path, {k: z[k] for k in ("steps", "dt") if k in z.files})
            self._rigid_stated(np.asarray(z["rigid_force"], dtype=float) if "rigid_force" in z.files else None)
        reaction = res.reaction if res.reaction is not None else np.full((expected, 3), np.nan)  # none given
        return res.displacement, reaction, step_us, settled

    def _rigid_stated(self, given: np.ndarray | None) -> None:
        """A scene with rigid tools: the result states each one's force on the body (``rigid_force`` (K, 3)
        N, NaN where the engine has none to give; ``given``, None where it states none), the sign that the
        engine met them (an engine that read the export without them would answer as if they were not
        there); else CommandError."""
        c = self.inputs.loading.contacts
        if c is None or not c.count:
            return
        if given is None or given.shape[-2:] != (c.count, 3):
            got = "no rigid_force" if given is None else f"rigid_force of shape {given.shape}"
            raise CommandError(
                f"{self.label}: the scene has {c.count} rigid tool(s) (scene.json rigid_tools) and its result "
                f"states {got}: an engine that meets them writes each one's force on the body, ({c.count}, 3) N"
            )

    def _settled(self, path: Path, given: dict) -> dict:
        """The steps (a whole number >= 1) a static answer took, and their dt (s), where the result file
        states them; CommandError for a value that is neither."""
        out = {}
        for key, value in given.items():
            v = np.asarray(value)
            ok = v.ndim == 0 and np.issubdtype(v.dtype, np.number) and bool(np.isfinite(v)) and v > 0.0
            if ok and key == "steps":
                ok = v >= 1 and float(v) == int(v)
            if not ok:
                what = "a whole number of steps, at least 1" if key == "steps" else "a time step in seconds, > 0"
                raise CommandError(f"{self.label}: {path.name}: {key} = {value!r} is not {what}")
            out[key] = int(v) if key == "steps" else float(v)
        return out

    def critical_dt(self):
        return None  # its step is its own

    def start(self, dt) -> None:
        self._k = 0

    def advance_to(self, t: float) -> None:
        self._run()
        step = self.inputs.time.output_every
        self._k = int(round(t / step))

    def settle(self, rtol, max_steps, dt, dt_fraction) -> Settling:
        """Its static answer; the steps it took when its result file says (``steps``, with ``dt`` when it
        steps in time), so that a frame budget charges each of them, else one update."""
        t0 = time.perf_counter()
        self._run()
        wall = time.perf_counter() - t0
        settled = self._answer[3]
        steps, step = settled.get("steps", 1), settled.get("dt")
        static = {"method": self.label, "steps": steps, "residual": None, "wall_s": wall, "stated": bool(settled)}
        return Settling(steps, None, step, None, wall, static)

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


def on_scene(inputs: SceneInputs, label: str, u: np.ndarray) -> None:
    """CommandError where a command's answer ``u`` (T, N, 3) m does not keep the scene's own
    constraints, before any score: its tool vertices 100 or 1000 times where the scene puts them (its
    lengths in cm or mm), or away from there (an export made before the tool moved, another tool path),
    or a held component that moved (another frame, other vertices held). A gap within GAP of the
    largest displacement passes: a penalty tool holds its place to a few percent; so does one within a
    float32 position's round-off (POSITION_ROUNDOFF)."""
    lo = inputs.loading
    _, wanted = tool_motions(inputs)  # (T, P, 3) m
    mask = lo.tool_mask != 0.0
    scale = max(float(np.abs(wanted).max(initial=0.0)), float(np.abs(u).max()), 1e-300)
    limit = max(GAP * scale, POSITION_ROUNDOFF * float(np.abs(inputs.points).max()))
    if mask.any():
        got = u[:, lo.tool_vertex]
        size = max(float(np.linalg.norm(wanted * mask)), 1e-300)
        for k, unit in UNITS.items():
            if np.linalg.norm((got / 10.0**k - wanted) * mask) <= SHAPE_MATCH * size:
                raise CommandError(
                    f"{label}: its tools' vertices moved {10**k} times as far as the scene moves them: lengths in "
                    f"{unit}? write the answer in metres, as the export is"
                )
        gap = np.abs(got - wanted) * mask
        if gap.max() > limit:
            t, p, c = np.unravel_index(int(np.argmax(gap)), gap.shape)
            v = int(lo.tool_vertex[p])
            raise CommandError(
                f"{label}: the tool's vertex {v} is {gap[t, p, c]:.3g} m off in {'xyz'[c]} from where the scene "
                f"puts it ({wanted[t, p, c]:.4g} m at output {t}): another tool path, or a stale export"
            )
    held = lo.free == 0.0
    held[lo.tool_vertex] &= ~mask
    moved = np.abs(u) * held
    if moved.max() > limit:
        t, v, c = np.unravel_index(int(np.argmax(moved)), moved.shape)
        raise CommandError(
            f"{label}: vertex {v} moved {moved[t, v, c]:.3g} m in {'xyz'[c]} (output {t}), which the scene holds at "
            "0: a result in another frame, or an engine that held other vertices"
        )


def _call(args: list[str], timeout: float, relay, label: str, cwd: str) -> tuple[int, str]:
    """Run ``args`` in ``cwd`` (what it writes beside its answer goes with the directory), each line of its stderr passed to ``relay`` as it comes (its stdout dropped); its exit
    status and its last stderr line. CommandError naming ``label`` if it cannot start or runs past
    ``timeout`` s (then it is killed)."""
    last = [""]

    def read(stream):
        for line in stream:
            if line.strip():
                last[0] = line.strip()
                relay(line.rstrip())

    try:
        proc = subprocess.Popen(args, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=cwd)
    except FileNotFoundError:
        raise CommandError(f"{label}: no such program {args[0]!r}") from None
    with proc:
        reader = threading.Thread(target=read, args=(proc.stderr,), daemon=True)
        reader.start()
        try:
            status = proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            proc.kill()
            raise CommandError(f"{label}: still running after {timeout:g} s, stopped") from None
        except BaseException:  # an interrupt, or the harness's own bound: the process goes with it
            proc.kill()
            raise
        reader.join(timeout=5.0)
    return status, last[0]
