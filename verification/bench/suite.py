"""The performance benchmark: median microseconds per step of every model on the liver meshes, with
scipy's BSR sparse matrix-vector product with the same stiffness as the baseline, in the same run.

Each row times the integrator's compiled n-step call (symplectic Euler; the force kernel, the update,
the tools and the blow-up check), each call from the same state, in rounds that interleave the rows
after a warm-up; the median and the spread are reported. The scene: the liver held at the centre of
its back under gravity, at rest plus a small random displacement so that the non-linear models do real
work (the hybrid row: a tenth of the vertices moved past its threshold). The "haptic loop" rows call
step with n = 1, once per step, as a 1000 Hz device loop does: the cost of a whole call, Python and
numba's dispatch included; the row CALL_ROW is a call that takes no step (n = 0), the call's own cost.
The rows "M, 2 threads" run the threaded kernels (realtime.threaded) on every core, up to THREADS, in
the same rounds as their one-thread rows, and report the speed-up over them (the step, and the rows
"M, force alone": the force kernel without the update, on one thread and on all), beside what the
machine itself gains from the same threads, timed in the same rounds (verification.bench.roofline.thread_loops:
its FMA loop, and its triad on as many bytes as stvk-tm's step streams, on one thread and on all): a
speed-up near those is the machine's limit, not the code's. "liver-x10-renumbered" is liver-x10 numbered
along the body (realtime.renumber), which a simulator can do to its own mesh once. Speed is never
asserted in the tests: this command reports it.

Each row with a fixed amount of work (linear-tm, stvk-tm, mass-spring, scipy's product) also gets its
roofline (verification.bench.roofline): the least time its flops and bytes allow at this core's measured FMA
peak and at the triad bandwidth for data of its size, and the fraction of that bound the row achieves.
The rows "stvk-tm, element arithmetic alone" and "stvk-tm, gather and scatter alone" split stvk-tm's
force in its two phases, each with its roofline (roofline.stvk_phase_work) and its share of the row
"stvk-tm, force alone": where the kernel's time goes. Last, what the hot loops compile to on this
target (verification.bench.codegen: packed instructions, signed-index shifts): the counts that explain the
timings, measured here because they differ from one machine to the next.
"""

from __future__ import annotations

import os
import platform
import time

import numba as nb
import numpy as np

from meshes import stored_mesh
from meshes.store import RENUMBERED, STORED
from realtime import Loading, Material, State, SymplecticEuler, build_model
from realtime.blocks import BLOCK, GEO_ROWS_U, HOT, gather, scatter_block
from realtime.geometry import unique_edges
from realtime.models import SPECS, condensed, corotational_tm, hybrid_tm, linear_tm, mass_spring, precomputed, stvk_tm
from realtime.models.hybrid_tm import nonlinear_fraction
from realtime.models.linear_tm import cut
from realtime.quasistatic import QuasiStatic
from realtime.stvk import stvk_block
from verification.bench import codegen
from verification.bench.roofline import Roofline, bsr_work, step_work, stvk_phase_work, thread_loops, thread_scaling
from verification.cache import git_commit, versions
from verification.progress import log

MESHES = ("liver", "liver-x10", "liver-x10-renumbered")
#: The most threads a threaded row uses (it uses every core up to this).
THREADS = 2
#: Dense quasi-static models hold (surface dofs)^2 or (free dofs x surface dofs) numbers: past this
#: many surface dofs they are not built (2 GB of float64 at 16 000).
DENSE_LIMIT = 6000


def machine() -> dict:
    cpu = "unknown"
    try:
        for line in open("/proc/cpuinfo"):
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    return {
        "cpu": cpu,
        "cores": os.cpu_count(),
        "platform": platform.platform(),
        "commit": git_commit(),
        "date": time.strftime("%Y-%m-%dT%H:%M:%SZ", time.gmtime()),
        **versions(),
    }


def _loading(mesh, density):
    free = np.ones((mesh.n_vertices, 3))
    c = mesh.points.mean(axis=0)
    back = (mesh.points[:, 1] < mesh.points[:, 1].min() + 0.015) & (np.abs(mesh.points[:, 0] - c[0]) < 0.03)
    free[back] = 0.0
    from realtime.model import lumped_masses

    g = lumped_masses(mesh.points, mesh.tets, density)[:, None] * np.array([0.0, 0.0, -9.81])
    return Loading(free=free, external_force=g)


def _time_round_robin(cases: list[dict], repeats: int, warm: bool = False) -> None:
    """Time every case's ``fn`` (which runs ``n`` steps) in turns, ``repeats`` rounds, after a warm-up
    call of each; write step_us (median), step_us_min and step_us_max (microseconds per step) into
    the case. Rounds interleave the cases so that drift of the machine touches all of them alike.
    ``warm``: call each case once more, untimed, right before its timed call, so that its data is back
    in the caches whatever the case before it evicted (cases of other libraries, with other footprints)."""
    for c in cases:
        c["fn"]()
    samples = [[] for _ in cases]
    for _ in range(repeats):
        for k, c in enumerate(cases):
            if warm:
                c["fn"]()
            t0 = time.perf_counter()
            c["fn"]()
            samples[k].append((time.perf_counter() - t0) / c["n"] * 1e6)
    for c, t in zip(cases, samples, strict=True):
        t = np.sort(t)
        c.update(step_us=float(np.median(t)), step_us_min=float(t[0]), step_us_max=float(t[-1]))


#: The row of a step call that takes no step (n = 0), timed over CALLS calls: microseconds per call.
CALL_ROW = "linear-tm, a call of no step (the call's own cost)"
CALLS = 1000


@nb.njit(nogil=True)
def _force_loop(force, data, scratch, u, f, n):
    """n calls of the model's force kernel, from compiled code (a call from Python pays numba's typing of
    the kernel's data, tens of microseconds). Not cached: a cached loop that calls a parallel kernel
    crashed when loaded in a process that had not started numba's threads (realtime.steppers)."""
    for _ in range(n):
        force(data, scratch, u, f)


def _force_case(model, u, n):
    """n evaluations of ``model``'s force at u (N, 3) m, the kernel alone (no update)."""
    scratch, f = model.new_scratch(), np.zeros_like(u)

    def fn():
        _force_loop(model.force_kernel, model.data, scratch, u, f, n)

    return fn


# stvk-tm's force in its two phases, compiled like its kernel (blocks.HOT) but not cached: numba checks
# a cached function against its own file only, and these inline the engine's block code.
_PHASE_JIT = {**HOT, "cache": False}


@nb.njit(**_PHASE_JIT)
def _stvk_arithmetic_loop(data, W, n):
    """n passes of stvk-tm's element arithmetic over every block of BlockData ``data``, in place on W
    (9 BLOCK,), as stvk_block: no gather, no scatter. The bench gives it a new scratch's zeros (the
    flops do not depend on the values, and zeros stay zeros, never denormal)."""
    tets, geo, prm, _ = data
    for _ in range(n):
        for b in range(tets.shape[0] // BLOCK):
            stvk_block(W, geo, np.uint64(b) * GEO_ROWS_U, prm[b], False)


@nb.njit(**_PHASE_JIT)
def _gather_scatter_loop(data, W, u, f, n):
    """n passes of stvk-tm's gather of u (N, 3) m and scatter into f (N, 3) N over every block of
    BlockData ``data`` (f zeroed first, as the kernel does), with no element arithmetic between."""
    tets, _, _, everywhere = data
    t1, u1, f1 = tets.reshape(-1), u.reshape(-1), f.reshape(-1)
    for _ in range(n):
        f[:] = 0.0
        for b in range(tets.shape[0] // BLOCK):
            gather(t1, b * BLOCK, u1, W)
            scatter_block(t1, b * BLOCK, W, f1, everywhere)


def _phase_cases(model, u, n, base) -> list[dict]:
    """stvk-tm's force split in its phases, each a row beside "stvk-tm, force alone" (its share of it):
    the element arithmetic alone and the gather and scatter alone, placed on their rooflines
    (roofline.stvk_phase_work). They show where the kernel's time goes: the arithmetic's fraction of
    the FMA roofline is the kernel's once its indexed loads and stores are set apart."""
    (W,), f = model.new_scratch(), np.zeros_like(u)
    data = model.data
    return [
        {**base, "name": "stvk-tm, element arithmetic alone", "model": stvk_tm.NAME, "phase": "arithmetic", "n": n,
         "part_of": "stvk-tm, force alone", "fn": lambda: _stvk_arithmetic_loop(data, W, n)},
        {**base, "name": "stvk-tm, gather and scatter alone", "model": stvk_tm.NAME, "phase": "gather and scatter",
         "n": n, "part_of": "stvk-tm, force alone", "fn": lambda: _gather_scatter_loop(data, W, u, f, n)},
    ]  # fmt: skip


def _step_case(integ, model, state, dt, n, calls=1):
    """``calls`` step calls of n steps each, from the same start every time (the copy costs about a
    microsecond), so that every round times the same configuration: left to run on, the liver sags
    under gravity and a hybrid model's non-linear part would grow from call to call. n = 1 with many
    calls is a haptic loop: the cost of a whole call, Python and numba's dispatch included."""
    u0, v0 = state.u.copy(), state.v.copy()

    def fn():
        np.copyto(state.u, u0)
        np.copyto(state.v, v0)
        state.acc = None
        for _ in range(calls):
            integ.step(model, state, dt, n)

    return fn


def _place_on_roofline(roof: Roofline, row: dict, work: tuple[float, float] | None) -> None:
    """Write the row's roofline bound (microseconds per step, and which ceiling) and achieved fraction."""
    if work is None or row.get("step_us") is None:
        return
    bound, limit = roof.bound_us(*work)
    row.update(
        flops=work[0], bytes=work[1], roofline_us=bound, roofline_limit=limit, roofline_fraction=bound / row["step_us"]
    )


def run(meshes=MESHES, repeats: int = 15, steps: int = 50) -> dict:
    """Every case on every mesh of ``meshes``, timed in round-robin rounds (``repeats``), each placed on
    this machine's roofline; the machine, its thread scaling and what the hot loops compile to."""
    rows = []
    log("bench: measuring this core's FMA peak and triad bandwidths (the roofline)")
    roof = Roofline()
    rng = np.random.default_rng(0)
    thread_ceilings = {}
    for name in meshes:
        mesh = stored_mesh(name)
        base = {"mesh": name, "mesh_sha256": mesh.sha256()[:16], "n_vertices": mesh.n_vertices, "n_tets": mesh.n_tets}
        loading = _loading(mesh, ISO.density)
        u0 = 1e-4 * rng.standard_normal(mesh.points.shape) * loading.free
        n = steps if mesh.n_tets < 20000 else max(steps // 2, 5)
        cases, built = _model_cases(name, mesh, base, loading, u0, n)
        cases += _float32_cases(name, mesh, loading, u0, n, cases)
        threads = min(os.cpu_count() or 1, THREADS)
        cases += _thread_cases(name, mesh, base, loading, u0, n, cases, built, threads)
        cases += _phase_cases(built[stvk_tm.NAME], u0, n, base)
        # what the machine itself gains from the threads, in the same rounds: the roofline's loops on one
        # thread and on all, the triad on as many bytes as stvk-tm's step streams
        n_edges = len(unique_edges(mesh.tets))
        footprint = step_work(stvk_tm.NAME, mesh.n_vertices, mesh.n_tets, n_edges)[1]
        ceilings = thread_loops(threads, footprint) if threads > 1 else {}
        cases += [{"name": key, "ceiling": True, "n": units, "fn": fn} for key, (fn, units) in ceilings.items()]
        cases.append(_bsr_case(mesh, base, loading, u0))
        cases.append(_cut_case(mesh, base, loading))
        skipped, quasi = _quasi_static_cases(name, mesh, base, loading)
        rows += skipped
        cases += quasi
        log(f"bench: {name} timing {len(cases)} cases x {repeats} rounds")
        _time_round_robin(cases, repeats)
        if ceilings:
            timed = {c["name"]: c["step_us"] for c in cases if c.get("ceiling")}
            thread_ceilings[name] = {"threads": threads, "bytes": footprint, **thread_scaling(timed, threads)}
            cases = [c for c in cases if not c.get("ceiling")]
        rows += _placed(roof, cases, mesh, n_edges)
        _relate(rows, name)
    log("bench: what the hot loops compile to on this target (verification.bench.codegen)")
    return {
        "machine": {**machine(), "roofline": roof.summary(), "thread_scaling": thread_ceilings},
        "compiled_code": codegen.report(),
        "results": rows,
        "meshes": {m: STORED.get(m) or (*STORED[m.removesuffix(RENUMBERED)], "renumbered") for m in meshes},
    }


#: The benchmark's materials: isotropic StVK, and transversely isotropic with the volume penalty.
ISO = Material(2.8e4, 0.4, 1000.0, law="stvk")
FIBRE = Material(2.8e4, 0.4, 1000.0, law="stvk", fiber=(1.0, 0.0, 0.0), young_fiber=6e4, volume_penalty=5e4)


def _model_cases(name: str, mesh, base: dict, loading, u0, n: int) -> tuple[list, dict]:
    """Each model's step on one thread (and the haptic loop's one step a call, and its bare call), and
    the one-thread model of each row by its label."""
    cases = []
    haptic = []
    built = {}  # label -> the one-thread model of its row
    rows = [
        (linear_tm.NAME, linear_tm.NAME, ISO),
        ("linear-tm (transverse)", linear_tm.NAME, FIBRE),
        (corotational_tm.NAME, corotational_tm.NAME, ISO),
        (stvk_tm.NAME, stvk_tm.NAME, ISO),
        ("stvk-tm (transverse + penalty)", stvk_tm.NAME, FIBRE),
        ("hybrid-tm (10% of vertices past threshold)", hybrid_tm.NAME, ISO),
        (mass_spring.NAME, mass_spring.NAME, ISO),
    ]
    # every other time-stepping model on the scene's own mesh, on the isotropic material: a model added
    # as one file has its row
    named = {m for _, m, _ in rows}
    rows += [
        (s.name, s.name, ISO)
        for s in SPECS.values()
        if not s.quasi_static and s.mechanics and not s.own_mesh and s.name not in named
    ]
    for label, model_name, mat in rows:
        log(f"bench: {name} {label}")
        model = build_model(model_name, mesh.points, mesh.tets, mat, loading)
        built[label] = model
        integ = SymplecticEuler()
        dt = 0.5 * integ.critical_dt(model)
        u = u0.copy()
        if model_name == hybrid_tm.NAME:
            # move a tenth of the vertices past the threshold: the non-linear part of a local tool.
            # At 0.5 dt_crit that jolt would spread over the mesh within the timed steps (88% of
            # the tetrahedra non-linear after 50); a step costs the same at any dt, so the hybrid
            # row steps at 1e-3 dt_crit and keeps the prepared non-linear set.
            near = np.argsort(np.linalg.norm(mesh.points - mesh.points[0], axis=1))[: mesh.n_vertices // 10]
            u[near] += 2 * model.extra["threshold"] * loading.free[near]
            dt *= 2e-3
        state = State(u=u, v=np.zeros_like(u))
        cases.append(
            {
                "name": label,
                "model": model_name,
                **base,
                "dt": dt,
                "integrator": integ.name,
                "n": n,
                "fn": _step_case(integ, model, state, dt, n),
            }
        )
        if label in (linear_tm.NAME, stvk_tm.NAME):
            haptic.append(
                {
                    **cases[-1],
                    "name": f"{label}, one step a call (haptic loop)",
                    "n": n,
                    "fn": _step_case(SymplecticEuler(), model, State(u=u.copy(), v=np.zeros_like(u)), dt, 1, n),
                }
            )
        if label == linear_tm.NAME:
            # what a haptic loop's call costs before it steps (the checks, the entry into the compiled
            # loop, the returned force), apart from the noise of a difference of two step times
            haptic.append(
                {
                    **cases[-1],
                    "name": CALL_ROW,
                    "n": CALLS,
                    "fn": _step_case(SymplecticEuler(), model, State(u=u.copy(), v=np.zeros_like(u)), dt, 0, CALLS),
                }
            )
        if model_name == hybrid_tm.NAME:
            cases[-1]["probe"] = lambda model=model, state=state: {
                "nonlinear_fraction": nonlinear_fraction(model.tets, state.u, model.extra["threshold"])
            }
    return cases + haptic, built


def _float32_cases(name: str, mesh, loading, u0, n: int, cases: list) -> list:
    """The float32 kernels (build_model's precision), beside their float64 rows."""
    out = []
    for model_name in (s.name for s in SPECS.values() if s.float32):
        log(f"bench: {name} {model_name}, float32")
        model = build_model(model_name, mesh.points, mesh.tets, ISO, loading, precision="float32")
        one = next(c for c in cases if c["name"] == model_name)
        u = u0.astype(np.float32)
        state = State(u=u, v=np.zeros_like(u))
        out.append(
            {
                **one,
                "name": f"{model_name}, float32",
                "precision": "float32",
                "versus": model_name,
                "fn": _step_case(SymplecticEuler(), model, state, one["dt"], n),
            }
        )
    return out


def _thread_cases(name: str, mesh, base: dict, loading, u0, n: int, cases: list, built: dict, threads: int) -> list:
    """The threaded kernels on every core (realtime.threaded), beside their one-thread rows: the step,
    and the force kernel alone (the update after it streams the state and does not gain as much)."""
    out = []
    for model_name in (linear_tm.NAME, corotational_tm.NAME, stvk_tm.NAME) if threads > 1 else ():
        log(f"bench: {name} {model_name}, {threads} threads")
        model = build_model(model_name, mesh.points, mesh.tets, ISO, loading, threads=threads)
        one = next(c for c in cases if c["name"] == model_name)
        state = State(u=u0.copy(), v=np.zeros_like(u0))
        alone = f"{model_name}, force alone"
        out += [
            {
                **one,
                "name": f"{model_name}, {threads} threads",
                "threads": threads,
                "versus": model_name,
                "fn": _step_case(SymplecticEuler(), model, state, one["dt"], n),
            },
            {**base, "name": alone, "model": model_name, "n": n, "fn": _force_case(built[model_name], u0, n)},
            {
                **base,
                "name": f"{alone}, {threads} threads",
                "model": model_name,
                "threads": threads,
                "versus": alone,
                "n": n,
                "fn": _force_case(model, u0, n),
            },
        ]
    return out


def _bsr_case(mesh, base: dict, loading, u0) -> dict:
    """The baseline a user would otherwise write: scipy's BSR product with the same matrix."""
    lin = build_model(linear_tm.NAME, mesh.points, mesh.tets, ISO, loading)
    K = lin.extra["tensors"].matrix().tobsr(blocksize=(3, 3))
    x = u0.ravel().copy()
    reps = 50 if mesh.n_tets < 20000 else 10

    def bsr(K=K, x=x, reps=reps):
        for _ in range(reps):
            K @ x

    return {"name": "scipy-bsr-matvec", "model": None, **base, "nnz_blocks": int(K.nnz // 9), "n": reps, "fn": bsr}


#: The cuts one timed call of the cut case makes, one tetrahedron each.
CUTS = 10


def _cut_case(mesh, base: dict, loading) -> dict:
    """Cutting one tetrahedron out of linear-tm (``realtime.models.linear_tm.cut``), one after another in a
    random order across the mesh: what a haptic frame pays for a scalpel's stroke. Microseconds per
    cut."""
    state = {"model": build_model(linear_tm.NAME, mesh.points, mesh.tets, ISO, loading), "next": 0}
    order = np.random.default_rng(0).permutation(mesh.n_tets)

    def cuts(state=state, order=order):
        for _ in range(CUTS):
            state["model"] = cut(state["model"], [int(order[state["next"]])])
            state["next"] += 1

    return {"name": "linear-tm, cut one tetrahedron", "model": None, **base, "n": CUTS, "fn": cuts}


def _quasi_static_cases(name: str, mesh, base: dict, loading) -> tuple[list, list]:
    """Precomputed and condensed: the full update with one contact vertex, and precomputed's tool-force
    update; rows that say why where the dense precomputation would not fit."""
    skipped, cases = [], []
    surface = len(mesh.surface_vertices) * 3
    for model_name in (precomputed.NAME, condensed.NAME):
        if surface > DENSE_LIMIT:
            skipped.append(
                {
                    "name": model_name,
                    "model": model_name,
                    **base,
                    "step_us": None,
                    "skipped": f"{surface} surface dofs: the dense precomputation would not fit",
                }
            )
            continue
        log(f"bench: {name} {model_name}")
        tool = int(mesh.surface_vertices[np.argmax(mesh.points[mesh.surface_vertices, 2])])
        free = loading.free.copy()
        free[tool] = 0.0
        lo = Loading(
            **{
                **loading.__dict__,
                "free": free,
                "tool_vertex": np.array([tool]),
                "tool_mask": np.ones((1, 3)),
                "tool_id": np.zeros(1, np.int64),
                "tool_kind": np.zeros(1, np.int64),
                "tool_vector": np.array([[0.0, 0.0, -0.005]]),
                "tool_axis": np.array([[0.0, 0.0, 1.0]]),
                "tool_center": np.zeros((1, 3)),
                "tool_angle": np.zeros(1),
                "tool_ramp": np.zeros(1),
                "tool_ramp_shape": np.zeros(1, np.int64),
            }
        )
        t0 = time.perf_counter()
        model = build_model(model_name, mesh.points, mesh.tets, ISO, lo)
        build_s = time.perf_counter() - t0
        state = State.at_rest(mesh.n_vertices)
        cases.append(
            {
                "name": f"{model_name} (full update, 1 contact vertex)",
                "model": model_name,
                **base,
                "build_s": build_s,
                "n": 1,
                "fn": _step_case(QuasiStatic(), model, state, 1e-3, 1),
            }
        )
        if model_name == precomputed.NAME:
            pc = model.extra["quasistatic"]
            d = np.array([0.0, 0.0, -0.005])

            def force(pc=pc, tool=tool, d=d):
                for _ in range(1000):
                    pc.tool_force(tool, d)

            cases.append(
                {
                    "name": "precomputed tool-force update (1 contact vertex)",
                    "model": model_name,
                    **base,
                    "n": 1000,
                    "fn": force,
                }
            )
    return skipped, cases


def _placed(roof, cases: list, mesh, n_edges: int) -> list:
    """The timed cases as rows, each placed on the roofline by the work its kernel does."""
    rows = []
    for c in cases:
        c.pop("fn")
        c.update(c.pop("probe", dict)())
        if c["name"] == "scipy-bsr-matvec":
            work = bsr_work(c["nnz_blocks"], mesh.n_vertices)
        elif "phase" in c:
            work = stvk_phase_work(c["phase"], mesh.n_vertices, mesh.n_tets)
        elif c["name"] == c["model"] or c["name"].startswith(f"{c['model']}, one step"):
            work = step_work(c["model"], mesh.n_vertices, mesh.n_tets, n_edges)
        else:  # a variant (fibres, penalty) does more than the counted kernel
            work = None
        _place_on_roofline(roof, c, work)
        rows.append(c)
    return rows


def _relate(rows: list, name: str) -> None:
    """Each variant row's speed-up over the one-thread float64 row it was measured beside, and each
    part's share of its whole."""
    for c in rows:
        if c["mesh"] == name and "versus" in c:
            # measured in the same rounds as the one-thread float64 row it is a variant of
            one = next(r for r in rows if r["mesh"] == name and r["name"] == c["versus"])
            c["speedup"] = one["step_us"] / c["step_us"]
        whole = next((r for r in rows if r["mesh"] == name and r["name"] == c.get("part_of")), None)
        if c["mesh"] == name and whole is not None:  # "force alone" is timed on a machine with threads
            c["share"] = c["step_us"] / whole["step_us"]
