"""Slitting and suturing a linear tensor-mass model (issue 12): local tensor updates that must equal the
model built from scratch on the changed mesh, and a suture that undoes a slit."""

import numpy as np
import pytest

from meshes import structured_box
from realtime import InputError, Loading, Material, Materials, SymplecticEuler, build_model
from realtime.model import State
from realtime.topology import slit, suture

from ..conftest import assert_same_model

HOST = Material(5e3, 0.45, 1000.0)
STIFF = Material(5e5, 0.3, 1200.0)
#: Two sums of the same blocks in another order (subtracted and added again): a few hundred ulps of the
#: largest force.
ROUND_OFF = 1e-12


def block():
    """A 4 x 2 x 2 cm grid block of two materials, held at x = 0 and pulled by gravity."""
    mesh = structured_box((0.04, 0.02, 0.02), (8, 4, 4))
    x = mesh.points
    free = np.ones_like(x)
    free[x[:, 0] < 1e-9] = 0.0
    loading = Loading(free=free, external_force=np.tile([0.0, 0.0, -1e-3], (len(x), 1)))
    index = (mesh.points[mesh.tets].mean(axis=1)[:, 2] > 0.01).astype(np.int64)
    return mesh, Materials((HOST, STIFF), index), loading


def slit_faces(mesh):
    """The faces on the plane x = 2 cm with y below 1.5 cm: a slit from the face y = 0 into the body."""
    x = mesh.points
    on = (np.abs(x[:, 0] - 0.02) < 1e-9) & (x[:, 1] < 0.015 + 1e-9)
    faces = np.sort(mesh.tets[:, [[1, 2, 3], [0, 3, 2], [0, 1, 3], [0, 2, 1]]].reshape(-1, 3), axis=1)
    faces = np.unique(faces[np.all(on[faces], axis=1)], axis=0)
    assert len(faces) > 10
    return faces


def test_slit_equals_the_model_built_on_the_slit_mesh(rng):
    mesh, materials, loading = block()
    model = build_model("linear-tm", mesh.points, mesh.tets, materials, loading)
    faces = slit_faces(mesh)
    after, pairs = slit(model, faces)
    # the vertices on the slit's inner edge (y = 1.5 cm) have one side and stay whole
    inner = np.unique(faces)[np.abs(mesh.points[np.unique(faces), 1] - 0.015) < 1e-9]
    assert len(pairs) == len(np.unique(faces)) - len(inner)
    assert after.n_vertices == mesh.n_vertices + len(pairs)
    fresh = build_model("linear-tm", after.points, after.tets, after.material, after.loading)
    assert_same_model(after, fresh, rng)
    np.testing.assert_allclose(after.loading.external_force.sum(axis=0), loading.external_force.sum(axis=0))
    # each lip has its own copy: the tetrahedra using a vertex of the slit all lie on one side of it
    side = after.points[after.tets].mean(axis=1)[:, 0] > 0.02
    for v, c in pairs:
        for w in (v, c):
            assert len(np.unique(side[np.any(after.tets == w, axis=1)])) == 1
        assert side[np.any(after.tets == v, axis=1)][0] != side[np.any(after.tets == c, axis=1)][0]


def test_suturing_a_slit_returns_the_original_model(rng):
    mesh, materials, loading = block()
    model = build_model("linear-tm", mesh.points, mesh.tets, materials, loading)
    after, pairs = slit(model, slit_faces(mesh))
    back = suture(after, pairs)
    original = build_model("linear-tm", mesh.points, mesh.tets, materials, loading)  # model's tensors changed
    assert back.n_vertices == original.n_vertices
    assert np.array_equal(back.tets, original.tets)
    assert_same_model(back, original, rng)
    np.testing.assert_allclose(back.loading.external_force, loading.external_force, rtol=ROUND_OFF, atol=0)
    # and it steps; the slit model, whose tensors the suture changed, is refused
    state = State.at_rest(back.n_vertices)
    SymplecticEuler().step(back, state, 1e-5, 2)
    with pytest.raises(InputError, match="mesh was changed"):
        SymplecticEuler().step(after, State.at_rest(after.n_vertices), 1e-5, 1)


def test_suturing_two_bodies_equals_the_joined_mesh(rng):
    """Two blocks side by side, each with its own vertices on the shared plane: joining the coincident
    vertices gives the model of the one-piece mesh."""
    a = structured_box((0.02, 0.02, 0.02), (4, 4, 4))
    b = structured_box((0.02, 0.02, 0.02), (4, 4, 4))
    points = np.concatenate([a.points, b.points + [0.02, 0.0, 0.0]])
    tets = np.concatenate([a.tets, b.tets + a.n_vertices])
    left = np.flatnonzero(np.abs(a.points[:, 0] - 0.02) < 1e-9)
    right = a.n_vertices + np.flatnonzero(np.abs(b.points[:, 0]) < 1e-9)
    order_l = np.lexsort(points[left].T[::-1])
    order_r = np.lexsort(points[right].T[::-1])
    pairs = np.stack([left[order_l], right[order_r]], axis=1)
    free = np.ones_like(points)
    free[points[:, 0] < 1e-9] = 0.0
    loading = Loading(free=free, external_force=np.zeros_like(points))
    apart = build_model("linear-tm", points, tets, HOST, loading)
    joined = suture(apart, pairs)
    target = np.arange(len(points))
    target[pairs[:, 1]] = pairs[:, 0]
    fresh = build_model("linear-tm", points, target[tets], HOST, joined.loading)
    assert_same_model(joined, fresh, rng)
    assert np.all(joined.loading.free[pairs[:, 1]] == 0.0)  # the joined copies: unused, held


def test_bad_topology_changes_are_one_line_errors():
    mesh, materials, loading = block()
    model = build_model("linear-tm", mesh.points, mesh.tets, materials, loading)
    with pytest.raises(InputError, match=r"suture: vertices \[0, 1\] are .* m apart"):
        suture(model, [[0, 1]])
    with pytest.raises(InputError, match=r"slit: face \[0, 1, 2\] is not an interior triangle"):
        slit(model, [[0, 1, 2]])
    with pytest.raises(InputError, match="stvk-tm does not support topology changes"):
        slit(build_model("stvk-tm", mesh.points, mesh.tets, HOST), slit_faces(mesh))
    n = mesh.n_vertices
    for call, message in (
        (lambda: suture(model, [[0, n]]), rf"suture: pair: \[0, {n}\] is outside 0..{n - 1}"),
        (lambda: suture(model, [[0, 1, 2]]), r"suture: pair: must have shape \(K, 2\), got \(1, 3\)"),
        (lambda: suture(model, [[0.5, 1]]), r"suture: pair: must be whole-number indices"),
        (lambda: slit(model, [[0, 1, -1]]), rf"slit: face: \[0, 1, -1\] is outside 0..{n - 1}"),
        (lambda: slit(model, [[0, 1], [2, 3]]), r"slit: face: must have shape \(K, 3\), got \(2, 2\)"),
    ):
        with pytest.raises(InputError, match=message):
            call()
