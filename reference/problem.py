"""The boundary-value problem both solvers solve: constraints and loads on a mesh (no dolfinx here).

These are the objects a scene file becomes (``verification.scene`` parses TOML into them); the
reference turns them into forms, and the harness turns them into the real-time engine's ``Loading``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from meshes.regions import Region

COMPONENTS = ("x", "y", "z")

#: How a tool travels from 0 at t = 0 to its full value at t = ramp (part of the problem statement):
#: "linear", at constant speed; "smooth", the quintic s^3 (10 - 15 s + 6 s^2) of s = t / ramp, whose
#: velocity and acceleration vanish at both ends.
RAMP_SHAPES = ("linear", "smooth")


def ramp(t: float, duration: float, shape: str) -> tuple[float, float, float]:
    """The fraction of its travel a tool has made at time t (s), and its first and second time
    derivatives (1/s, 1/s^2; from the right at both ends: the motion starts at t = 0, and from
    t = duration on the travel holds), for a ramp of ``duration`` s (0: at once) of the given shape.

    The reference defines this itself: it is part of the problem both solvers solve, and the ground
    truth borrows nothing from the engine it judges (a test compares the engine's numba copy).
    """
    if duration <= 0.0 or t >= duration:
        return 1.0, 0.0, 0.0
    if t < 0.0:
        return 0.0, 0.0, 0.0
    s = t / duration
    if shape == "linear":
        return s, 1.0 / duration, 0.0
    if shape == "smooth":
        value = s**3 * (10.0 - 15.0 * s + 6.0 * s * s)
        rate = 30.0 * s * s * (1.0 - s) ** 2 / duration
        accel = 60.0 * s * (1.0 - s) * (1.0 - 2.0 * s) / duration**2
        return value, rate, accel
    raise ValueError(f"ramp shape {shape!r} is not one of {', '.join(RAMP_SHAPES)}")


def component_mask(components: tuple[str, ...]) -> np.ndarray:
    """(3,) float64: 1.0 for each named component."""
    return np.array([1.0 if c in components else 0.0 for c in COMPONENTS])


@dataclass(frozen=True)
class Fixed:
    """Vertices held at rest on the given components."""

    region: Region
    components: tuple[str, ...] = COMPONENTS


@dataclass(frozen=True)
class Gravity:
    """Acceleration (3,) m/s^2 of every point: body force rho g."""

    value: tuple[float, float, float]


@dataclass(frozen=True)
class Force:
    """Total force (3,) N spread as a uniform traction over the boundary faces in the region."""

    region: Region
    value: tuple[float, float, float]


@dataclass(frozen=True)
class Traction:
    """Traction (3,) Pa on the boundary faces in the region (all three vertices inside)."""

    region: Region
    value: tuple[float, float, float]


@dataclass(frozen=True)
class Displacement:
    """A tool: the region follows a prescribed translation or rigid rotation, ramped in time.

    translation (3,) m, or rotation: axis (3,) unit, center (3,) m, angle in degrees. The
    displacement (the angle, for a rotation) grows from 0 at t = 0 to its value at t = ramp and then
    holds; ramp_shape "linear" (constant speed) or "smooth" (velocity and acceleration zero at both
    ends), see ``ramp``.
    """

    region: Region
    components: tuple[str, ...] = COMPONENTS
    translation: tuple[float, float, float] | None = None
    axis: tuple[float, float, float] | None = None
    center: tuple[float, float, float] | None = None
    angle: float = 0.0
    ramp: float = 0.0
    ramp_shape: str = "linear"

    @property
    def is_rotation(self) -> bool:
        return self.translation is None

    def fraction(self, t: float) -> float:
        """Ramp factor s(t) in [0, 1]."""
        return ramp(t, self.ramp, self.ramp_shape)[0]

    def value(self, x: np.ndarray, t: float = math.inf) -> np.ndarray:
        """Prescribed displacement (K, 3) m at rest points x (K, 3) m and time t (s)."""
        return self.at_fraction(x, self.fraction(t))

    def kinematics(self, x: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Exact displacement (K, 3) m, velocity (K, 3) m/s and acceleration (K, 3) m/s^2 at time t of
        rest points x (K, 3) m of the tool's region.

        A translation moves as s(t) value; a rotation by theta(t) = s(t) angle about axis k turns
        r = x - center into R r, so its velocity is theta' k x (R r) and its acceleration
        theta'' k x (R r) + theta'^2 k x (k x (R r)).
        """
        s, ds, dds = ramp(t, self.ramp, self.ramp_shape)
        x = np.asarray(x, dtype=float)
        u = self.at_fraction(x, s)
        if not self.is_rotation:
            vec = np.asarray(self.translation, dtype=float)
            return u, np.broadcast_to(ds * vec, x.shape).copy(), np.broadcast_to(dds * vec, x.shape).copy()
        k = np.asarray(self.axis, dtype=float)
        k = k / np.linalg.norm(k)
        rr = u + (x - np.asarray(self.center, dtype=float))  # R r
        w, dw = math.radians(self.angle) * ds, math.radians(self.angle) * dds
        kxr = np.cross(k, rr)
        return u, w * kxr, dw * kxr + w * w * np.cross(k, kxr)

    def at_fraction(self, x: np.ndarray, s: float) -> np.ndarray:
        """Displacement (K, 3) m at rest points x (K, 3) m with the tool at fraction s of its travel."""
        x = np.asarray(x, dtype=float)
        if not self.is_rotation:
            return np.broadcast_to(s * np.asarray(self.translation), x.shape).copy()
        k = np.asarray(self.axis, dtype=float)
        k = k / np.linalg.norm(k)
        th = math.radians(s * self.angle)
        r = x - np.asarray(self.center, dtype=float)
        rot = r * math.cos(th) + np.cross(k, r) * math.sin(th) + np.outer(r @ k, k) * (1.0 - math.cos(th))
        return rot - r


Load = Gravity | Force | Traction | Displacement

#: The shapes of a rigid tool (``RigidTool``).
TOOL_SHAPES = ("sphere", "capsule", "plane")


@dataclass(frozen=True)
class RigidTool:
    """A rigid instrument pressed on the body without friction, moving by a prescribed translation.

    shape "sphere": ``center`` (3,) m and ``radius`` m; "capsule": the segment from ``center`` to ``end``
    (3,) m swept by a ball of ``radius`` m; "plane": the half-space behind the plane through ``center``
    whose unit ``normal`` (3,) points out of the tool, toward the body. ``travel`` (3,) m is the
    translation reached at ``ramp`` s along ``ramp_shape`` (``ramp``), then held. The geometry is given
    at t = 0, where the tool must not yet be inside the body. ``stations`` (a static scene): the truth
    reads the force and contact area at that many evenly spaced fractions of the travel.
    """

    shape: str
    center: tuple[float, float, float]
    radius: float = 0.0
    end: tuple[float, float, float] | None = None
    normal: tuple[float, float, float] | None = None
    travel: tuple[float, float, float] = (0.0, 0.0, 0.0)
    ramp: float = 0.0
    ramp_shape: str = "linear"
    stations: int = 0  # a static scene's force-indentation curve: read at k / stations of the travel

    def offset(self, s: float) -> np.ndarray:
        """(3,) m: where the tool has moved at fraction s of its travel."""
        return s * np.asarray(self.travel, dtype=float)

    def gap(self, y: np.ndarray, s: float) -> np.ndarray:
        """(K,) m: the signed distance of points y (K, 3) m from the tool's surface at fraction s of its
        travel, negative inside the tool (the reference's UFL ``reference.contact.gap`` is this formula)."""
        y = np.asarray(y, dtype=float) - self.offset(s) - np.asarray(self.center, dtype=float)
        if self.shape == "plane":
            return y @ np.asarray(self.normal, dtype=float)
        if self.shape == "capsule":
            axis = np.asarray(self.end, dtype=float) - np.asarray(self.center, dtype=float)
            t = np.clip(y @ axis / (axis @ axis), 0.0, 1.0)
            y = y - t[:, None] * axis
        return np.linalg.norm(y, axis=1) - self.radius


@dataclass(frozen=True)
class Problem:
    """Constraints, loads and rigid tools: tuples of the dataclasses above."""

    fixed: tuple[Fixed, ...]
    loads: tuple[Load, ...]
    contacts: tuple[RigidTool, ...] = ()  # rigid tools touching the body (reference.contact)

    def __repr__(self) -> str:
        """The dataclass's repr, without ``contacts`` when there are none: a scene's hash is drawn from it,
        and a scene without rigid tools keeps the hash (and the gates' baselines) it had before they were."""
        tools = f", contacts={self.contacts!r}" if self.contacts else ""
        return f"Problem(fixed={self.fixed!r}, loads={self.loads!r}{tools})"

    @property
    def tools(self) -> tuple[Displacement, ...]:
        return tuple(ld for ld in self.loads if isinstance(ld, Displacement))

    @property
    def held_by_tools(self) -> bool:
        """Whether a tool, prescribed (a displacement load) or rigid (a contact), exerts a force on the
        body: the force a haptic device renders, which ``reaction`` sums."""
        return bool(self.tools or self.contacts)

    def gravity(self) -> np.ndarray:
        """Sum of the gravity loads (3,) m/s^2."""
        g = np.zeros(3)
        for ld in self.loads:
            if isinstance(ld, Gravity):
                g += np.asarray(ld.value)
        return g
