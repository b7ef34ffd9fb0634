"""What every adapter shares: an exported scene read with numpy alone, the loop that drives an engine
through it, and the result written as the harness reads it (docs/engines.md).

An adapter runs in the engines' own venv (``.venv-engines``, made by ``make engines``), which has its own
numpy and none of the project: it reads only the files ``tissuebench export`` wrote (``scene.json`` and
``arrays.npz``, docs/scenes.md "Exported scenes"), and writes one ``.npz``. The engine behind it is
reached through ``Stepper``, a handful of calls every engine here offers: step by dt, read and write
positions and velocities of the vertices.

A static scene is solved as these engines solve statics: by dynamic relaxation. The tools move to their
final place over ``ramp_steps`` steps, then the run goes on with kinetic damping (every velocity set to
zero when the kinetic energy passes a peak, Cundall's scheme for explicit relaxation, Topping & Khan,
"Parallel finite element computations", 1996, ch. 4) until the harness's ``rtol`` is met twice in a row:
by the residual of the load where the engine gives its net force (``residual``), else by the largest
displacement change over the last quarter of the run against the largest displacement (or the engine's
round-off in a position, 8 ulp of the largest coordinate, if that is larger); or until round-off stops it
first (the residual no longer halves, the change stops shrinking below ``STALLED`` or below ``WALK``
round-offs). The state is then released from rest and must stay where it is (``HOLD``). A dynamic scene
is run from rest to its end, and sampled at its output instants; the tools' prescribed displacements come
from the export at those instants, linearly interpolated in between.

A scene's rigid tools (``scene.json`` ``rigid_tools``: a sphere, a capsule or a plane, frictionless) are the
engine's own contact: the adapter builds each as its engine's shape, the driver moves it along its travel with
the vertex tools (``Stepper.set_rigid``), and its force on the body is what the engine's contact exerts
(``Stepper.rigid_force``). Only static scenes have them (the truth solves no dynamic contact).

The result's keys: ``displacement`` (T, N, 3) m at the scene's vertices; ``reaction`` (T, 3) N, the tools'
force on the body, where the engine gives its internal force (``tool_force``), the rigid tools' contact
force added; ``rigid_force`` (K, 3) N, each rigid tool's; ``step_us`` (us per step of the
engine's own step call, median over the run's batches); ``dt`` s; ``steps``; ``diverged`` (1 when the run
blew up, and ``diverged_at`` s); ``settled`` (0 when a static run hit its step limit); ``law`` (the
engine's law the scene's was mapped to, in words); ``engine`` (name and version).
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

#: The export's format and the versions an adapter reads.
FORMAT, VERSIONS = "tissuebench-scene", (1,)


#: A relaxation whose relative change has stopped shrinking (by half over the last half of the run) below
#: this is settled at its engine's round-off (float32 engines random-walk at about 1e-4 of the
#: displacement: measured 1.6e-4 with newton's semi-implicit solver on the built-in cantilever).
STALLED = 1e-3

#: A float32 engine's walk in the change is absolute, about 12 to 16 of its round-offs in a position
#: (``round_off``): newton's semi-implicit solver, 1.6e-4 of the cantilever's 7.4 mm, and 1.1e-3 of the
#: 2.2 mm the liver press's sphere pushes at half its travel, which ran into the adapter's 300 s wall with
#: its change still above STALLED. A change below WALK of them (three times that) has stalled, halving or
#: not: nothing finer can be seen (the same press at its full travel, its change still shrinking like
#: 1 / n at 3 round-offs, ran into the wall too); one failing to halve below WALK of them, above STALLED.
WALK = 48.0


#: A residual that makes no progress at all over the last half of the run (its least value within 1 % of
#: the first half's) while the state no longer moves (its change within WALK round-offs) is at a fixed point
#: of the engine's step from this many ramps on; one that merely fails to halve, from 40, as the change.
#: MuJoCo's discrete flex sits at its fixed point from its first few hundred steps, not moving at all: at 40
#: ramps (8000 steps of 63 ms on the liver) it ran into the 300 s wall unsettled. Its explicit flex settles
#: by kinetic damping's staircase, the state moving on while the residual stays level: on the hanging bar
#: its residual stayed between 6e-4 and 1.1e-3 from step 650 to 2650, then fell to 5e-11 by step 14 400;
#: taken for a fixed point at step 2700, its answer was 4e-3 from P1 StVK. A level within BUDGET_TOLERANCE
#: is a floor however the state moves: MuJoCo's contact solver keeps the plane press's residual between 3e-10
#: and 3e-8 of the load, the state jittering by as much, for as long as it runs.
RESIDUAL_WINDOW = 10

#: A residual within PLATEAU_FACTOR of the tolerance that has not fallen by 10 % in PLATEAU_STEPS steps is at
#: its floor, the built-in models' rule (realtime/statics.py, ``_converged``: 50 chunks of 200 steps, within
#: 1000 rtol). MuJoCo's explicit flex on the cantilever (float64, 7.8e-6 s steps) reached 1.6e-10 of the load
#: at step 40 000 against the harness's 1e-10 and stayed there; the halving rule above, which looks back
#: over half the run, called it stalled at step 77 100.
PLATEAU_FACTOR, PLATEAU_STEPS = 1e3, 10_000

#: The fraction of ``Exported.wave_step`` an explicit engine relaxes with by default. Kinetic damping
#: zeroes the velocities at every peak of the kinetic energy, which makes some steps gradient descent,
#: stable only below sqrt(2) / omega_max instead of 2 / omega_max; and the wave step overestimates the
#: critical step by up to 2 on well-shaped tetrahedra (structured cube: wave step 8.1e-4 s, critical
#: 9.0e-4 s for P1, and the relaxation unstable at 4e-4 s, stable at 3e-4 s). Hence a quarter.
RELAX_FRACTION = 0.25

#: A run whose budget runs out with its residual, or else its change, at most this (relative, as ``rtol``)
#: ends there as a stall: its answer is the one a tolerance of this would have stopped at (the adapters'
#: own, before the harness's was passed down), and the harness's 1e-10 is for arithmetic that reaches it.
BUDGET_TOLERANCE = 1e-6

#: A relaxed state is an equilibrium when, released from rest, it moves by at most HOLD of its largest
#: displacement in HOLD_STEPS steps. Measured on the built-in cantilever: newton's VBD at 1 ms and 10
#: iterations leaves the equilibrium the other engines agree on by 15% in 10 steps; at 0.1 ms it stays
#: within 4e-4 in 10 steps, the semi-implicit solver within float32 round-off.
HOLD, HOLD_STEPS = 1e-2, 50


class AdapterError(Exception):
    """A scene an adapter cannot run; the message is printed as the adapter's one line, exit 2."""


def gravity_only(scene: Exported, who: str) -> np.ndarray:
    """(3,) m/s^2: the scene's gravity, where its loads are gravity alone (the export's nodal forces equal
    each vertex's lumped mass times it); AdapterError naming ``who`` (an engine that takes no nodal force)
    where they are not."""
    g = np.asarray(scene.spec.get("gravity_m_s2") or (0.0, 0.0, 0.0), dtype=float)
    weight = scene.lumped_masses()[:, None] * g
    free = ~scene.held()
    other = np.abs(scene.external_force - weight)[free].max(initial=0.0)
    if other > 1e-9 * max(float(np.abs(weight).max()), 1e-300):
        raise AdapterError(
            f"{who} takes gravity as its only load (no nodal force): this scene has other loads "
            f"(up to {other:.3g} N on a vertex)"
        )
    return g


def warp_device(wp, name: str):
    """warp's device ``name`` (``cpu``, ``cuda``, ``cuda:N``), where this machine has it; AdapterError
    naming the devices it has where not (a machine without a CUDA driver has ``cpu`` alone)."""
    have = [d.alias for d in wp.get_devices()]
    alias = "cuda:0" if name == "cuda" else name
    if alias not in have:
        raise AdapterError(f"device {name}: warp finds no such device on this machine (it has {', '.join(have)})")
    return wp.get_device(alias)


@dataclass(frozen=True)
class Exported:
    """An exported scene: ``spec`` is ``scene.json``; arrays as in its "arrays" entry (points (N, 3) m,
    tets (M, 4), material_index (M,), free (N, 3), external_force (N, 3) N, tool_vertex (P,), tool_mask
    (P, 3), tool_displacement (T, P, 3) m)."""

    spec: dict
    points: np.ndarray
    tets: np.ndarray
    material_index: np.ndarray
    free: np.ndarray
    external_force: np.ndarray
    tool_vertex: np.ndarray
    tool_mask: np.ndarray
    tool_displacement: np.ndarray

    @property
    def static(self) -> bool:
        return self.spec["time"]["mode"] == "static"

    @property
    def output_times(self) -> np.ndarray:
        return np.asarray(self.spec["time"]["output_times_s"], dtype=float)

    @property
    def size(self) -> float:
        """The body's largest extent, m."""
        return float(np.ptp(self.points, axis=0).max())

    def lame(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Per tetrahedron: lambda (M,) Pa, mu (M,) Pa, density (M,) kg/m^3."""
        mats = self.spec["materials"]
        pick = np.asarray(self.material_index)
        lam = np.array([m["lambda_pa"] for m in mats])[pick]
        mu = np.array([m["mu_pa"] for m in mats])[pick]
        rho = np.array([m["density_kg_m3"] for m in mats])[pick]
        return lam, mu, rho

    @property
    def damping(self) -> tuple[float, float]:
        """Rayleigh damping of a dynamic scene: (alpha 1/s, mass-proportional; beta s, stiffness-
        proportional); (0, 0) for a static one."""
        t = self.spec["time"]
        return float(t.get("damping_mass_per_s") or 0.0), float(t.get("damping_stiffness_s") or 0.0)

    def volumes(self) -> np.ndarray:
        """(M,) m^3: each tetrahedron's volume."""
        x = self.points[self.tets]
        e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
        return np.abs(np.einsum("ij,ij->i", e1, np.cross(e2, e3))) / 6.0

    def lumped_masses(self) -> np.ndarray:
        """(N,) kg: a quarter of each tetrahedron's mass at each of its vertices."""
        _, _, rho = self.lame()
        m = np.zeros(len(self.points))
        np.add.at(m, self.tets.ravel(), np.repeat(rho * self.volumes() / 4.0, 4))
        return m

    def wave_step(self, modulus: np.ndarray) -> float:
        """The smallest time, s, a dilatational wave takes across an element: each tetrahedron's smallest
        altitude (3 V over its largest face) over sqrt(modulus / rho), ``modulus`` (M,) Pa the P-wave
        modulus the engine runs with (lambda + 2 mu for the Lame constants). An explicit step is stable
        below about this; a relaxation with kinetic damping, below about a quarter of it (``RELAX_FRACTION``)."""
        _, _, rho = self.lame()
        x = self.points[self.tets]
        faces = [
            np.cross(x[:, b] - x[:, a], x[:, c] - x[:, a]) for a, b, c in ((0, 1, 2), (0, 1, 3), (0, 2, 3), (1, 2, 3))
        ]
        largest = np.max([0.5 * np.linalg.norm(f, axis=1) for f in faces], axis=0)
        return float(np.min(3.0 * self.volumes() / largest / np.sqrt(modulus / rho)))

    @property
    def rigid(self) -> list[dict]:
        """The rigid tools, as ``scene.json`` lists them (``rigid_tools``; none in an older export)."""
        return list(self.spec.get("rigid_tools") or [])

    @functools.cached_property
    def rigid_travel(self) -> np.ndarray:
        """(K, 3) m: each rigid tool's whole translation (a static scene's answer is at its end), read once:
        the driver asks for it before every step."""
        return np.array([t["travel_m"] for t in self.rigid], dtype=float).reshape(-1, 3)

    def held(self) -> np.ndarray:
        """(N, 3) bool: the components held at zero or prescribed by a tool."""
        return self.free == 0.0

    def prescribed(self, t: float) -> np.ndarray:
        """(N, 3) m: the displacement the tools prescribe at time t (s), zero elsewhere; for a static scene
        the final place whatever t."""
        out = np.zeros_like(self.points)
        d = self.tool_displacement
        if len(self.tool_vertex) == 0:
            return out
        if self.static:
            now = d[-1]
        else:
            times = self.output_times
            k = int(np.clip(np.searchsorted(times, t) - 1, 0, len(times) - 2))
            s = float(np.clip((t - times[k]) / (times[k + 1] - times[k]), 0.0, 1.0))
            now = (1.0 - s) * d[k] + s * d[k + 1]
        np.add.at(out, self.tool_vertex, now * self.tool_mask)
        return out


def read(scene_dir: str | Path) -> Exported:
    """The scene ``tissuebench export`` wrote into ``scene_dir``; AdapterError naming what is wrong."""
    d = Path(scene_dir)
    try:
        spec = json.loads((d / "scene.json").read_text())
    except (OSError, ValueError) as exc:
        raise AdapterError(f"{d / 'scene.json'}: cannot read it ({exc})") from None
    if spec.get("format") != FORMAT or spec.get("version") not in VERSIONS:
        raise AdapterError(f"{d / 'scene.json'}: format {spec.get('format')!r} version {spec.get('version')!r}, "
                           f"not {FORMAT!r} {VERSIONS}")  # fmt: skip
    with np.load(d / spec["arrays"]["file"]) as z:
        arrays = {k: np.asarray(z[k]) for k in z.files}
    fields = [f for f in Exported.__dataclass_fields__ if f != "spec"]
    return Exported(spec, **{k: arrays[k] for k in fields})


class Stepper:
    """An engine as the driver sees it. ``step(dt)`` advances one step; the arrays are (N, 3) float64 in
    the scene's vertex order: ``positions()``/``set_positions(x)`` m, ``velocities()``/``set_velocities(v)``
    m/s. ``masses()`` (N,) kg, the engine's own lumped masses (kinetic energy for the damping).
    ``epsilon``: the machine epsilon of the engine's arithmetic (a relaxation stops at its round-off)."""

    epsilon: float = float(np.finfo(np.float64).eps)

    def internal_force(self) -> np.ndarray | None:
        """(N, 3) N: the engine's elastic force on each vertex at its present state (minus its energy's
        gradient), for the tools' force; None where the engine does not give its own law's."""
        return None

    def net_force(self) -> np.ndarray | None:
        """(N, 3) N: the net static force on each vertex at the present state (elastic, external and
        contact, what equilibrium zeroes), where the engine gives all of it; None elsewhere (the relaxation
        then stops on the displacement's change)."""
        return None

    def set_rigid(self, offset: np.ndarray, velocity: np.ndarray) -> None:
        """Put each rigid tool at ``offset`` (K, 3) m from its place at t = 0, moving at ``velocity`` (K, 3)
        m/s. An engine without a contact of its own raises AdapterError (it has no rigid tool to move)."""
        raise AdapterError("this adapter does not model a rigid tool's contact")

    def rigid_force(self) -> np.ndarray:
        """(K, 3) N: each rigid tool's force on the body, as the engine's contact exerts it at the present
        state."""
        raise AdapterError("this adapter does not model a rigid tool's contact")

    def unstable(self) -> bool:
        """Whether the engine itself found its state unstable (MuJoCo resets to rest when it does, which
        no displacement shows)."""
        return False

    def step(self, dt: float) -> None: ...

    def positions(self) -> np.ndarray: ...

    def set_positions(self, x: np.ndarray) -> None: ...

    def velocities(self) -> np.ndarray: ...

    def set_velocities(self, v: np.ndarray) -> None: ...

    def masses(self) -> np.ndarray: ...


class _Clock:
    """The engine's step calls timed in batches: the median of per-step means over batches. The first call
    is not timed (it compiles the engine's kernels, where it has any)."""

    def __init__(self, batch: int = 50):
        self.batch, self.samples, self._t, self._n, self._first = batch, [], 0.0, 0, True

    def timed(self, fn, *args) -> None:
        if self._first:
            self._first = False
            fn(*args)
            return
        t0 = time.perf_counter()
        fn(*args)
        self._t += time.perf_counter() - t0
        self._n += 1
        if self._n == self.batch:
            self.samples.append(self._t / self._n * 1e6)
            self._t, self._n = 0.0, 0

    def us(self) -> float | None:
        if self.samples:
            return float(np.median(self.samples))
        return self._t / self._n * 1e6 if self._n else None


def _impose(engine: Stepper, scene: Exported, held: np.ndarray, target: np.ndarray, velocity: np.ndarray) -> None:
    """The held and prescribed components put where the scene says, with the tools' velocity."""
    x, v = engine.positions(), engine.velocities()
    x[held] = (scene.points + target)[held]
    v[held] = velocity[held]
    engine.set_positions(x)
    engine.set_velocities(v)


def tool_force(engine: Stepper, scene: Exported) -> np.ndarray | None:
    """(3,) N: the force the tools exert on the body, -(f_int + f_ext) on the components they prescribe,
    summed (the reference's and the built-in models' definition; in a dynamic run the quasi-static part,
    a tool vertex's own inertia left out); None without the engine's internal force."""
    f = engine.internal_force()
    if f is None or len(scene.tool_vertex) == 0:
        return None
    total = f + scene.external_force
    return -(total[scene.tool_vertex] * scene.tool_mask).sum(axis=0)


def _ramped(engine: Stepper, scene: Exported, held, final: np.ndarray, n: int, ramp_steps: int, dt: float) -> None:
    """Before step ``n``: the tools at n / ramp_steps of their travel to ``final`` (N, 3) m, the rigid
    ones of theirs, moving at the ramp's speed through its last step, then still there."""
    moving = n <= ramp_steps
    speed = final / (ramp_steps * dt) if moving else np.zeros_like(final)
    _impose(engine, scene, held, min(n / ramp_steps, 1.0) * final, speed)
    if scene.spec.get("rigid_tools"):
        travel = scene.rigid_travel
        engine.set_rigid(min(n / ramp_steps, 1.0) * travel, travel / (ramp_steps * dt) if moving else 0.0 * travel)


def reaction(engine: Stepper, scene: Exported) -> tuple[np.ndarray | None, np.ndarray | None]:
    """The tools' force on the body (3,) N at the present state (``tool_force``, plus every rigid tool's
    contact force), and each rigid tool's (K, 3) N (None without any). The sum is None where vertex
    tools' force is unknown (no internal force from the engine)."""
    vertex = tool_force(engine, scene)
    if not scene.rigid:
        return vertex, None
    rigid = np.asarray(engine.rigid_force(), dtype=float).reshape(-1, 3)
    if len(scene.tool_vertex) and vertex is None:
        return None, rigid
    return rigid.sum(axis=0) + (0.0 if vertex is None else vertex), rigid


def _blown(u: np.ndarray, size: float, engine: Stepper) -> bool:
    """Diverged: a displacement that is not finite or over ten times the body, or the engine says so."""
    return not np.all(np.isfinite(u)) or float(np.abs(u).max()) > 10.0 * size or engine.unstable()


def residual(engine: Stepper, scene: Exported) -> float | None:
    """The net force on the free components (``Stepper.net_force``) relative to the larger of the load's
    norm and the elastic force's on the vertices the world does not hold, the tools' own included (their
    reaction where there is no load): the harness's ``rtol`` measure. None where the engine does not give its
    net force."""
    net = engine.net_force()
    if net is None:
        return None
    free = scene.free != 0.0
    f = engine.internal_force()
    moving = ~scene.held().all(axis=1)
    moving[scene.tool_vertex] = True  # the tools' vertices: their elastic force is the tools' reaction
    elastic = 0.0 if f is None else float(np.linalg.norm(f[moving]))
    scale = max(float(np.linalg.norm(scene.external_force[free])), elastic, 1e-300)
    return float(np.linalg.norm(net[free])) / scale


def round_off(engine: Stepper, scene: Exported) -> float:
    """The engine's round-off in a position, m: eight of its machine epsilons of the largest coordinate."""
    return 8.0 * engine.epsilon * float(np.abs(scene.points).max())


def relax(
    engine: Stepper, scene: Exported, dt: float, rtol: float, max_steps: int, progress, max_wall: float = 300.0
) -> dict:
    """A static scene's equilibrium by kinetic-damped dynamic relaxation (the module docstring). Where the
    engine gives its net force, it stops when the residual (``residual``) is below ``rtol``, the harness's own
    measure, twice in a row; elsewhere when the displacement change, measured over the last quarter of the run
    (at least ``check`` steps, so that a slow mode still on its way is seen however few steps one of its cycles
    takes), is. Either stops first where it makes no more progress: the change stalled below ``STALLED`` (or
    ``WALK`` round-offs), or the residual no longer halving over the last half of the run or on a plateau near
    the tolerance (``PLATEAU_STEPS``) (``stalled_at``, ``residual`` in the result), or at a fixed point of the
    engine's step, the residual level and the state still (``fixed_point`` 1: an implicit step solved to the
    engine's own tolerance, not round-off), and then runs the damped tail (``_stalled``). When its budget
    (``max_steps`` steps or ``max_wall`` seconds, whichever comes first) runs out before the stall rules'
    windows, they act on the run it had: a change below ``STALLED`` (or ``WALK`` round-offs) that failed to
    halve, one within ``WALK`` round-offs, a residual below ``STALLED`` that no longer halves, or either within
    ``BUDGET_TOLERANCE`` however it still falls, is a stall there too (``budget_spent`` 1 in the result:
    MuJoCo's discrete flex on the liver, its residual at 4e-8 after 300 s of 63 ms steps, was "not settled").
    Otherwise it stops unsettled."""
    held, final = scene.held(), scene.prescribed(0.0)
    t_start = time.perf_counter()
    ramp_steps = max(1, min(max_steps // 10, 200))
    clock, m = _Clock(), engine.masses()[:, None]
    check, calm, ke_prev = 50, 0, 0.0
    floor = round_off(engine, scene)
    past = []  # (step, displacement) every check steps, back to a quarter of the run
    changes = {}  # step: the relative change then
    residuals = {}  # step: the residual then, where the engine gives its net force
    best, best_at = np.inf, 0  # the least residual by 10 %, and the step it came at
    for n in range(1, max_steps + 1):
        _ramped(engine, scene, held, final, n, ramp_steps, dt)
        clock.timed(engine.step, dt)
        v = engine.velocities()
        ke = float((m * v * v).sum())
        if ke < ke_prev:  # past a peak of kinetic energy: start again from rest here
            engine.set_velocities(np.where(held, v, 0.0))
            ke = 0.0
        ke_prev = ke
        if n % check:
            continue
        u = engine.positions() - scene.points
        if _blown(u, scene.size, engine):
            return {"u": u, "steps": n, "dt": dt, "step_us": clock.us(), "diverged": 1, "diverged_at": n * dt}
        past = [(k, p) for k, p in past if k >= (3 * n) // 4 - check] + [(n, u)]
        change = float(np.abs(u - past[0][1]).max())
        scale = max(float(np.abs(u).max()), 1e-300)
        res = residual(engine, scene) if n > 2 * ramp_steps else None
        # the budget runs out by the next check: the stall rules then act on what the run has, however short
        spent = time.perf_counter() - t_start > max_wall or n + check > max_steps
        why = " (its budget spent)" if spent else " (round-off)"
        if res is not None:
            residuals[n] = res
            calm = calm + 1 if res <= rtol else 0
            earlier = [v for k, v in residuals.items() if k <= n // 2]
            recent = min(v for k, v in residuals.items() if k > n // 2)
            fixed = change <= WALK * floor  # the engine's steps no longer move the state
            level = earlier and recent >= 0.99 * min(earlier)  # no progress at all
            still = level and (fixed or res <= BUDGET_TOLERANCE)  # a fixed point, or a floor within the answer
            slow = earlier and recent > 0.5 * min(earlier)  # less than halving
            if res < 0.9 * best:
                best, best_at = res, n
            plateau = best < PLATEAU_FACTOR * rtol and n - best_at >= PLATEAU_STEPS
            due = (n >= RESIDUAL_WINDOW * ramp_steps and still) or (n >= 40 * ramp_steps and slow) or plateau
            ends = spent and (res <= BUDGET_TOLERANCE or ((still or slow) and res < STALLED))
            if res > rtol and (due or ends):
                at_fixed_point = fixed and not (spent or plateau)
                if at_fixed_point:
                    why = " (a fixed point of the engine's step: the state no longer moves)"
                elif not (spent or plateau):
                    why = (
                        f" (no progress over the last half of the run, within {BUDGET_TOLERANCE:g} of the load)"
                        if still
                        else " (no longer halving over the last half of the run, the state still moving)"
                    )
                progress(f"step {n}: the residual stalled at {res:.2e} of the load, asked {rtol:g}{why}")
                run = {"steps": n, "dt": dt, "step_us": clock.us(), "residual": res, "budget_spent": int(spent)}
                run["fixed_point"] = int(at_fixed_point)
                return _stalled(
                    engine, scene, dt, run, max_steps - n, max_wall - (time.perf_counter() - t_start), progress
                )
        else:
            calm = calm + 1 if n > 2 * ramp_steps and change <= max(rtol * scale, floor) else 0
        changes[n] = change / scale
        then = changes.get(check * ((n // 2) // check))
        slow = then is not None and max(STALLED, WALK * floor / scale) > changes[n] > 0.5 * then
        walked = change <= WALK * floor  # within the engine's round-off walk: nothing finer can be seen
        ends = spent and (changes[n] <= BUDGET_TOLERANCE or slow or walked)
        if res is None and calm < 2 and (((slow or walked) and n >= 40 * ramp_steps) or ends):
            progress(f"step {n}: the change stalled at {changes[n]:.2e} of the largest displacement{why}")
            run = {"steps": n, "dt": dt, "step_us": clock.us(), "stalled_at": changes[n], "budget_spent": int(spent)}
            return _stalled(engine, scene, dt, run, max_steps - n, max_wall - (time.perf_counter() - t_start), progress)
        if time.perf_counter() - t_start > max_wall:
            progress(f"step {n}: still moving ({change / scale:.2e}) after {max_wall:g} s, stopped")
            return {"u": u, "steps": n, "dt": dt, "step_us": clock.us(), "settled": 0, "wall_limit": max_wall}
        if n % (check * 200) == 0:
            what = (
                f"residual {res:.2e} of the load"
                if res is not None
                else f"displacement change {change / scale:.2e} of its largest value ({change:.2e} of {scale:.2e} m)"
            )
            progress(f"step {n}: {what}, asked {rtol:g}")
        if calm >= 2:
            return _held(engine, scene, u, dt, {"steps": n, "dt": dt, "step_us": clock.us(), "residual": res})
    u = engine.positions() - scene.points
    return {"u": u, "steps": max_steps, "dt": dt, "step_us": clock.us(), "settled": 0}


def _stalled(engine: Stepper, scene: Exported, dt: float, run: dict, steps: int, wall: float, progress) -> dict:
    """A relaxation that round-off stopped (``run``: its steps, dt, step time, where it stalled): the
    damped tail within what is left of the step and time budgets (``steps``, ``wall`` s), then the hold."""
    budget = min(steps, int(wall * 1e6 / (run["step_us"] or 1e6)))
    u, tail = _damped_tail(engine, scene, dt, budget, progress)
    run.update({f"tail_{k}": v for k, v in tail.items()}, steps=run["steps"] + tail["steps"])
    if tail["steps"] and run.get("residual") is not None:
        run["residual"] = residual(engine, scene)
    return _held(engine, scene, u, dt, run)


#: A damped tail runs this many of its slowest mode's time constants 1 / omega.
TAIL_TIMES = 16.0


def _damped_tail(engine: Stepper, scene: Exported, dt: float, budget: int, progress) -> tuple:
    """Where kinetic damping stalls, the answer may still drift along the slowest mode, below the random
    walk an engine's float32 force leaves in the change it measures (newton's semi-implicit solver on the
    cantilever: stalled 1.5e-3 from its own law's P1 answer, 8.7e-4 after six times as many steps more,
    1.5e-4 after this tail of about as many steps as the stall took).
    Its omega^2 is read by Rayleigh's method: the quotient of the displacement itself on the free
    components (a static deflection is the slowest mode's shape to first order, where the drift, noise
    and all, overestimates it fourfold), its stiffness product from the engine's own force at a state
    displaced a thousandth further along it; the run then goes on with mass-proportional damping 2 omega,
    critical for that mode, for TAIL_TIMES / omega.
    Returns the displacement (N, 3) m and the tail's record (omega rad/s, alpha 1/s, steps; steps 0 where
    the engine gives no force of its own or the quotient is not positive)."""
    u = engine.positions() - scene.points
    f0 = engine.internal_force()
    step = 1e-3 * np.where(scene.held(), 0.0, u)
    if f0 is None or not np.abs(step).max() > 0.0 or budget <= 0:
        return u, {"steps": 0}
    engine.set_positions(scene.points + u + step)
    f1 = engine.internal_force()
    engine.set_positions(scene.points + u)
    m = engine.masses()[:, None]
    omega2 = float(np.sum(step * (f0 - f1)) / max(float(np.sum(m * step * step)), 1e-300))
    if not (np.isfinite(omega2) and omega2 > 0.0):
        return u, {"steps": 0}
    omega = omega2**0.5
    alpha, k = 2.0 * omega, min(budget, int(TAIL_TIMES / (omega * dt)))
    progress(f"the drift's mode: omega = {omega:.3g} rad/s; {k} steps damped at {alpha:.3g} 1/s (critical for it)")
    held, target = scene.held(), scene.points + scene.prescribed(0.0)
    engine.set_velocities(np.zeros_like(u))
    for _ in range(k):  # each step: the damping and the held components in one round trip of the state
        engine.step(dt)
        x, v = engine.positions(), engine.velocities() / (1.0 + alpha * dt)
        x[held], v[held] = target[held], 0.0
        engine.set_positions(x)
        engine.set_velocities(v)
    return engine.positions() - scene.points, {"omega": omega, "alpha": alpha, "steps": k}


def _held(engine: Stepper, scene: Exported, u: np.ndarray, dt: float, run: dict) -> dict:
    """A relaxed state checked for what a static answer is: released from rest, the engine stays there.
    It runs HOLD_STEPS steps with no damping; if the displacement then moves by more than HOLD of its
    largest value (or than the engine's round-off in a position, where that is larger), the state is no
    equilibrium of the engine at this step (an iterative solver that does not converge per step can stall
    the relaxation away from it) and the run is "not settled"."""
    held, still = scene.held(), np.zeros_like(u)
    engine.set_velocities(still)
    for _ in range(HOLD_STEPS):
        _impose(engine, scene, held, scene.prescribed(0.0), still)  # the tools stay where they are
        engine.step(dt)
    # relative to the displacement, or where that is within round_off / HOLD (a body a rigid tool has not
    # reached yet) to that: a movement at the engine's round-off holds (newton's float32 noise read 0.21 of
    # a displacement of nothing on the liver press)
    scale = max(float(np.abs(u).max()), round_off(engine, scene) / HOLD)
    drift = float(np.abs(engine.positions() - scene.points - u).max() / scale)
    out = {"u": u, **run, "settled": int(drift <= HOLD), "hold_drift": drift, "hold_steps": HOLD_STEPS}
    engine.set_positions(scene.points + u)  # the relaxed state, for its tools' force
    engine.set_velocities(np.zeros_like(u))
    total, rigid = reaction(engine, scene)
    return {**out, "reaction": total, "rigid_force": rigid}


def probe(engine: Stepper, scene: Exported, dt: float, steps: int, progress) -> dict:
    """Is ``dt`` a stable step of the engine on this scene: ``steps`` steps of its plain dynamics from rest
    (no damping of ours), the loads on and the tools moved to their final place over the first tenth, and
    whether the displacement stays bounded (``diverged`` otherwise). Its displacement is the last step's,
    not an answer to judge."""
    held, final = scene.held(), scene.prescribed(0.0)
    ramp_steps = max(1, steps // 10)
    clock = _Clock()
    for n in range(1, steps + 1):
        _ramped(engine, scene, held, final, n, ramp_steps, dt)
        clock.timed(engine.step, dt)
        if n % 50 == 0 or n == steps:
            u = engine.positions() - scene.points
            if _blown(u, scene.size, engine):
                return {"u": u, "steps": n, "dt": dt, "step_us": clock.us(), "diverged": 1, "diverged_at": n * dt}
        if n % 1000 == 0:
            progress(f"stability probe: step {n} of {steps}")
    return {"u": engine.positions() - scene.points, "steps": steps, "dt": dt, "step_us": clock.us(), "probe": steps}


def trajectory(engine: Stepper, scene: Exported, dt: float, progress) -> dict:
    """A dynamic scene from rest, sampled at its output instants."""
    held, times = scene.held(), scene.output_times
    n_total = int(np.ceil(times[-1] / dt - 1e-9))
    clock, out, t, k = _Clock(), [np.zeros_like(scene.points)], 0.0, 1
    forces = [tool_force(engine, scene)]
    for n in range(1, n_total + 1):
        t_next = min(n * dt, times[-1])
        h = t_next - t
        _impose(engine, scene, held, scene.prescribed(t), (scene.prescribed(t_next) - scene.prescribed(t)) / h)
        clock.timed(engine.step, h)
        t = t_next
        while k < len(times) and t >= times[k] - 1e-9 * dt:
            _impose(engine, scene, held, scene.prescribed(times[k]), np.zeros_like(scene.points))
            u = engine.positions() - scene.points
            if _blown(u, scene.size, engine):
                return {"u": np.array(out + [u]), "steps": n, "dt": dt, "step_us": clock.us(), "diverged": 1,
                        "diverged_at": t}  # fmt: skip
            out.append(u)
            forces.append(tool_force(engine, scene))
            k += 1
        if n % 2000 == 0:
            progress(f"t = {t:.4g} of {times[-1]:g} s")
    reaction = None if any(f is None for f in forces) else np.array(forces)
    return {"u": np.array(out), "steps": n_total, "dt": dt, "step_us": clock.us(), "reaction": reaction}


def write(path: str | Path, scene: Exported, run: dict, law: str, engine: str) -> None:
    """The result as the harness reads it (the module docstring), written whole (a temporary file, then a
    rename)."""
    u = np.asarray(run["u"], dtype=float)
    if u.ndim == 2:
        u = u[None]
    keys = {k: v for k, v in run.items() if k != "u" and v is not None}
    out = Path(path)
    tmp = out.with_name(out.name + ".part.npz")
    np.savez(tmp, displacement=u, law=law, engine=engine, **keys)
    os.replace(tmp, out)


def arguments(description: str, solvers: tuple[str, ...]) -> argparse.ArgumentParser:
    """The command line every adapter takes: SCENE_DIR RESULT.npz and the engine's knobs."""
    ap = argparse.ArgumentParser(description=description)
    ap.add_argument("scene", help="the directory tissuebench export wrote")
    ap.add_argument("result", help="the .npz to write")
    ap.add_argument("--solver", choices=solvers, default=solvers[0])
    ap.add_argument("--dt", type=float, help="the time step, s (default: the adapter's stable guess)")
    ap.add_argument("--iterations", type=int, default=10, help="solver iterations per step (where it has them)")
    ap.add_argument("--substeps", type=int, default=1, help="steps per dt (dt / substeps each)")
    ap.add_argument("--rtol", type=float, default=1e-6, help="a static run's relaxation tolerance")
    ap.add_argument("--max-steps", type=int, default=100_000, help="a static run's most steps")
    ap.add_argument("--max-wall", type=float, default=300.0, help="a static run's most seconds")
    ap.add_argument("--probe", type=int, default=0, help="only test dt's stability: this many plain steps from rest")
    ap.add_argument("--device", default="cpu", help="warp's device a warp engine runs on (cpu, cuda, cuda:N)")
    return ap


#: The line a served adapter (``main``'s ``--serve``) writes on stderr after each run, with its exit status.
SERVED = "tissuebench-adapter-served:"


def main(run, description: str, solvers: tuple[str, ...], argv=None, more=None) -> int:
    """Parse (``more(parser)`` adds an engine's own options), run ``run(scene, args, progress) -> (run dict,
    law, engine)``, write; one line and exit 2 on an AdapterError. With the single argument ``--serve``,
    many runs in this one process (``serve``)."""
    argv = sys.argv[1:] if argv is None else list(argv)
    if argv == ["--serve"]:
        return serve(run, description, solvers, more)
    parser = arguments(description, solvers)
    if more is not None:
        more(parser)
    args = parser.parse_args(argv)
    name = Path(sys.argv[0]).stem

    def progress(text: str) -> None:
        print(f"{name} {args.solver}: {text}", file=sys.stderr, flush=True)

    try:
        scene = read(args.scene)
        result, law, engine = run(scene, args, progress)
    except AdapterError as exc:
        print(f"{name}: {exc}", file=sys.stderr)
        return 2
    write(args.result, scene, result, law, engine)
    return 0


def serve(run, description: str, solvers: tuple[str, ...], more=None) -> int:
    """Runs one after another in this process, each a line of stdin (a JSON list: the command line a run
    would have), each ended by ``SERVED`` and the status it would have exited with on stderr: the engine is
    imported once (newton and warp take 2.6 s to import, a run on the liver a few seconds more). A run that
    fails otherwise than by an AdapterError ends the service (its engine may be left in any state)."""
    import traceback

    for line in sys.stdin:
        try:
            status = main(run, description, solvers, json.loads(line), more)
        except SystemExit as exc:  # argparse's own exit on a command line it refuses
            status = exc.code if isinstance(exc.code, int) else 2
        except Exception:
            traceback.print_exc()
            status = 1
        print(f"{SERVED} {status}", file=sys.stderr, flush=True)
        if status not in (0, 2):
            return status
    return 0


def drive(engine: Stepper, scene: Exported, args, dt: float, progress) -> dict:
    """The scene run on ``engine`` at ``dt`` (split into ``args.substeps``): relaxed if static, a trajectory
    if dynamic; with ``args.probe``, only the stability probe."""
    if scene.rigid and not scene.static:
        raise AdapterError("a rigid tool in a dynamic scene: the adapters move rigid tools in static scenes only")
    if args.probe:
        return probe(engine, scene, dt, args.probe, progress)
    if scene.static:
        return relax(engine, scene, dt, args.rtol, args.max_steps, progress, args.max_wall)
    return trajectory(engine, scene, dt, progress)
