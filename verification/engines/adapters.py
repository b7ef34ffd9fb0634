"""The engines users pick, through the seam: NVIDIA newton, MuJoCo, PyBullet, MuJoCo Warp and Genesis, each run
by its adapter in the engines' own venv (Genesis in its own: ``make genesis``) (docs/engines.md).

``--engine newton`` or ``--engine mujoco`` registers one (``load_engine``); its models are then named like
the built-in ones (``newton-vbd``, ``mujoco-flex``). An adapter is a script in ``adapters/`` that reads the
exported scene and writes its answer; it runs in ``.venv-engines`` (``make engines``: newton, warp and
MuJoCo from PyPI with their own numpy, so that the project's stays Debian's), or in the Python
``TISSUEBENCH_ENGINES_PYTHON`` names. The harness passes the knobs a run asks for (``dt``, and in
``options``: ``iterations``, ``substeps``, warp's ``device``) on its command line, and reads back what the adapter reports:
the step it took, its steps, its own step time, whether it diverged or did not settle, and which of the
engine's laws it mapped the scene's to (the row's ``engine``).

Their runs are cached like the built-in models' (the adapters and their pinned versions are in the key,
``verification.cache.RUN_CODE``).
"""

from __future__ import annotations

import os
import re
import sys
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from realtime import DivergenceError, NotConvergedError
from realtime.errors import InputError, ModelRestriction

from .command import TIMEOUT, CommandSimulation
from .protocol import SceneInputs, Settling, foreign_spec
from .served import served_call

ROOT = Path(__file__).resolve().parents[2]
#: Where the adapters are (each runs in its engine's venv: ``AdapterEngine.venv``).
ADAPTERS_DIR = ROOT / "adapters"


@dataclass
class AdapterEngine:
    """An engine behind an adapter script: ``solvers`` maps each model's name to the adapter's
    ``--solver``; ``laws`` the law (``realtime.material.LAWS``) each one's elasticity is, as its source
    defines it with the constants the adapter passes; ``knobs`` are the options its command line takes
    besides ``dt``; ``explicit`` names
    the models explicit in the elasticity (their steps are bound by the critical one), ``iterative``
    those with an iteration count; ``rigid`` those whose adapter meets a scene's rigid tools with the
    engine's own contact (``Stepper.set_rigid``); the others are not applicable on a contact scene."""

    name: str
    script: str
    solvers: dict
    knobs: tuple = ()
    laws: dict = field(default_factory=dict)
    explicit: tuple = ()
    iterative: tuple = ()
    rigid: tuple = ()
    #: the models whose contact acts at the vertices (as the built-in models'): their contact area is
    #: measured from their vertices' gaps to the tool, as the built-in models' (``realtime.contact.areas``)
    vertex_contact: tuple = ()
    #: the device its engine is built for ("cuda": newton and MuJoCo Warp are GPU engines; "cpu": MuJoCo);
    #: a run elsewhere (warp's CPU here, where no CUDA device exists) is said so in its row and on the page
    home_device: str = "cpu"
    #: in ``tissuebench engines`` when no --engine names the adapters (an engine too slow on this machine's
    #: device for a study of many runs is asked for by name)
    default: bool = True
    timeout: float = TIMEOUT
    #: the venv its adapter runs in (under the repository), the make target that builds it, and the
    #: environment variable that names another Python instead
    venv: str = ".venv-engines"
    make_target: str = "engines"
    python_variable: str = "TISSUEBENCH_ENGINES_PYTHON"
    cacheable: bool = True
    isolated: bool = True  # its adapter runs in a process of its own
    #: its adapter serves many runs in one process (``engines.served``); False where a run leaves its engine
    #: in a state the next could see (Genesis's ``gs.init`` once a process, PyBullet's connection a run)
    serves: bool = True
    spec: str = ""
    #: The engine's own warnings the harness knows: a regular expression of the line, and what it means
    #: here. Each is explained once a process, in place of the engine's line and the element line after it.
    known_warnings: tuple = ()
    models: dict = field(init=False)  # each model's name -> its ModelSpec

    def __post_init__(self):
        self.models = {
            m: foreign_spec(m, f"{self.name}'s {solver} solver", own_law=self.laws.get(m))
            for m, solver in self.solvers.items()
        }
        self.spec = self.name

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict):
        self.check_options(model, options)
        return AdapterSimulation(self, inputs, model, dict(options))

    def python(self) -> Path:
        """The Python its adapter runs with: its variable's, else its venv's."""
        return Path(os.environ.get(self.python_variable) or ROOT / self.venv / "bin" / "python")

    def check_options(self, model: str, options: dict) -> None:
        """InputError naming the option and its value where ``options`` are not the knobs this engine takes
        with the values they take (a command refuses them before any truth is solved)."""
        unknown = sorted(set(options) - set(self.knobs) - {"probe"})  # probe: studies.engines' stability test
        if unknown:
            raise InputError(f"{model}: no option {unknown[0]!r}; it takes {', '.join(self.knobs) or 'none'}")
        for key, value in options.items():
            if key == "device" and not (isinstance(value, str) and re.fullmatch(r"cpu|cuda(:\d+)?", value)):
                raise InputError(f"{model}: device = {value!r}: warp's device, cpu, cuda or cuda:N")
            if key == "device":
                continue
            if key in self.knobs and not (isinstance(value, int) and not isinstance(value, bool) and value >= 1):
                raise InputError(f"{model}: {key} = {value!r}: a whole number >= 1")


#: The adapters, by the name ``--engine`` takes.
ADAPTERS = {
    "newton": AdapterEngine(
        "newton",
        "newton_tets.py",
        {"newton-semi-implicit": "semi-implicit", "newton-vbd": "vbd", "newton-xpbd": "xpbd"},
        knobs=("iterations", "substeps", "device"),
        home_device="cuda",
        # newton's tetrahedra (adapters/newton_tets.py): the stable neo-Hookean with its log term (semi-implicit,
        # kernels_particle.eval_tetrahedra) and without it (VBD, particle_vbd_kernels); XPBD's constraints
        # are no hyperelastic law
        laws={"newton-semi-implicit": "stable-neo-hookean", "newton-vbd": "stable-neo-hookean-no-log"},
        explicit=("newton-semi-implicit",),
        iterative=("newton-vbd", "newton-xpbd"),
        rigid=("newton-semi-implicit", "newton-vbd", "newton-xpbd"),
        vertex_contact=("newton-semi-implicit", "newton-vbd", "newton-xpbd"),  # particle-shape contact
        known_warnings=(
            (
                r"^Warp CUDA warning: Could not find or load the NVIDIA CUDA driver",
                "warp finds no CUDA driver on this machine, so newton runs on warp's CPU device only: its step "
                "times here are CPU times, not those of the GPU newton is built for; its answers are the same",
            ),
        ),
    ),
    "mujoco": AdapterEngine(
        "mujoco",
        "mujoco_flex.py",
        {"mujoco-flex": "discrete", "mujoco-flex-euler": "Euler"},
        knobs=("substeps",),
        laws={"mujoco-flex": "stvk", "mujoco-flex-euler": "stvk"},  # its flex's elasticity is StVK
        explicit=("mujoco-flex-euler",),
        rigid=("mujoco-flex", "mujoco-flex-euler"),  # its outer tetrahedra against the geom: no vertex gap to measure
        known_warnings=(
            (
                r"^WARNING: flex '.*' is not rigid and has no equality constraints or passive forces",
                "MuJoCo's compiler warns that the flex is 'not rigid and has no equality constraints or "
                "passive forces': it does not count the flex's own <elasticity>, which is the passive force "
                "that holds it (its answer is P1 StVK to 3e-8, tests/verification/test_adapters_newton_mujoco.py); nothing is wrong",
            ),
            (
                r"^WARNING: Nan, Inf or huge value in Q",
                "MuJoCo warns of NaN, Inf or huge values when a run blows up (its step above the stable one): "
                "the harness stops that run there and its row says diverged",
            ),
        ),
    ),
    "pybullet": AdapterEngine(
        "pybullet",
        "pybullet_tets.py",
        {"pybullet-deformable": "explicit"},
        knobs=("substeps",),
        # Bullet's btDeformableNeoHookeanForce is Smith et al.'s law with its log term (adapters/pybullet_tets.py)
        laws={"pybullet-deformable": "stable-neo-hookean"},
        explicit=("pybullet-deformable",),
        serves=False,
    ),
    "mujoco-warp": AdapterEngine(
        "mujoco-warp",
        "mujoco_warp_flex.py",
        {"mujoco-warp-flex": "discrete", "mujoco-warp-flex-euler": "Euler"},
        knobs=("substeps", "device"),
        home_device="cuda",
        laws={"mujoco-warp-flex": "stvk", "mujoco-warp-flex-euler": "stvk"},  # MuJoCo's flex, in warp
        explicit=("mujoco-warp-flex-euler",),
        # on warp's CPU device a step took 3 ms (Euler) and 60 ms (discrete, CG) on 48 tetrahedra: a study
        # of many runs asks for it by name
        default=False,
        known_warnings=(
            (
                r"^WARNING: flex '.*' is not rigid and has no equality constraints or passive forces",
                "MuJoCo's compiler warns that the flex is 'not rigid and has no equality constraints or "
                "passive forces' before MuJoCo Warp takes the model: the flex's own <elasticity> holds it; nothing "
                "is wrong",
            ),
            (
                r"^Warp CUDA warning: Could not find or load the NVIDIA CUDA driver",
                "warp finds no CUDA driver on this machine, so MuJoCo Warp runs on warp's CPU device only: its "
                "step times here are CPU times, not those of the GPU it is built for; its answers are the same",
            ),
        ),
    ),
    "genesis": AdapterEngine(
        "genesis",
        "genesis_fem.py",
        {
            "genesis-explicit": "explicit-linear",
            "genesis-explicit-snh": "explicit-snh",
            "genesis-implicit": "implicit-linear",
            "genesis-implicit-corotated": "implicit-corotated",
        },
        knobs=("iterations", "substeps"),
        # Genesis's Elastic models (adapters/genesis_fem.py): the small-strain law, and Smith et al.'s with its
        # log term at the matched constants; its corotated linear law is none of the truth's
        laws={"genesis-explicit": "linear", "genesis-explicit-snh": "stable-neo-hookean", "genesis-implicit": "linear"},
        # its implicit solver's Newton iterations a step (the knob "iterations", Genesis's 1 by default) move a
        # relaxation's path, not its fixed point: not studied as VBD's and XPBD's are
        explicit=("genesis-explicit", "genesis-explicit-snh"),
        # PyTorch and Genesis (8.5 GB with the CUDA libraries PyPI's wheels bring) in a venv of their own,
        # built by `make genesis` and never by `make test`: a study asks for it by name
        venv=".venv-genesis",
        make_target="genesis",
        python_variable="TISSUEBENCH_GENESIS_PYTHON",
        default=False,
        serves=False,
        known_warnings=(
            (
                r"is not a recognized feature for this target \(ignoring feature\)",
                "Genesis's kernel compiler (quadrants, on LLVM) names CPU features this LLVM does not know "
                "(avx512er, avx512pf, prefetchwt1) and ignores them; nothing is wrong",
            ),
        ),
    ),
}

#: The warnings already explained in this process (one explanation each, not one a run).
_EXPLAINED: set = set()


def engines_python() -> Path:
    """The Python the engines' venv's adapters run with: ``TISSUEBENCH_ENGINES_PYTHON``, else
    ``.venv-engines``'s."""
    return ADAPTERS["newton"].python()


def adapter(name: str) -> AdapterEngine:
    """The adapter ``name``, checked runnable; InputError naming what is missing."""
    engine = ADAPTERS[name]
    python = engine.python()
    if not python.exists():
        raise InputError(f"--engine {name}: its venv is not built ({python}): run `make {engine.make_target}`")
    return engine


class AdapterSimulation(CommandSimulation):
    """An adapter's run as a Simulation: the command runs once, with the step the harness asks for (or
    the adapter's own), and its answer is read as a command engine's (``CommandSimulation``)."""

    own_step = True  # with no step asked, the adapter chooses one (not the output interval)

    def __init__(self, engine: AdapterEngine, inputs: SceneInputs, model: str, options: dict):
        super().__init__(engine, inputs, model)
        self.options, self.asked_dt, self.report, self.budget = options, None, {}, None
        self._skip_next = False  # the element line after a known warning
        self.integrator = engine.solvers[model]

    @property
    def label(self) -> str:
        return f"engine {self.engine.name}, model {self.model}"

    def command(self, scene_dir: Path, result: Path) -> list[str]:
        args = [str(self.engine.python()), str(ADAPTERS_DIR / self.engine.script), str(scene_dir), str(result)]
        args += ["--solver", self.engine.solvers[self.model]]
        if self.asked_dt is not None:
            args += ["--dt", repr(float(self.asked_dt))]
        if self.budget is not None:  # a static run: the harness's tolerance (of the load) and step budget
            args += ["--rtol", repr(float(self.budget[0])), "--max-steps", str(int(self.budget[1]))]
        for k, v in sorted(self.options.items()):
            args += [f"--{k}", str(v)]
        return args

    def _call(self, args: list[str], cwd: str) -> tuple[int, str]:
        if not self.engine.serves:
            return super()._call(args, cwd)
        return served_call(args, self.engine.timeout, self.relay, self.label)

    def failed(self, status: int, last: str) -> None:
        """An adapter exits 2 with one line when its engine cannot represent the scene (several
        materials for MuJoCo's one flex elasticity, a law it has no match for): that model's answer,
        "not applicable" with the reason in a study of many (``ModelRestriction``); else CommandError."""
        if status == 2 and last:
            raise ModelRestriction(last)  # the adapter's line names it and the reason
        super().failed(status, last)

    def relay(self, line: str) -> None:
        """A line the adapter wrote on stderr: a warning the harness knows is explained once (and the
        engine's element line after it dropped); the adapter's progress is passed on as it is, and any
        other line (the engine's own) named as the engine's."""
        if self._skip_next and line.startswith("Element name "):
            self._skip_next = False
            return
        self._skip_next = False
        if not line.strip():
            return
        for pattern, meaning in self.engine.known_warnings:
            if re.search(pattern, line):
                self._skip_next = True
                if pattern not in _EXPLAINED:
                    _EXPLAINED.add(pattern)
                    print(f"{self.engine.name}: {meaning}", file=sys.stderr, flush=True)
                return
        ours = line.startswith(Path(self.engine.script).stem)  # the adapter's own progress names itself
        print(line if ours else f"{self.engine.name} (the engine's own output): {line}", file=sys.stderr, flush=True)

    def _read(self, path: Path) -> tuple:
        with np.load(path) as z:
            self.report = {k: z[k].item() for k in z.files if z[k].ndim == 0}
        r = self.report
        if r.get("diverged"):
            t = r.get("diverged_at")
            raise AdapterDivergence(self.model, int(r.get("steps", 0)), float(r["dt"]), self.integrator, t)
        if r.get("probe"):  # a stability probe's field is no answer
            return None, None, r.get("step_us"), {}
        if r.get("settled") == 0 and r.get("hold_drift") is not None:
            raise NotConvergedError(
                f"{self.label}: no equilibrium at dt = {float(r['dt']):.3g} s: its relaxed state, released from "
                f"rest, moves {float(r['hold_drift']):.2g} of its displacement in {int(r['hold_steps'])} steps (adapters/exported.py)"
            )
        if r.get("settled") == 0:
            limit = f" (its {r['wall_limit']:g} s)" if r.get("wall_limit") else ""
            raise NotConvergedError(
                f"{self.label}: not settled in {int(r['steps'])} steps of {float(r['dt']):.3g} s{limit} "
                "(adapters/exported.py, relax)"
            )
        return super()._read(path)

    def probe(self, dt: float, steps: int) -> dict:
        """Whether ``dt`` is a stable step here: ``steps`` plain steps from rest under the scene's loads
        (adapters/exported.py, probe). Returns dt, stable (bool), and for an unstable step the step and
        time it blew up at."""
        self.options["probe"], self.asked_dt = steps, dt
        try:
            self._run()
        except AdapterDivergence as exc:
            return {"dt": dt, "stable": False, "step": exc.step, "steps": steps}
        return {"dt": dt, "stable": True, "steps": steps, "step_us": self.report.get("step_us")}

    @property
    def dt(self) -> float | None:
        return self.report.get("dt")

    def contact_area(self) -> np.ndarray | None:
        """(K,) m^2: each rigid tool's contact area on the answer, where the engine's contact acts at the
        vertices (``AdapterEngine.vertex_contact``), measured as the built-in models' is; None (unknown)
        where it acts on elements, whose vertices a tool touches without entering (MuJoCo's flex)."""
        if self.model not in self.engine.vertex_contact:
            return None
        from realtime.contact import areas

        return areas(self.inputs.loading.contacts, self.inputs.points, self.displacement(), np.inf)

    @property
    def info(self) -> dict:
        """What the run was: the engine and its version, the law the scene's was mapped to, the knobs."""
        self._run()
        r = self.report
        keep = ("engine", "law", "iterations", "substeps", "stalled_at", "residual", "tail_omega", "tail_steps")
        keep += ("hold_drift", "device", "budget_spent", "fixed_point")
        return {k: r[k] for k in keep if k in r}

    def start(self, dt) -> None:
        super().start(dt)
        if dt is not None:
            self.asked_dt = dt

    def settle(self, rtol, max_steps, dt, dt_fraction) -> Settling:
        if dt is not None:
            self.asked_dt = dt
        if dt_fraction is not None:
            raise InputError(f"{self.label}: its steps are its own: give dt in seconds, not a fraction")
        self.budget = (rtol, max_steps)
        s = super().settle(rtol, max_steps, dt, dt_fraction)
        r = self.report
        static = {
            "method": "dynamic relaxation with kinetic damping (adapters/exported.py)",
            "steps": int(r["steps"]),
            "residual": None,
            "wall_s": s.wall_s,
        }
        return Settling(int(r["steps"]), None, float(r["dt"]), None, s.wall_s, static)


class AdapterDivergence(DivergenceError):
    """An adapter's run that blew up (non-finite, or over 10 times the body): the step, dt and the time;
    ``solver``, the engine's solver that ran."""

    def __init__(self, model: str, step: int, dt: float, integrator: str, t):
        self.step, self.dt, self.dt_crit, self.reason, self.solver = step, dt, None, "", integrator
        when = f" (t = {t:.4g} s)" if t is not None else ""
        RuntimeError.__init__(self, f"{model} with {integrator} diverged at step {step}{when}: dt = {dt:.4g} s")
