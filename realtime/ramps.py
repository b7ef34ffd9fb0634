"""How a tool travels along its path: the ramp shapes (shared by the prescribed tools of ``realtime.model``
and the rigid tools of ``realtime.contact``)."""

from __future__ import annotations

import numba as nb

#: How a tool travels from 0 at t = 0 to its full value at t = ramp: "linear" (a constant speed, with
#: jumps in velocity at both ends) or "smooth" (the quintic 10 s^3 - 15 s^4 + 6 s^5 of s = t / ramp,
#: whose velocity and acceleration vanish at both ends). Index = the code in Loading.tool_ramp_shape.
RAMP_SHAPES = ("linear", "smooth")


@nb.njit(nogil=True, cache=True)
def ramp_fraction(t: float, ramp: float, shape: int) -> float:
    """Fraction in [0, 1] of its travel a tool has made at time t (s), for a ramp of ``ramp`` s (0:
    at once) and the shape RAMP_SHAPES[shape]."""
    s = 1.0 if ramp <= 0.0 else min(max(t / ramp, 0.0), 1.0)
    if shape == 1:
        return s * s * s * (10.0 + s * (6.0 * s - 15.0))
    return s
