"""Immutable model, mutable state, and the loading they share (after NVIDIA Warp's old warp.sim).

A ``Model`` is built once (``realtime.build_model``) and never changes during a run: rest positions,
tetrahedra, lumped masses, the material, the model's force kernel with its precomputed data, and the
``Loading`` (constraints, external forces, tools). A ``State`` is what an integrator advances:
displacements, velocities, time. Nothing in a Model refers to a State, so one model can drive many
states in turn (a sweep over time steps). Nothing a step writes lives in a Model either: the element
kernels' scratch blocks (``Model.new_scratch``) and the force buffers belong to the integrator's
workspace, so that a step allocates nothing and two threads can step two states on one model at
once (a haptic loop beside a visual one), each with its own integrator.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import NamedTuple

import numba as nb
import numpy as np

from .contact import areas as contact_areas
from .contact import check as check_contacts
from .contact import forces as contact_forces
from .errors import InputError, LoadingError, float_array, index_array, whole_numbers
from .geometry import InvalidMeshError, check_tets, lumped_volumes, signed_volumes
from .material import Material, Materials
from .ramps import RAMP_SHAPES, ramp_fraction

_JIT = dict(nogil=True, cache=True)

#: The scratch tuple of the force kernels that write nothing besides their output (linear tensor-mass,
#: springs): every force kernel takes one, so that the integrators call them all alike.
NO_SCRATCH = (np.zeros(0),)


def no_scratch() -> tuple:
    """Model.new_scratch of those kernels: NO_SCRATCH (shared; they never write it)."""
    return NO_SCRATCH


#: The float types a model may run in (Model.precision): numpy's name -> dtype.
PRECISIONS = {"float64": np.dtype(np.float64), "float32": np.dtype(np.float32)}

TOOL_TRANSLATION = 0
TOOL_ROTATION = 1


class Tools(NamedTuple):
    """The tool arrays the compiled loops take, with the shapes and units of Loading's fields of the same
    meaning (vertex: tool_vertex, mask: tool_mask, tool: tool_id, kind: tool_kind, vector: tool_vector,
    axis: tool_axis, center: tool_center, angle: tool_angle, ramp: tool_ramp, shape: tool_ramp_shape)."""

    vertex: np.ndarray
    mask: np.ndarray
    tool: np.ndarray
    kind: np.ndarray
    vector: np.ndarray
    axis: np.ndarray
    center: np.ndarray
    angle: np.ndarray
    ramp: np.ndarray
    shape: np.ndarray


@dataclass(frozen=True)
class Loading:
    """Constraints and loads on a mesh of N vertices with L tools touching P vertices in all.

    Attributes:
        free: (N, 3) float64, 1.0 where the component moves freely, 0.0 where it is fixed or prescribed.
        external_force: (N, 3) float64, N; constant nodal forces (gravity, forces, tractions).
        tool_vertex: (P,) int64 vertices driven by tools.
        tool_mask: (P, 3) float64, 1.0 on the prescribed components of that vertex.
        tool_id: (P,) int64, which tool drives the vertex.
        tool_kind: (L,) int64, TOOL_TRANSLATION or TOOL_ROTATION.
        tool_vector: (L, 3) float64, final translation, m (translations).
        tool_axis: (L, 3) float64, unit rotation axis (rotations).
        tool_center: (L, 3) float64, point on the axis, m (rotations).
        tool_angle: (L,) float64, final angle, rad (rotations).
        tool_ramp: (L,) float64, s; the tool moves (the angle, for rotations) from 0 at t = 0 and holds
            its final value from t = ramp on; 0 means applied at once.
        tool_ramp_shape: (L,) int64, the index in RAMP_SHAPES of how it moves in between.
        contacts: rigid tools touching the body (``realtime.contact.Contacts``, made by
            ``realtime.contact.contacts``), or None: no rigid tool.
    """

    free: np.ndarray
    external_force: np.ndarray
    tool_vertex: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tool_mask: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tool_id: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tool_kind: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    tool_vector: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tool_axis: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tool_center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    tool_angle: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tool_ramp: np.ndarray = field(default_factory=lambda: np.zeros(0))
    tool_ramp_shape: np.ndarray | None = None
    contacts: object = None

    def __post_init__(self):
        if self.tool_ramp_shape is None:  # linear unless said otherwise
            object.__setattr__(self, "tool_ramp_shape", np.zeros(len(self.tool_ramp), dtype=np.int64))

    def check(self, n_vertices: int) -> None:
        """Raise LoadingError unless every array has its documented shape and dtype, finite values and
        indices in range for a mesh of ``n_vertices`` (the kernels do no bounds checks: a bad index
        would write outside an array), free 0 or 1, and 0 on every component a tool prescribes."""
        n_points = len(np.asarray(self.tool_vertex).reshape(-1))
        n_tools = len(np.asarray(self.tool_kind).reshape(-1))
        shapes = {
            "free": ((n_vertices, 3), np.float64),
            "external_force": ((n_vertices, 3), np.float64),
            "tool_vertex": ((n_points,), np.int64),
            "tool_mask": ((n_points, 3), np.float64),
            "tool_id": ((n_points,), np.int64),
            "tool_kind": ((n_tools,), np.int64),
            "tool_vector": ((n_tools, 3), np.float64),
            "tool_axis": ((n_tools, 3), np.float64),
            "tool_center": ((n_tools, 3), np.float64),
            "tool_angle": ((n_tools,), np.float64),
            "tool_ramp": ((n_tools,), np.float64),
            "tool_ramp_shape": ((n_tools,), np.int64),
        }
        for name, (shape, dtype) in shapes.items():
            a = getattr(self, name)
            if not isinstance(a, np.ndarray) or a.shape != shape or a.dtype != dtype:
                got = f"{a.shape} {a.dtype}" if isinstance(a, np.ndarray) else type(a).__name__
                raise LoadingError(f"Loading.{name}: must be a {shape} {np.dtype(dtype)} array, got {got}")
            if dtype == np.float64 and not np.all(np.isfinite(a)):
                bad = tuple(int(i) for i in np.argwhere(~np.isfinite(a))[0])
                raise LoadingError(f"Loading.{name}{list(bad)}: must be finite, got {a[bad]}")
        for name, upper in (
            ("tool_vertex", n_vertices),
            ("tool_id", n_tools),
            ("tool_kind", 2),
            ("tool_ramp_shape", len(RAMP_SHAPES)),
        ):
            a = getattr(self, name)
            if len(a) and (a.min() < 0 or a.max() >= upper):
                bad = int(np.argmax((a < 0) | (a >= upper)))
                raise LoadingError(f"Loading.{name}[{bad}] = {a[bad]}: must lie in 0..{upper - 1}")
        if not np.all((self.free == 0.0) | (self.free == 1.0)):
            bad = tuple(int(i) for i in np.argwhere((self.free != 0.0) & (self.free != 1.0))[0])
            raise LoadingError(f"Loading.free{list(bad)} = {self.free[bad]}: must be 1 (free) or 0 (held)")
        prescribed = self.free[self.tool_vertex] * (self.tool_mask != 0.0)
        if np.any(prescribed != 0.0):
            p, c = (int(i) for i in np.argwhere(prescribed != 0.0)[0])
            raise LoadingError(
                f"Loading.free[{int(self.tool_vertex[p])}, {c}] = 1.0: tool {int(self.tool_id[p])} prescribes that "
                "component, so it is not free (set it to 0): the static and condensed solvers and the spectra "
                "read free alone"
            )
        if len(self.tool_ramp) and self.tool_ramp.min() < 0.0:
            bad = int(np.argmin(self.tool_ramp))
            raise LoadingError(f"Loading.tool_ramp[{bad}] = {self.tool_ramp[bad]}: must be >= 0 s")
        if self.contacts is not None:
            check_contacts(self.contacts, n_vertices)

    @staticmethod
    def translating_tool(
        free: np.ndarray, external_force: np.ndarray, vertices, vector=(0.0, 0.0, 0.0), ramp: float = 0.0, mask=None
    ) -> Loading:
        """One translating tool on ``vertices`` (P,) int, moving them by ``vector`` (3,) m over ``ramp`` s
        (linearly; 0: at once) on the components ``mask`` (P, 3) or (3,) float64 holds (default all three),
        with the given ``free`` (a copy, with the tool's components cleared: a prescribed component is
        not free) and ``external_force``."""
        vertices = index_array("Loading.translating_tool: vertices", vertices, len(free), error=LoadingError)
        mask = np.ones(3) if mask is None else np.asarray(mask, dtype=np.float64)
        tool_mask = np.ascontiguousarray(np.broadcast_to(mask, (len(vertices), 3)))
        free = np.array(free, dtype=np.float64)
        free[vertices] *= tool_mask == 0.0
        return Loading(
            free=free,
            external_force=external_force,
            tool_vertex=vertices,
            tool_mask=tool_mask,
            tool_id=np.zeros(len(vertices), dtype=np.int64),
            tool_kind=np.zeros(1, dtype=np.int64),
            tool_vector=np.array([vector], dtype=np.float64),
            tool_axis=np.array([[0.0, 0.0, 1.0]]),
            tool_center=np.zeros((1, 3)),
            tool_angle=np.zeros(1),
            tool_ramp=np.array([float(ramp)]),
        )

    @staticmethod
    def free_body(n_vertices: int) -> Loading:
        """No constraint and no load."""
        return Loading(free=np.ones((n_vertices, 3)), external_force=np.zeros((n_vertices, 3)))

    def tools_tuple(self) -> Tools:
        """The tool arrays as the compiled loops take them."""
        return Tools(
            self.tool_vertex,
            self.tool_mask,
            self.tool_id,
            self.tool_kind,
            self.tool_vector,
            self.tool_axis,
            self.tool_center,
            self.tool_angle,
            self.tool_ramp,
            self.tool_ramp_shape,
        )


@dataclass
class State:
    """What an integrator advances.

    Attributes:
        u: (N, 3) displacement from the rest positions, m, in the model's float type (Model.dtype:
            float64, or float32 for a float32 model).
        v: (N, 3) velocity, m/s, the same type.
        t: time, s.
        steps: number of steps taken.
        acc: (N, 3) float64 acceleration, m/s^2, kept by integrators that need it between calls
            (central difference); None until the first step. Set it to None after changing u or v.
        acc_key: which integrator workspace and forces ``acc`` was computed with (set_forces makes it
            stale); None when unknown.
    """

    u: np.ndarray
    v: np.ndarray
    t: float = 0.0
    steps: int = 0
    acc: np.ndarray | None = None
    acc_key: tuple | None = None

    @staticmethod
    def at_rest(n_vertices: int, dtype=np.float64) -> State:
        """u = v = 0 for N = ``n_vertices``, in ``dtype`` (a model's ``dtype``: Model.rest_state)."""
        return State(u=np.zeros((n_vertices, 3), dtype), v=np.zeros((n_vertices, 3), dtype))

    def copy(self) -> State:
        acc = None if self.acc is None else self.acc.copy()
        return State(self.u.copy(), self.v.copy(), self.t, self.steps, acc, self.acc_key)


class Deferred:
    """A Model field's value made when first read: a cut's model gets its tetrahedra (and the material of
    each) as ``Deferred(lambda: ...)``, so that the cut itself costs what it touches. Gathering the
    57 837 alive tetrahedra of liver-x10 took 2 ms, a haptic frame, at every cut; a simulator that steps
    the cut model never reads them (its kernel has its own tensors)."""

    __slots__ = ("make",)

    def __init__(self, make: Callable[[], object]):
        self.make = make


class _DeferredField:
    """The descriptor of a Model field that may be given a ``Deferred``: read, it makes and keeps the
    value. A required field still (no default: reading it on the class raises AttributeError)."""

    def __set_name__(self, owner, name: str) -> None:
        self.name = name

    def __get__(self, obj, objtype=None):
        if obj is None:
            raise AttributeError(self.name)
        value = obj.__dict__[self.name]
        if isinstance(value, Deferred):
            value = obj.__dict__[self.name] = value.make()
        return value

    def __set__(self, obj, value) -> None:
        obj.__dict__[self.name] = value


@dataclass(frozen=True)
class Model:
    """A real-time model, ready to step.

    Attributes:
        name: the model's name (its ModelSpec's, realtime.models).
        points: (N, 3) float64 rest positions, m.
        tets: (M, 4) int64, positively oriented (may be given Deferred: made when first read).
        material: the Material, or the Materials of a body made of several (one per tetrahedron; may
            be given Deferred).
        mass: (N,) float64 lumped masses, kg (rho V / 4 from each tetrahedron).
        loading: constraints and loads.
        force_kernel: numba function ``force(data, scratch, u, f)`` writing the internal force (N, 3), N.
        energy_kernel: numba function ``energy(data, u) -> float`` elastic energy, J.
        data: the tuple of read-only arrays the kernels take.
        linear: True if the internal force is linear in u (the stiffness never changes).
        extra: model-specific objects (for example the TensorMass, for cutting).
        new_scratch: a function returning a fresh tuple of the arrays ``force_kernel`` writes besides
            its output (each caller that steps the model at the same time as another needs its own).
        rest_stiffness_of: the model's own ``rest_stiffness`` (a function of the model).
        eigenvalue_bound_of: the model's own ``element_eigenvalue_bound`` (a function of the model).
        precision: "float64", or "float32": the force kernel's data, the state and the force buffers
            in single precision, the kernel computing in it (the models whose ModelSpec says float32; the
            geometry, masses and loads stay float64, the updates compute in float64 and round).
    """

    name: str
    points: np.ndarray
    tets: np.ndarray = _DeferredField()
    material: Material | Materials = _DeferredField()
    mass: np.ndarray
    loading: Loading
    force_kernel: Callable
    energy_kernel: Callable
    data: tuple
    linear: bool
    extra: dict = field(default_factory=dict)
    new_scratch: Callable[[], tuple] = no_scratch
    rest_stiffness_of: Callable | None = None
    eigenvalue_bound_of: Callable | None = None
    precision: str = "float64"

    @property
    def n_vertices(self) -> int:
        return len(self.points)

    @property
    def dtype(self) -> np.dtype:
        """The float type of the state, the force buffers and the force kernel's arithmetic."""
        return PRECISIONS[self.precision]

    def rest_state(self) -> State:
        """A State at rest for this model (u = v = 0 in its ``dtype``)."""
        return State.at_rest(self.n_vertices, self.dtype)

    @property
    def materials(self) -> Materials:
        """The material of each tetrahedron of ``tets`` (Materials.of ``material``)."""
        return Materials.of(self.material, len(self.tets))

    def nodal(self, what: str, value) -> np.ndarray:
        """``value`` as a C-contiguous (N, 3) array of the model's ``dtype`` (a copy only where needed),
        or InputError naming ``what`` and what it got: the kernels index (N, 3) arrays without bounds
        checks, so a shorter one would be read or written past its end (a (3, 3) u given to
        internal_force corrupted the heap and aborted the process)."""
        a = float_array(what, value, self.dtype, f"an ({self.n_vertices}, 3) array")
        if a.shape != (self.n_vertices, 3):
            raise InputError(f"{what}: must have shape ({self.n_vertices}, 3) (the model's vertices), got {a.shape}")
        return a

    def internal_force(self, u: np.ndarray) -> np.ndarray:
        """Internal elastic force (N, 3), N, at displacement u (N, 3) m, both in the model's ``dtype`` (u
        is rounded to it; with scratch of its own: safe beside any other call). A model whose force
        remembers (hybrid-tm's hysteresis) gives it here as from rest; an integrator's
        ``internal_force`` gives it with the run's memory."""
        return self.force_with(self.new_scratch(), u)

    def force_with(self, scratch: tuple, u: np.ndarray) -> np.ndarray:
        """The internal force (N, 3), N, at u (N, 3) m with the kernel's ``scratch`` (a tuple as
        ``new_scratch`` makes, which the call updates)."""
        u = self.nodal("internal_force: u", u)
        f = np.empty_like(u)
        self.force_kernel(self.data, scratch, u, f)
        return f

    def rest_stiffness(self):
        """The stiffness at rest, scipy CSR (3N, 3N) N/m (dof 3 i + c), as the model defines it: the
        springs' for mass-spring, the P1 linear stiffness of its material for the tetrahedral models
        (the volume penalty left out). Implicit Euler's preconditioner and the slowest mode use it."""
        return self.rest_stiffness_of(self)

    def element_eigenvalue_bound(self) -> float:
        """max over the model's elements of lambda_max(K_e, M_e), 1/s^2: an upper bound on omega_max^2
        at rest (``spectra.element_critical_dt``)."""
        return self.eigenvalue_bound_of(self)

    def check_current(self) -> None:
        """Raise InputError if this model's mesh was changed since it was built (``realtime.models.linear_tm.cut``,
        ``realtime.topology.slit`` or ``suture`` returned its successor, which shares and has changed its
        stiffness tensors)."""
        tensors = self.extra.get("tensors")
        if tensors is not None and tensors.generation != self.extra.get("generation", tensors.generation):
            raise InputError(
                f"{self.name}: this model's mesh was changed {tensors.generation - self.extra['generation']} time(s) "
                "since it was built (cut, slit or sutured); step the model realtime.models.linear_tm.cut or realtime.topology "
                "returned"
            )

    def elastic_energy(self, u: np.ndarray) -> float:
        """Elastic energy, J, at displacement u (N, 3) m (rounded to the model's ``dtype``)."""
        return float(self.energy_kernel(self.data, self.nodal("elastic_energy: u", u)))

    def kinetic_energy(self, v: np.ndarray) -> float:
        """Kinetic energy sum m |v|^2 / 2, J, for velocities v (N, 3) m/s."""
        v = self.nodal("kinetic_energy: v", v)
        return float(0.5 * np.sum(self.mass[:, None] * v * v))

    def tool_displacement(self, t: float) -> np.ndarray:
        """Prescribed displacements (P, 3) m of the tool vertices at time t (s)."""
        out = np.zeros((len(self.loading.tool_vertex), 3))
        _tool_displacements(self.points, self.loading.tools_tuple(), t, out)
        return out

    def tool_reactions(self, u: np.ndarray) -> np.ndarray:
        """Force (L, 3) N each tool exerts on the body at static equilibrium at displacement u (N, 3) m.

        On a prescribed component the body's equation reads 0 = f_int + f_ext + R, so a tool's force is
        R = -(f_int + f_ext) summed over its components. In a dynamic run this is the quasi-static part;
        the force with inertia and damping is what the integrators' ``step`` returns.
        """
        lo = self.loading
        u = self.nodal("tool_reactions: u", u)
        out = np.zeros((len(lo.tool_kind), 3))
        if len(lo.tool_vertex) == 0:
            return out
        own = self.extra.get("quasistatic")
        if own is not None and hasattr(own, "tool_reactions"):  # condensed: the state holds the surface only
            return own.tool_reactions(self, u)
        f = self.internal_force(u) + lo.external_force
        np.add.at(out, lo.tool_id, -f[lo.tool_vertex] * lo.tool_mask)
        return out

    def rigid_reactions(self, u: np.ndarray, t: float = np.inf) -> np.ndarray:
        """Force (K, 3) N each rigid tool (Loading.contacts) exerts on the body at displacement u (N, 3) m
        with the tools where they are at time t (s; default: at the end of their travel): the penalty
        forces on the vertices inside it, summed (``realtime.contact``); (0, 3) without rigid tools."""
        c = self.loading.contacts
        if c is None:
            return np.zeros((0, 3))
        return contact_forces(c, self.points, self.nodal("rigid_reactions: u", u), t)[1]

    def rigid_areas(self, u: np.ndarray, t: float = np.inf) -> np.ndarray:
        """Each rigid tool's contact area (K,) m^2 at displacement u (N, 3) m with the tools where they are
        at time t (s; default: the end of their travel): the lumped boundary areas of the vertices inside
        it (``realtime.contact.areas``); (0,) without rigid tools."""
        c = self.loading.contacts
        if c is None:
            return np.zeros(0)
        return contact_areas(c, self.points, self.nodal("rigid_areas: u", u), t)

    def contact_force(self, u: np.ndarray, t: float = np.inf) -> np.ndarray:
        """The rigid tools' force (N, 3) N on each vertex at displacement u (N, 3) m with the tools where
        they are at time t (s; default: at the end of their travel); zero without rigid tools."""
        c = self.loading.contacts
        if c is None:
            return np.zeros((self.n_vertices, 3))
        return contact_forces(c, self.points, self.nodal("contact_force: u", u), t)[0]

    def reaction(self, u: np.ndarray) -> np.ndarray:
        """Total force (3,) N the tools exert on the body at static equilibrium: tool_reactions summed, and
        the rigid tools' at the end of their travel (rigid_reactions)."""
        return self.tool_reactions(u).sum(axis=0) + self.rigid_reactions(u).sum(axis=0)


def check_float64(model: Model, what: str) -> None:
    """InputError unless ``model`` is float64: a float32 model's kernel reads rounded copies of the
    tensors, which changing the mesh in place would not reach."""
    if model.precision != "float64":
        raise InputError(
            f"{what}: {model.name} was built with precision = {model.precision!r}; only a float64 model can change its mesh"
        )


def lumped_masses(points: np.ndarray, tets: np.ndarray, density) -> np.ndarray:
    """rho V / 4 of each tetrahedron given to each of its vertices, (N,) float64, kg. density: kg/m^3,
    one number or (M,) float64, each tetrahedron's."""
    if np.ndim(density) == 0:
        return density * lumped_volumes(points, tets)
    vol = np.abs(signed_volumes(points, tets)) * np.asarray(density, dtype=float)
    return np.bincount(np.asarray(tets).ravel(), weights=np.repeat(vol / 4.0, 4), minlength=len(points))


def prepare_mesh(points, tets) -> tuple[np.ndarray, np.ndarray]:
    """Contiguous float64 points and int64 tets, validated (raises InvalidMeshError)."""
    points = float_array("mesh: points", points, np.float64, "an (N, 3) array", InvalidMeshError)
    tets = np.ascontiguousarray(whole_numbers("mesh: tets", tets, InvalidMeshError))
    check_tets(points, tets)
    return points, tets


@nb.njit(**_JIT)
def _tool_value(X, kind, vector, axis, center, angle, ramp, shape, t, out):
    """Displacement (3,) of rest point X (3,) under one tool at time t; written to out (3,)."""
    s = ramp_fraction(t, ramp, shape)
    if kind == 0:
        for c in range(3):
            out[c] = s * vector[c]
        return
    th = s * angle
    ct, st = np.cos(th), np.sin(th)
    r0, r1, r2 = X[0] - center[0], X[1] - center[1], X[2] - center[2]
    k0, k1, k2 = axis[0], axis[1], axis[2]
    kd = k0 * r0 + k1 * r1 + k2 * r2
    # Rodrigues: R r = r cos + (k x r) sin + k (k . r)(1 - cos)
    x0 = r0 * ct + (k1 * r2 - k2 * r1) * st + k0 * kd * (1.0 - ct)
    x1 = r1 * ct + (k2 * r0 - k0 * r2) * st + k1 * kd * (1.0 - ct)
    x2 = r2 * ct + (k0 * r1 - k1 * r0) * st + k2 * kd * (1.0 - ct)
    out[0] = x0 - r0
    out[1] = x1 - r1
    out[2] = x2 - r2


@nb.njit(**_JIT)
def _tool_displacements(points, tools, t, out):
    for p in range(tools.vertex.shape[0]):
        k = tools.tool[p]
        _tool_value(
            points[tools.vertex[p]], tools.kind[k], tools.vector[k], tools.axis[k], tools.center[k],
            tools.angle[k], tools.ramp[k], tools.shape[k], t, out[p],
        )  # fmt: skip
