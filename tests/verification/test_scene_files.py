"""Scene files: the built-ins load; every bad value fails with one line naming file and key, status 2."""

import textwrap

import numpy as np
import pytest

from verification.cli import main
from verification.scene import SceneError
from verification.scene_file import builtin_scenes, load_scene

GOOD = textwrap.dedent("""
    name = "t"
    [mesh]
    generator = "box"
    size = [0.1, 0.02, 0.02]
    h = 0.005
    [material]
    law = "linear"
    young = 5.0e5
    poisson = 0.45
    density = 1000.0
    [[fixed]]
    box = [[-1e-9, -1.0, -1.0], [1e-9, 1.0, 1.0]]
    [[load]]
    kind = "gravity"
    value = [0.0, 0.0, -9.81]
""")


def write(tmp_path, text):
    p = tmp_path / "scene.toml"
    p.write_text(text)
    return p


def test_builtin_scenes_load():
    names = set(builtin_scenes())
    assert {"cantilever", "cantilever-pull"} <= names
    for name in names:
        scene = load_scene(name)
        assert scene.mesh.n_tets > 0


def test_good_scene(tmp_path):
    s = load_scene(write(tmp_path, GOOD))
    assert s.material.lam > 0 and len(s.problem.fixed) == 1


BAD = [
    ("poisson = 0.45", "poisson = 0.5", "material.poisson"),
    ('kind = "gravity"', 'kind = "magnetic"', "load[0].kind"),
    ("box = [[-1e-9, -1.0, -1.0], [1e-9, 1.0, 1.0]]", "box = [[5.0, 5.0, 5.0], [6.0, 6.0, 6.0]]", "fixed[0].box"),
    ("density = 1000.0", "density = 1000.0\ncolour = 3", "material.colour"),
    ("young = 5.0e5\n", "", "material.young"),
    ('generator = "box"', 'generator = "sphere"', "mesh.generator"),
    ("h = 0.005", 'h = "fine"', "mesh.h"),
    ("value = [0.0, 0.0, -9.81]", "value = [0.0, -9.81]", "load[0].value"),
    (
        "density = 1000.0",
        "density = 1000.0\nfiber_around = { axis = [0.0, 0.0, 0.0] }\nyoung_fiber = 1e6",
        "material.fiber_around.axis",
    ),
    (
        "density = 1000.0",
        "density = 1000.0\nfiber = [1.0, 0.0, 0.0]\nfiber_around = { axis = [0.0, 0.0, 1.0] }\nyoung_fiber = 1e6",
        "material.fiber_around",
    ),
    (
        "density = 1000.0",
        "density = 1000.0\nfiber_around = { axis = [0.0, 0.0, 1.0], centre = [0.0, 0.0, 0.0] }\nyoung_fiber = 1e6",
        "material.fiber_around.centre",
    ),
]


@pytest.mark.parametrize("old, new, key", BAD, ids=[b[2] for b in BAD])
def test_bad_scene_is_one_line_naming_file_and_key(tmp_path, capsys, old, new, key):
    assert old in GOOD
    path = write(tmp_path, GOOD.replace(old, new))
    with pytest.raises(SceneError, match=key.replace("[", r"\[").replace("]", r"\]")):
        load_scene(path).mesh  # noqa: B018  (regions are checked against the mesh)
    assert main(["compare", str(path), "--model", "linear-tm"]) == 2
    err = capsys.readouterr().err.strip()
    assert "\n" not in err and str(path) in err and key in err


def test_error_lists_allowed_values(tmp_path):
    with pytest.raises(SceneError, match="gravity, force, traction, displacement"):
        load_scene(write(tmp_path, GOOD.replace('kind = "gravity"', 'kind = "magnetic"')))


def test_fixed_and_tool_overlap_is_an_error(tmp_path):
    text = GOOD + textwrap.dedent("""
        [[load]]
        kind = "displacement"
        box = [[-1.0, -1.0, -1.0], [0.01, 1.0, 1.0]]
        value = [0.0, 0.0, 0.001]
    """)
    with pytest.raises(SceneError, match=r"load\[1\].*drives component x of vertex"):
        load_scene(write(tmp_path, text)).mesh  # noqa: B018


def test_unknown_scene_name():
    with pytest.raises(SceneError, match="not a built-in scene"):
        load_scene("no-such-scene")


TOOL = GOOD.replace(
    'kind = "gravity"\nvalue = [0.0, 0.0, -9.81]',
    'kind = "displacement"\nbox = [[0.0999, -1.0, -1.0], [1.0, 1.0, 1.0]]\nvalue = [0.0, 0.0, -0.005]\n'
    'ramp = 0.05\nramp_shape = "smooth"',
)
assert TOOL != GOOD


def test_smooth_ramp_reaches_both_ends_at_rest(tmp_path):
    """ramp_shape = "smooth": the tool's fraction is the quintic 10 s^3 - 15 s^4 + 6 s^5, whose
    velocity and acceleration vanish at both ends; the scene passes it to the reference's tool and to
    the real-time models' alike (one function: realtime.ramps.ramp_fraction)."""
    from verification.engines.builtin import scene_model

    scene = load_scene(write(tmp_path, TOOL))
    tool = scene.problem.tools[0]
    assert tool.ramp_shape == "smooth"
    t = 0.05 * np.array([0.0, 1e-3, 0.5, 1 - 1e-3, 1.0, 2.0])
    s = np.array([tool.fraction(x) for x in t])
    # the quintic at these points, exactly; near the ends it moves as 10 s^3 (zero velocity and
    # acceleration). A few operations in double precision: round-off
    np.testing.assert_allclose(
        s, [0.0, 1e-8 - 1.5e-11 + 6e-15, 0.5, 1 - 1e-8 + 1.5e-11 - 6e-15, 1.0, 1.0], rtol=1e-13, atol=1e-24
    )
    model = scene_model(scene, "linear-tm")
    assert model.loading.tool_ramp_shape.tolist() == [1]
    np.testing.assert_allclose(model.tool_displacement(0.025)[:, 2], -0.0025, rtol=1e-12)
    with pytest.raises(SceneError, match=r"load\[0\]\.ramp_shape.*'cubic' is not one of linear, smooth"):
        load_scene(write(tmp_path, TOOL.replace('"smooth"', '"cubic"')))
