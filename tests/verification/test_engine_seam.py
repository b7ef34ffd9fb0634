"""The engine seam (docs/seam.md): the built-in engine answers the protocol, and an
engine no study knows, registered beside it, is run and judged by the same calls."""

import json
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import scipy.sparse.linalg as spla

from realtime import build_model
from realtime.errors import InputError
from verification import engines
from verification.cli import main
from verification.engines.builtin import BUILTIN
from verification.engines.protocol import Engine, SceneInputs, Settling, Simulation
from verification.inputs import scene_inputs
from verification.runs.compare import compare
from verification.runs.simulate import run_model
from verification.scene_file import load_scene

#: The examples, an engine of a user's among them (direct_p1.py).
EXAMPLES = Path(__file__).resolve().parents[2] / "examples"


class DirectP1:
    """A plug-in engine: the P1 linear-elastic equilibrium by one sparse solve (what a settled
    linear-tm reaches by damped dynamics), built from the scene's arrays alone."""

    name = "direct-p1"
    models = ("direct-p1",)

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict):
        return _DirectSimulation(inputs)


class _DirectSimulation:
    model, integrator, timing = "direct-p1", "sparse LU", (3, 3)

    def __init__(self, inputs: SceneInputs):
        self.inputs = inputs
        self.u = np.zeros_like(inputs.points)

    def critical_dt(self):
        return None

    def start(self, dt):
        self.u[:] = 0.0

    def advance_to(self, t):
        raise NotImplementedError("a static engine")

    def settle(self, rtol, max_steps, dt, dt_fraction):
        i = self.inputs
        linear = build_model("linear-tm", i.points, i.tets, i.material.replace(law="linear"), i.loading)
        free = np.flatnonzero(i.loading.free.reshape(-1) != 0.0)
        K = linear.rest_stiffness()[free][:, free].tocsc()
        self.u.reshape(-1)[free] = spla.spsolve(K, i.loading.external_force.reshape(-1)[free])
        self.reaction = linear.reaction(self.u)
        return Settling(1, None, None, None, 0.0, {"method": "sparse LU", "steps": 1})

    def step(self, n):
        pass

    def step_us(self):
        return None  # timed by the harness

    def displacement(self):
        return self.u

    def tool_force(self):
        return self.reaction


def test_a_command_leaves_no_plug_in_behind():
    """The plug-ins a command names are registered for that command only: the next one, in the same
    process (a test, a notebook), sees the built-in engine alone, and the default time bound."""
    from verification.runs import simulate

    main(
        [
            "run",
            "cantilever",
            "--engine",
            "tests.verification.test_engine_seam:DirectP1",
            "--engine-timeout",
            "5",
            "--model",
            "nope",
        ]
    )
    assert set(engines.ENGINES) == {"realtime"} and simulate.PLUG_IN_TIMEOUT == 600.0


def test_the_builtin_engine_answers_the_protocol():
    scene = load_scene("cantilever")
    inputs = scene_inputs(scene)
    assert isinstance(BUILTIN, Engine) and set(engines.ENGINES) == {"realtime"}
    sim = BUILTIN.build(inputs, "linear-tm", "symplectic-euler", {})
    assert isinstance(sim, Simulation)
    # the scene's arrays as the protocol documents them
    assert inputs.points.shape == (scene.mesh.n_vertices, 3) and inputs.points.dtype == np.float64
    assert inputs.tets.shape == (scene.mesh.n_tets, 4) and inputs.loading.free.shape == inputs.points.shape
    assert inputs.sha256 == scene.sha256() and inputs.source == str(scene.path)


def test_an_unknown_model_names_the_engines_models():
    with pytest.raises(InputError, match=r"no engine offers 'nope'; the models are .*linear-tm"):
        engines.engine_for("nope")


def test_a_plug_in_engine_is_run_and_judged_through_the_seam(monkeypatch):
    """A linear static scene: the plug-in's direct P1 solve and linear-tm settled by damped dynamics
    (rtol 1e-10) are one linear system, so compare gives both the same error against the reference, to
    the settling's tolerance (1e-7 of the error, far above 1e-10 of the load)."""
    monkeypatch.setitem(engines.ENGINES, "direct-p1", DirectP1())
    scene = load_scene("cantilever").with_material(law="linear")
    res = run_model(scene, "direct-p1")
    assert res.meta["solver"] == "direct-p1" and res.meta["model"] == "direct-p1"
    assert res.meta["integrator"] == "sparse LU"
    assert res.meta["static"]["method"] == "sparse LU" and res.meta["step_us"] > 0.0
    ours = compare(scene, "linear-tm", degree=1, budget=False)
    theirs = compare(scene, "direct-p1", degree=1, budget=False)
    assert theirs.status == "ok" and theirs.rel_l2 > 0.0
    assert theirs.rel_l2 == pytest.approx(ours.rel_l2, rel=1e-7)


class _Spoilt(DirectP1):
    """DirectP1 whose answer a subclass spoils, as a faulty engine would."""

    name = "spoilt"
    models = ("spoilt",)

    def build(self, inputs, model, integrator, options):
        sim = super().build(inputs, model, integrator, options)
        settle = sim.settle

        def spoilt(*args):
            out = settle(*args)
            sim.u = self.spoil(sim.u)
            return out

        sim.settle = spoilt
        return sim


class Crashes(_Spoilt):
    def spoil(self, u):
        raise ZeroDivisionError("the plug-in's own bug")


class WritesNaN(_Spoilt):
    def spoil(self, u):
        u = u.copy()
        u[3, 1] = np.nan
        return u


class WrongShape(_Spoilt):
    def spoil(self, u):
        return u[:-1]


class InMillimetres(_Spoilt):
    def spoil(self, u):
        return u * 1e3


class Hangs(_Spoilt):
    def spoil(self, u):
        time.sleep(60)  # past any bound a test gives it
        return u


class Segfaults(_Spoilt):
    def build(self, inputs, model, integrator, options):
        import ctypes

        ctypes.string_at(0)  # reads address 0: the interpreter dies of SIGSEGV, at once


class HangsInC(_Spoilt):
    def spoil(self, u):
        import numba

        @numba.njit
        def spin(n):  # compiled: no Python bytecode for a signal handler to interrupt
            k = 0
            while n > 0:
                k = (k + 1) % 7
            return k

        spin(1)
        return u


class Diverges(_Spoilt):
    def spoil(self, u):
        from realtime import DivergenceError

        raise DivergenceError("spoilt", 12, 1e-4, 2e-4, "its own integrator")


class NotAnEngine:
    name = "not-an-engine"


def test_a_plug_in_engine_named_on_the_command_line(monkeypatch, capsys):
    """--engine MODULE:CLASS makes its models runnable by every model command, judged as the built-in ones."""
    monkeypatch.setattr(engines, "ENGINES", dict(engines.ENGINES))
    args = ["compare", "cantilever", "--degree", "1", "--json"]  # gravity: the direct solve's load
    assert main([*args, "--engine", "tests.verification.test_engine_seam:DirectP1", "--model", "direct-p1"]) == 0
    theirs = json.loads(capsys.readouterr().out)
    assert main([*args, "--model", "linear-tm"]) == 0
    ours = json.loads(capsys.readouterr().out)
    # the direct solve and linear-tm settled are one linear system: the same error against the same truth
    assert theirs["status"] == "ok" and theirs["rel_l2"] == pytest.approx(ours["rel_l2"], rel=1e-6)


@pytest.mark.parametrize(
    "spec, needles",
    [
        ("nosuch.module:Engine", ("--engine nosuch.module:Engine: cannot import nosuch.module",)),
        ("tests.verification.test_engine_seam:Nope", ("tests.verification.test_engine_seam has no Nope",)),
        ("tests.verification.test_engine_seam:NotAnEngine", ("NotAnEngine is not an engine: it has no models, build",)),
        (
            "tests.verification.test_engine_seam:Crashes",
            ("engine spoilt, model spoilt: ZeroDivisionError: the plug-in's own bug",),
        ),
        (
            "tests.verification.test_engine_seam:WritesNaN",
            ("engine spoilt, model spoilt: its displacement[0, 3, 1] is nan",),
        ),
        ("tests.verification.test_engine_seam:WrongShape", ("its displacement is (1, 553, 3), not (1, 554, 3)",)),
        ("tests.verification.test_engine_seam:InMillimetres", ("over 10 times the body", "is it in metres?")),
        (
            "tests.verification.test_engine_seam:Hangs",
            ("engine spoilt, model spoilt: still running after 1 s, stopped",),
        ),
        (
            "tests.verification.test_engine_seam:HangsInC",
            ("engine spoilt, model spoilt: still running after 1 s, stopped",),
        ),
        (
            "tests.verification.test_engine_seam:Segfaults",
            ("engine spoilt, model spoilt: its process died (signal SIGSEGV)",),
        ),
    ],
)
def test_a_faulty_plug_in_is_one_line_and_exit_2(monkeypatch, capsys, spec, needles):
    monkeypatch.setattr(engines, "ENGINES", dict(engines.ENGINES))
    # 1 s stops the hanging plug-ins; the others' child settles the cantilever, over 1 s on a loaded machine
    timeout = "1" if "Hangs" in spec else "60"
    code = main(["run", "cantilever", "--engine", spec, "--engine-timeout", timeout, "--model", "spoilt"])
    _one_line_exit_2(code, capsys.readouterr().err, needles)


def _one_line_exit_2(code: int, err: str, needles) -> None:
    """Exit status 2 and one line of the tool's on stderr, holding every needle, never a traceback."""
    assert code == 2 and "Traceback" not in err
    lines = [line for line in err.splitlines() if line.startswith("tissuebench")]
    assert len(lines) == 1, err
    for n in needles:
        assert n in lines[0], lines[0]


def test_a_plug_in_that_diverges_is_a_diverged_row(monkeypatch):
    """A plug-in's DivergenceError comes back from its worker process with its step and steps: compare
    makes it a "diverged" row, as it does the built-in models' (the run, not the harness, failed)."""
    monkeypatch.setattr(engines, "ENGINES", dict(engines.ENGINES))
    engines.load_engine("tests.verification.test_engine_seam:Diverges")
    row = compare(load_scene("cantilever"), "spoilt", budget=False)
    assert row.status == "diverged" and row.step == 12 and row.dt == 1e-4 and row.dt_crit == 2e-4
    assert "diverged at step 12" in row.message


DIRECT_P1 = f"{sys.executable} {EXAMPLES / 'direct_p1.py'} {{scene}} {{result}}"


def test_an_engine_in_another_process_is_judged_through_the_seam(capsys):
    """A command that reads the exported scene and writes its answer (examples/direct_p1.py: P1
    assembled and solved with numpy and scipy, nothing of the project imported): on cantilever-pull, a
    tool-driven static scene, its error against the reference is linear-tm's settled one (one linear
    system, to the settling's 1e-10 of the load), and its own step time is reported as the engine's."""
    args = ["compare", "cantilever-pull", "--degree", "1", "--json"]
    assert main([*args, "--engine-cmd", DIRECT_P1, "--model", "numpy-p1"]) == 0
    theirs = json.loads(capsys.readouterr().out)
    assert main([*args, "--model", "linear-tm"]) == 0
    ours = json.loads(capsys.readouterr().out)
    assert theirs["status"] == "ok" and theirs["rel_l2"] == pytest.approx(ours["rel_l2"], rel=1e-6)
    assert theirs["step_us"] > 0.0 and theirs["integrator"] == "the command's own"


STATED_STEPS = """
import ast, subprocess, sys
import numpy as np
scene, result, steps, direct = sys.argv[1:5]
subprocess.run([sys.executable, direct, scene, result], check=True)
with np.load(result) as z:
    out = dict(z)
out["steps"] = np.asarray(ast.literal_eval(steps))  # the test's literal: 400, or a bad value
out["step_us"] = out["step_us"] / float(out["steps"])  # its solve's time, as 400 steps of it
np.savez(result, **out)
"""


def test_an_engine_commands_settling_steps_are_charged_to_its_frames(tmp_path, capsys):
    """A command whose result file says its static answer took 400 steps (``steps``, each a 400th of its
    solve's time) is costed as 400 updates of its step time: frames of steps, and the answer after 400
    of them; the same command
    without ``steps`` is one update a frame, as before. A ``steps`` that is no whole number is one
    line."""
    script = tmp_path / "steps.py"
    script.write_text(STATED_STEPS)
    direct = EXAMPLES / "direct_p1.py"
    args = ["compare", "cantilever-pull", "--degree", "1", "--rate", "60", "--json", "--model", "numpy-p1"]
    assert main([*args, "--engine-cmd", f"{sys.executable} {script} {{scene}} {{result}} 400 {direct}"]) == 0
    stated = json.loads(capsys.readouterr().out)
    assert main([*args, "--engine-cmd", DIRECT_P1]) == 0
    silent = json.loads(capsys.readouterr().out)
    assert stated["settle_steps"] == 400 and silent["settle_steps"] == 1
    frame, one = stated["frame"], silent["frame"]
    assert one["steps_per_frame"] == 1 and "one update" in one["why"]
    assert frame["time_to_answer_s"] == pytest.approx(400 * stated["step_us"] * 1e-6)
    assert "settles in 400 steps" in frame["why"]
    code = main([*args, "--engine-cmd", f"{sys.executable} {script} {{scene}} {{result}} 2.5 {direct}"])
    _one_line_exit_2(code, capsys.readouterr().err, ("steps = ", "2.5", "is not a whole number of steps"))


@pytest.mark.parametrize(
    "command, needles",
    [
        ("no-such-program {scene}", ("no such program 'no-such-program'",)),
        (f"{sys.executable} -c 'import sys; sys.exit(\"it broke\")'", ("exited with status 1: it broke",)),
        (f"{sys.executable} -c 'import time; time.sleep(30)'", ("still running after 1 s, stopped",)),
        (f"{sys.executable} -c 'pass'", ("wrote no {result} file",)),
        (
            f"{sys.executable} -c 'import numpy, sys; numpy.savez(sys.argv[1], displacement=numpy.zeros((3, 3)))' {{result}}",
            ("result.npz: displacement must be (554, 3) or (T, 554, 3) for its 554 points, got (1, 3, 3)",),
        ),
        (  # the right shape on other points: it read "its displacement is (1, 554, 3), not (1, 554, 3)"
            f"{sys.executable} -c 'import numpy as n, sys; n.savez(sys.argv[1], displacement=n.zeros((554, 3)), "
            f"points=n.ones((554, 3)))' {{result}}",
            ("its points are not the scene's vertices: point ", "write the answer on the exported mesh's vertices"),
        ),
    ],
)
def test_a_failing_command_engine_is_one_line_and_exit_2(capsys, command, needles):
    code = main(["run", "cantilever", "--engine-cmd", command, "--engine-timeout", "1", "--model", "cmd-model"])
    _one_line_exit_2(code, capsys.readouterr().err, needles)


def test_the_advisor_judges_a_plug_in_as_it_judges_the_built_in_models(monkeypatch):
    """advise with a plug-in engine: the plug-in is a candidate like a built-in model, named with its
    measured step, its error and why it qualifies or not; its runs are not cached (their code is not in
    the key)."""
    from verification.studies.advise import advise

    monkeypatch.setattr(engines, "ENGINES", dict(engines.ENGINES))
    engines.ENGINES["direct-p1"] = DirectP1()
    scene = load_scene("cantilever")
    out = advise(scene, tol=0.5, rate=60.0, models=("direct-p1",))  # a tolerance its P1 error meets
    (plug,) = [c for c in out["candidates"] if c["model"] == "direct-p1"]
    assert plug["step_us"] > 0.0 and plug["why"].startswith("direct-p1 (sparse LU)")
    ours = compare(scene, "linear-tm", budget=False)  # one linear system: the same error
    assert plug["rel_l2"] == pytest.approx(ours.rel_l2, rel=1e-6)
    # its step (a no-op: the answer came from one solve) fits any frame, so the tolerance alone decides
    assert plug["qualifies"] == (plug["rel_l2"] <= 0.5) and plug["qualifies"], plug["why"]
    assert out["model"] == "direct-p1" and out["refine"] == 0 and "--engine" not in out["command"]


def test_gates_hold_a_plug_in_engine_and_a_result_file(tmp_path, monkeypatch):
    """A gate on a plug-in engine's model and one on a result file another code wrote: both measured
    (the same error as linear-tm's, one linear system), and a bound below it fails, saying by how much."""
    from verification.studies.gates import run_gates

    monkeypatch.setattr(engines, "ENGINES", dict(engines.ENGINES))
    scene = load_scene("cantilever")
    np.savez(tmp_path / "theirs.npz", displacement=run_model(scene, "linear-tm").displacement[0])
    (tmp_path / "gates.toml").write_text(
        """
[[gate]]
scene = "cantilever"
model = "direct-p1"
engine = "tests.verification.test_engine_seam:DirectP1"
metric = "rel_l2"
bound = 1.0

[[gate]]
scene = "cantilever"
model = "their-code"
result = "theirs.npz"
metric = "rel_l2"
bound = 1.0

[[gate]]
scene = "cantilever"
model = "their-code"
result = "theirs.npz"
metric = "rel_l2"
bound = 1e-9
"""
    )
    plug, result, strict = run_gates(tmp_path / "gates.toml", use_cache=False, baselines=False)
    assert plug["passed"] and result["passed"] and not strict["passed"]
    assert plug["value"] == pytest.approx(result["value"], rel=1e-6) and result["integrator"] == "result file"
    assert "exceeds the bound 1e-09" in strict["why"]


#: direct_p1's answer spoilt the ways a user's engine spoils it: written in mm, with the tool's vertices
#: where a stale export put them (its motion halved), with a held vertex moved.
SPOIL = """
import subprocess, sys
import numpy as np
scene, result, how = sys.argv[1:4]
subprocess.run([sys.executable, sys.argv[4], scene, result], check=True)
z = dict(np.load(result))
u = z["displacement"]
a = np.load(scene + "/arrays.npz")
if how == "mm":
    u = u * 1000.0
elif how == "stale":
    u[..., a["tool_vertex"], :] *= 0.5
else:
    held = np.flatnonzero((a["free"] == 0.0).all(axis=1) & ~np.isin(np.arange(len(a["points"])), a["tool_vertex"]))
    u[..., held[0], :] += 0.001
z["displacement"] = u
np.savez(result, **z)
"""


@pytest.mark.parametrize(
    "how, needles",
    [
        ("mm", ("its tools' vertices moved 1000 times as far as the scene moves them: lengths in millimetres?",)),
        ("stale", ("the tool's vertex ", "from where the scene puts it", "a stale export")),
        ("held", ("moved 0.001 m in x (output 0), which the scene holds at 0", "another frame")),
    ],
)
def test_an_engine_commands_answer_is_checked_against_the_scene_before_it_is_scored(tmp_path, capsys, how, needles):
    """--engine-cmd's answer passes judge's checks before any number: an answer in mm, one whose tool is
    where a stale export put it, one that moved a held vertex; each is one line naming the likely cause,
    exit 2 (the same engine unspoilt scores linear-tm's error, test above)."""
    spoil = tmp_path / "spoil.py"
    spoil.write_text(SPOIL)
    direct = EXAMPLES / "direct_p1.py"
    command = f"{sys.executable} {spoil} {{scene}} {{result}} {how} {direct}"
    code = main(["compare", "cantilever-pull", "--degree", "1", "--engine-cmd", command, "--model", "numpy-p1"])
    _one_line_exit_2(code, capsys.readouterr().err, needles)
