"""The boundary-value problem both solvers solve: constraints and loads on a mesh (no dolfinx here).

These are the objects a scene file becomes (``verification.scene`` parses TOML into them); the
reference turns them into forms, and the harness turns them into the real-time engine's ``Loading``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from meshes.regions import Region
from realtime.model import RAMP_SHAPES, ramp_fraction

COMPONENTS = ("x", "y", "z")


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
    holds; ramp_shape "linear" (constant speed) or "smooth" (realtime.model.ramp_fraction: velocity
    and acceleration zero at both ends).
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
        return float(ramp_fraction(t, self.ramp, RAMP_SHAPES.index(self.ramp_shape)))

    def value(self, x: np.ndarray, t: float = math.inf) -> np.ndarray:
        """Prescribed displacement (K, 3) m at rest points x (K, 3) m and time t (s)."""
        return self.at_fraction(x, self.fraction(t))

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


@dataclass(frozen=True)
class Problem:
    """Constraints and loads. ``fixed`` and ``loads`` are tuples of the dataclasses above."""

    fixed: tuple[Fixed, ...]
    loads: tuple[Load, ...]

    @property
    def tools(self) -> tuple[Displacement, ...]:
        return tuple(ld for ld in self.loads if isinstance(ld, Displacement))

    def gravity(self) -> np.ndarray:
        """Sum of the gravity loads (3,) m/s^2."""
        g = np.zeros(3)
        for ld in self.loads:
            if isinstance(ld, Gravity):
                g += np.asarray(ld.value)
        return g
