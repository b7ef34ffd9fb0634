"""The engine's API under random wrong arguments, run as ``python -m tests.realtime.api_fuzz SEED COUNT`` in a
child process (tests/verification/test_input_errors.py): a crash kills only the child, whose exit status and last
printed call then say which call it was. Every model and VARIANTS by default; ``python -m
tests.realtime.api_fuzz SEED COUNT MODEL,MODEL:OPTION=VALUE,...`` fuzzes those named. Each call is made with one argument spoiled (a wrong shape,
float type, layout, a NaN, an index out of range, a fraction, a string, None); it must return or raise
an InputError (or, for a NaN put in a state, the DivergenceError a NaN state is), nothing else. Prints
one line per call before making it, and a summary at the end."""

from __future__ import annotations

import sys

import numpy as np

#: Besides every model of the registry: the threaded and float32 kernels (their own data layouts and
#: scratch; the float32 stvk-tm energy was a typing error on every call until the fuzz ran on them).
VARIANTS = (
    "linear-tm:threads=2",
    "corotational-tm:threads=2",
    "stvk-tm:precision=float32",
    "mass-spring:precision=float32",
)


def spoil(value, rng, n_vertices: int):
    """``value`` with one thing wrong, and a word saying what."""
    a = np.asarray(value)
    choices = ["shape", "float32", "int", "fortran", "strided", "nan", "list", "string", "none", "empty", "scalar"]
    if a.dtype.kind in "iu":
        choices += ["negative", "past", "fraction", "huge"]
    kind = choices[int(rng.integers(len(choices)))]
    if kind == "shape":
        shape = list(a.shape) or [1]
        shape[int(rng.integers(len(shape)))] += int(rng.choice([-1, 1, 3]))
        return np.resize(a, [max(s, 0) for s in shape]), kind
    if kind == "float32":
        return a.astype(np.float32), kind
    if kind == "int":
        return a.astype(np.int32), kind
    if kind == "fortran":
        return np.asfortranarray(a), kind
    if kind == "strided":
        return np.repeat(a, 2, axis=0)[::2] if a.ndim else a, kind
    if kind == "nan":
        b = a.astype(float).copy()
        if b.size:
            b.flat[int(rng.integers(b.size))] = np.nan
        return b, kind
    if kind == "list":
        return a.tolist(), kind
    if kind == "string":
        return "oops", kind
    if kind == "none":
        return None, kind
    if kind == "empty":
        return a[:0] if a.ndim else np.zeros(0), kind
    if kind == "scalar":
        return 3.0, kind
    b = a.copy()
    if b.size:
        i = int(rng.integers(b.size))
        b.flat[i] = {"negative": -1, "past": n_vertices + 7, "huge": 2**40}.get(kind, 0)
    if kind == "fraction":
        return b.astype(float) + 0.5, kind
    return b, kind


def main(seed: int, count: int, names: tuple[str, ...] = ()) -> int:
    from meshes import stored_mesh
    from realtime import (
        MODELS,
        DivergenceError,
        InputError,
        Loading,
        Material,
        State,
        build_model,
        max_eigenvalue,
        renumber,
    )
    from realtime.integrators import CentralDifference, ImplicitEuler, SymplecticEuler
    from realtime.models.linear_tm import cut
    from realtime.topology import slit, suture

    rng = np.random.default_rng(seed)
    mesh = stored_mesh("beam")
    n = mesh.n_vertices
    free = np.ones((n, 3))
    free[mesh.points[:, 0] < 1e-9] = 0.0
    tip = np.flatnonzero(mesh.points[:, 0] > mesh.points[:, 0].max() - 1e-9)
    loading = Loading.translating_tool(free, np.zeros((n, 3)), tip, (0.0, 0.0, -1e-3), ramp=1e-3)
    mat = Material(5e5, 0.3, 1000.0)
    names = names or (*MODELS, *VARIANTS)

    def build(name):
        """The model ``name``, or a variant "model:option=value" of it."""
        model_name, _, option = name.partition(":")
        key, _, value = option.partition("=")
        options = {key: int(value) if value.isdigit() else value} if key else {}
        return build_model(model_name, mesh.points, mesh.tets, mat, loading, **options)

    models = {name: build(name) for name in names}
    integrators = (SymplecticEuler, CentralDifference, ImplicitEuler)
    zeros = np.zeros((n, 3))

    def calls(model):
        """(name, function of its arguments, the right arguments) of the API's calls on ``model``."""
        integ = integrators[int(rng.integers(3))]()
        state = lambda u, v: State(u=u, v=v)  # noqa: E731
        return [
            ("internal_force", model.internal_force, [zeros]),
            ("elastic_energy", model.elastic_energy, [zeros]),
            ("kinetic_energy", model.kinetic_energy, [zeros]),
            ("tool_reactions", model.tool_reactions, [zeros]),
            ("max_eigenvalue", lambda u: max_eigenvalue(model, u, tol=1e-3), [zeros]),
            (f"{integ.name}.step u", lambda u: integ.step(model, state(u, zeros.copy()), 1e-6, 2), [zeros.copy()]),
            (f"{integ.name}.step v", lambda v: integ.step(model, state(zeros.copy(), v), 1e-6, 2), [zeros.copy()]),
            (f"{integ.name}.step dt", lambda dt: integ.step(model, state(zeros.copy(), zeros.copy()), dt, 2), [1e-6]),
            (f"{integ.name}.set_forces", lambda f: integ.set_forces(model, f), [zeros]),
            (f"{integ.name}.set_tool", lambda x: integ.set_tool(model, 0, translation=x), [np.zeros(3)]),
            ("cut", lambda which: cut(model, which), [np.array([0, 1])]),
            ("suture", lambda pairs: suture(model, pairs), [np.array([[0, 1]])]),
            ("slit", lambda faces: slit(model, faces), [mesh.tets[:1, :3]]),
            ("build_model points", lambda p: build_model(model.name, p, mesh.tets, mat, loading), [mesh.points]),
            ("build_model tets", lambda t: build_model(model.name, mesh.points, t, mat, loading), [mesh.tets]),
            ("renumber points", lambda p: renumber(p, mesh.tets), [mesh.points]),
            ("renumber tets", lambda t: renumber(mesh.points, t), [mesh.tets]),
        ]

    outcomes = {"returned": 0, "InputError": 0, "DivergenceError": 0}
    for k in range(count):
        name = names[int(rng.integers(len(names)))]
        model = models[name]
        options = calls(model)
        what, call, args = options[int(rng.integers(len(options)))]
        spoilt, how = spoil(args[0], rng, n)
        print(f"{k}: {name} {what} ({how})", flush=True)
        try:
            call(spoilt)
            outcomes["returned"] += 1
            if what in ("cut", "slit", "suture"):  # the mesh changed: the next calls need a current model
                models[name] = build(name)
        except InputError:
            outcomes["InputError"] += 1
        except DivergenceError:
            if ".step" not in what or how not in ("nan", "scalar"):  # a NaN state, or dt = 3 s: both blow up
                raise
            outcomes["DivergenceError"] += 1
    print(f"done: {outcomes}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(int(sys.argv[1]), int(sys.argv[2]), *([tuple(sys.argv[3].split(","))] if len(sys.argv) > 3 else [])))
