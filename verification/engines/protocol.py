"""The seam between the harness and an engine (docs/data-flow.md).

Every study builds, steps and reads a model through these two protocols and nothing else: the harness
chooses the time step, samples the output instants, times the steps and compares; an engine turns a
scene's arrays into a running simulation. The built-in models are one engine
(``verification.engines.builtin``); an engine in another process or another venv is another, behind the
same calls, which is why every argument is plain data (arrays, numbers, strings) and every answer too.

The order of calls: ``Engine.build`` once; then ``critical_dt`` and ``start`` before any step; then, for
a dynamic scene, ``advance_to`` each output instant in turn, reading ``displacement`` and ``tool_force``
after each; for a static one, ``settle``, then the same two reads. ``step`` is what the harness times
(after the answer was read: timing moves the state on).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from typing import Protocol, runtime_checkable

import numpy as np

from realtime.material import Material, Materials
from realtime.model import Loading
from realtime.models import ModelSpec


@dataclass(frozen=True)
class TimeMode:
    """The scene's time mode: "static" (an equilibrium) or "dynamic" (a trajectory from rest to ``end``,
    s, sampled every ``output_every``, s), with Rayleigh damping C = ``damping_mass`` M (1/s) +
    ``damping_stiffness`` K (s)."""

    mode: str
    end: float
    output_every: float
    damping_mass: float
    damping_stiffness: float


@dataclass(frozen=True)
class SceneInputs:
    """A scene as what an engine builds from: plain arrays in SI units (docs/data-flow.md).

    Attributes:
        name: the scene's name (for messages and file names).
        source: the scene file, as the user named it (error messages name it).
        sha256: the scene's content hash (``Scene.sha256``): an engine's caches key on it.
        points: (N, 3) float64, m, the rest positions of the scene mesh's vertices.
        tets: (M, 4) int64, positively oriented tetrahedra of ``points``.
        material: the Material of the whole body, or Materials, one per tetrahedron (SI: Pa, kg/m^3).
        loading: the constraints and loads on ``points`` as ``realtime.model.Loading`` (arrays only):
            ``free`` (N, 3) 1.0 where a component moves and 0.0 where it is held; ``external_force``
            (N, 3) N, the P1 nodal vector of gravity, forces and tractions; the tools' vertices and
            their prescribed motion with its ramp in time.
        time: the TimeMode.
        gravity: (3,) m/s^2, the scene's gravity (already in ``loading.external_force``; for an engine that
            applies its own body force).
        loading_on: for an engine in this process that runs on a mesh of its own whose vertices lie on
            the scene mesh's (adaptive refinement), the loading of the same scene on that mesh
            (a function of its points (V, 3) m, tetrahedra (K, 4) and densities (K,) kg/m^3);
            None where the scene crossed a process boundary.
        regions: for an engine that meshes the body itself, the scene's held and driven regions by their
            rule (``meshes.regions.Region.rule``): "fixed", one entry a [[fixed]] table, and "tools", one
            a tool in ``loading``'s order, each {"rule": dict or None, "components": ["x", ...]}; empty
            where the scene was not made from a scene file.
    """

    name: str
    source: str
    sha256: str
    points: np.ndarray
    tets: np.ndarray
    material: Material | Materials
    loading: Loading
    time: TimeMode
    gravity: tuple[float, float, float] = (0.0, 0.0, 0.0)
    loading_on: Callable | None = field(default=None, repr=False, compare=False)
    regions: Mapping = field(default_factory=dict, compare=False)

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def has_tools(self) -> bool:
        return len(self.loading.tool_vertex) > 0


@dataclass(frozen=True)
class Settling:
    """What ``Simulation.settle`` reports: the steps it took from rest, the final relative residual (None
    where the engine does not measure one), its step dt and the explicit critical step dt_crit (s,
    None where it has none), and ``meta``: the engine's own record of how it settled (method, options),
    kept in the result's meta under "static" and beside it."""

    steps: int
    residual: float | None
    dt: float | None
    dt_crit: float | None
    wall_s: float
    static: dict
    meta: dict = field(default_factory=dict)


@runtime_checkable
class Simulation(Protocol):
    """One model of one engine built on one scene, with its state."""

    #: The model's name, and what advances it ("symplectic-euler", "quasi-static", an engine's solver).
    model: str
    integrator: str
    #: (n, repeats): how many steps the harness times in one call to ``step``, and how often; None for an
    #: engine that times itself (in a process of its own): the harness then asks ``step_us()``.
    timing: tuple[int, int] | None

    def critical_dt(self) -> float | None:
        """The largest stable step at rest, s, of an explicit integrator; None where the engine has no
        such limit (a quasi-static update)."""

    def start(self, dt: float | None) -> None:
        """Back to rest (u = v = 0 at t = 0), stepping with dt (s; None where the engine steps by the
        output instants)."""

    def advance_to(self, t: float) -> None:
        """Step until time t (s) and hold the state at t (by the engine's own sampling between its
        steps) for ``displacement`` and ``tool_force``."""

    def settle(self, rtol: float, max_steps: int, dt: float | None, dt_fraction: float | None) -> Settling:
        """Bring a static scene to equilibrium from rest, to a residual of ``rtol`` of the load, in at most
        ``max_steps`` steps (else NotConvergedError; DivergenceError if it blows up)."""

    def step(self, n: int) -> None:
        """n steps of the chosen dt (what the harness times)."""

    def step_us(self) -> float | None:
        """Only where ``timing`` is None: the engine's own time per step, us, or None if it reports none."""

    def displacement(self) -> np.ndarray:
        """(N, 3) float64, m: the displacement of the scene's N vertices now."""

    def tool_force(self) -> np.ndarray:
        """(3,) float64, N: the tools' total force on the body now."""


@runtime_checkable
class Engine(Protocol):
    """An engine: its name, the models it offers (each name with its ModelSpec: what the harness may know
    of it; a plug-in may list bare names, and then says nothing of them), and how one is built on a
    scene."""

    name: str
    models: Mapping[str, ModelSpec] | tuple[str, ...]

    def build(self, inputs: SceneInputs, model: str, integrator: str, options: dict) -> Simulation:
        """The model ``model`` on the scene ``inputs``, advanced by ``integrator``, with the model's own
        ``options`` (for example a threshold); InputError for what it cannot build."""


def foreign_spec(model: str, law: str, **facts) -> ModelSpec:
    """The spec of a model another engine builds: no builder here, ``law`` its own words, and whatever of
    ``facts`` (ModelSpec's fields) it declares; what it represents is unknown unless declared."""
    return ModelSpec(**{"name": model, "build": None, "law": law, "represents": None, **facts})
