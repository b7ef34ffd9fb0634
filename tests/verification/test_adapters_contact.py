"""A rigid tool through the seam: each adapter meets the scene's rigid tools with its engine's own contact
(docs/engines.md, "Rigid tools"), moved by the shared driver and judged like the built-in models'."""

import json

import numpy as np
import pytest

from tests.reference.test_contact import BLOCK, PLANE
from verification.cli import main

from .test_adapters_newton_mujoco import SIDE, E, _uniaxial_export, needs_engines, run_adapter

#: The plane's gap above the top at t = 0 and how far it presses past it, m: a strain of 1e-3.
GAP, PRESS = 1e-4, 1e-5


def _pressed_block(directory):
    """The uniaxial block of the adapters' constants test without its traction, pressed instead by a
    rigid plane on its whole top: uniaxial stress again, F = E A d / L whatever the law at a strain of 1e-3."""
    points = _uniaxial_export(directory)
    spec = json.loads((directory / "scene.json").read_text())
    spec["rigid_tools"] = [
        {
            "shape": "plane",
            "center_m": [0.0, 0.0, SIDE + GAP],
            "normal": [0.0, 0.0, -1.0],
            "travel_m": [0.0, 0.0, -(GAP + PRESS)],
            "ramp_s": 0.0,
            "ramp_shape": "linear",
            "friction": 0.0,
        }
    ]
    (directory / "scene.json").write_text(json.dumps(spec))
    with np.load(directory / "arrays.npz") as z:
        arrays = {k: z[k] for k in z.files}
    arrays["external_force"] = np.zeros_like(arrays["external_force"])
    np.savez(directory / "arrays.npz", **arrays)
    return points


@needs_engines
@pytest.mark.parametrize(
    "script, solver, dt, sink",
    [
        ("mujoco_flex.py", "discrete", 1e-3, (0.01, 0.03)),  # MuJoCo's 1 ms: the plane sinks 1.9 % of the press
        ("mujoco_flex.py", "discrete", 1e-4, (0.0, 0.005)),  # at 0.1 ms, 0.17 %: its soft constraint stiffens
        ("mujoco_flex.py", "Euler", None, (0.0, 0.005)),  # the explicit flex at its own stable step: 0.25 %
        ("newton_tets.py", "semi-implicit", None, (0.0, 0.02)),  # newton's penalty ke = 100 E h: 0.63 % (float32)
        ("newton_tets.py", "vbd", 1e-4, (0.0, 0.02)),  # the same penalty, implicit: 0.37 %
    ],
)
def test_an_engines_contact_presses_a_block_by_the_planes_travel_less_its_softness(tmp_path, script, solver, dt, sink):
    """An engine's own contact against a plane moved onto the block: uniaxial stress, whose force E A d / L
    and top displacement -d the engine meets less what its contact lets the plane sink into it (MuJoCo's
    soft constraint, whose time constant is two steps: the sink falls with the step; newton's penalty). The
    force is the engine's contact force, and the result's reaction is that force (no vertex tool here)."""
    points = _pressed_block(tmp_path / "scene")
    step = ["--dt", str(dt)] if dt else []
    u, report, arrays = run_adapter(tmp_path, script, solver, "--rtol", "1e-9", *step)
    assert report["settled"] == 1
    force = arrays["rigid_force"]
    assert force.shape == (1, 3) and np.abs(force[0, :2]).max() < 1e-6 * abs(force[0, 2])  # frictionless, square
    lost = 1.0 + force[0, 2] / (E * SIDE * PRESS)  # the force's shortfall: the sink over the press
    assert sink[0] <= lost <= sink[1], lost
    # the top where the force says it is, on average: MuJoCo's contacts act at points of the outer
    # elements, not on the face as a traction, and tilt the top by up to 2.0 % of the press (measured, 1 ms)
    top = u[points[:, 2] > SIDE - 1e-12, 2]
    assert top.mean() == pytest.approx(-PRESS * (1.0 - lost), rel=0.01)
    assert np.ptp(top) < 0.03 * PRESS
    np.testing.assert_allclose(arrays["reaction"], force[0], rtol=1e-12)


@pytest.mark.slow
@needs_engines
def test_compare_judges_each_engines_contact_as_the_built_in_models(tmp_path, capsys):
    """tissuebench compare on the plane press (tests/reference/test_contact.py) through each engine, judged
    as linear-tm is: its tool force against the truth's (reaction_rel_err measured 0.039 MuJoCo's StVK,
    0.107 newton's neo-Hookean, 0.085 linear-tm), and its distance from the P1 solution of its own law with
    the truth's contact on the same mesh, its numerics and its contact alone (measured 4.7e-3 and 2.7e-3,
    below the mesh's own 0.055: the bound 0.01). newton's contact area is measured from its vertices' gaps
    (the whole top, as linear-tm's); MuJoCo's, on its elements, is unknown."""
    path = tmp_path / "press.toml"
    path.write_text(BLOCK + PLANE)
    rows = {}
    for engine, model in (("mujoco", "mujoco-flex"), ("newton", "newton-semi-implicit")):
        assert main(["compare", str(path), "--degree", "1", "--json", "--model", model, "--engine", engine]) == 0
        rows[model] = json.loads(capsys.readouterr().out)
    for model in ("mujoco-flex", "newton-semi-implicit"):
        row = rows[model]
        assert 0.0 < row["reaction_rel_err"] < 0.2 and row["own_law"]["rel_l2"] < 0.01, row
        assert row["error_budget"]["dominant"] == "mesh", row
    assert rows["newton-semi-implicit"]["contact"][0]["area"] == pytest.approx(0.0016, rel=1e-3)
    assert rows["mujoco-flex"]["contact"][0]["area"] is None
