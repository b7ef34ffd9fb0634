"""Frictionless contact of the body with rigid tools, as a haptic loop can afford it: a penalty on the
surface vertices near each tool, against the tool's exact shape.

A tool is a sphere, a capsule (a segment swept by a ball) or a plane (``Rigid``), moved by a prescribed
translation along a ramp. Where a vertex's current position y = X + u lies inside a tool, at signed
distance g(y) < 0 from its surface, the vertex stores the energy k/2 g^2 and the tool pushes it out with
the force f = -k g grad g (grad g = n, the unit normal out of the tool). The stiffness of vertex i is

    k_i = gamma E A_i / h_i,

with A_i its lumped boundary area (a third of each boundary triangle around it), h_i the area-weighted
mean of those triangles' longest edges and E the body's stiffest Young's modulus: the vertex-lumped form
of the reference's boundary penalty kappa = gamma E / h (``reference.contact``), so a penetration is the
contact pressure times h / (gamma E) on both sides. Laursen, Computational Contact and Impact Mechanics
(2002), ch. 5, for the penalty; Wriggers, Computational Contact Mechanics (2006), sec. 4.1, for the
node-to-analytical-surface form.

The kernels are called by every step loop (``realtime.steppers``) after the elastic force, over the
candidate vertices only: the surface vertices whose rest position comes within ``margin`` of the tool
anywhere along its travel (``contacts``). No tool, no candidate, no work.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numba as nb
import numpy as np

from .errors import LoadingError
from .geometry import boundary_faces
from .ramps import RAMP_SHAPES, ramp_fraction

_JIT = dict(nogil=True, cache=True)

#: The engine's penalty factor: k_i = gamma E A_i / h_i. A Hertzian contact resolved by cells of a fifth of
#: its radius then penetrates about 1 / (5 gamma) of the indentation. The explicit steps take the contact
#: implicitly (``contact_kick``), so gamma costs no time step; it costs conditioning in implicit Euler's CG.
GAMMA = 100.0

#: The shapes, by their code in Contacts.shape.
SHAPES = ("sphere", "capsule", "plane")


@dataclass(frozen=True)
class Rigid:
    """A rigid tool as the engine takes it (SI units): ``shape`` one of SHAPES; ``center`` (3,) m the
    sphere's centre, the capsule's first end or a point of the plane at t = 0; ``radius`` m (sphere,
    capsule); ``end`` (3,) m the capsule's second end; ``normal`` (3,) the plane's unit normal out of the
    tool, toward the body; ``travel`` (3,) m reached at ``ramp`` s along ``ramp_shape`` (RAMP_SHAPES), then
    held."""

    shape: str
    center: tuple
    radius: float = 0.0
    end: tuple | None = None
    normal: tuple | None = None
    travel: tuple = (0.0, 0.0, 0.0)
    ramp: float = 0.0
    ramp_shape: str = "linear"


class Contacts(NamedTuple):
    """The arrays the step loops take, K tools and S candidate vertices:

    shape (K,) int64 the index in SHAPES; center, end (K, 3) float64 m at t = 0 (end: the capsule's, else
    center); normal (K, 3) float64 (the plane's unit normal, else 0); radius (K,) float64 m; travel (K, 3)
    float64 m; ramp (K,) float64 s; ramp_shape (K,) int64 (RAMP_SHAPES); vertex (S,) int64 the candidate
    vertices; tool (S,) int64 the tool each faces; stiffness (S,) float64 N/m the k_i above; faces (F, 3)
    int64 the boundary triangles whose three vertices are one tool's candidates, as positions in vertex
    (what ``areas`` measures)."""

    shape: np.ndarray
    center: np.ndarray
    end: np.ndarray
    normal: np.ndarray
    radius: np.ndarray
    travel: np.ndarray
    ramp: np.ndarray
    ramp_shape: np.ndarray
    vertex: np.ndarray
    tool: np.ndarray
    stiffness: np.ndarray
    faces: np.ndarray

    @property
    def count(self) -> int:
        """K, the tools."""
        return len(self.shape)


def no_contacts() -> Contacts:
    """No tool: what a Loading without rigid tools steps with."""
    z3, z = np.zeros((0, 3)), np.zeros(0)
    zi = np.zeros(0, dtype=np.int64)
    return Contacts(zi, z3, z3, z3, z, z3, z, zi, zi, zi, z, np.zeros((0, 3), dtype=np.int64))


def _tool_arrays(tool: Rigid, i: int) -> tuple:
    """(shape code, center, end, normal, radius, travel, ramp, ramp shape code) of one checked tool."""
    what = f"contacts: tool {i}"
    if tool.shape not in SHAPES:
        raise LoadingError(f"{what}: shape = {tool.shape!r}: must be one of {', '.join(SHAPES)}")
    if tool.ramp_shape not in RAMP_SHAPES:
        raise LoadingError(f"{what}: ramp_shape = {tool.ramp_shape!r}: must be one of {', '.join(RAMP_SHAPES)}")
    center = np.asarray(tool.center, dtype=float).reshape(3)
    travel = np.asarray(tool.travel, dtype=float).reshape(3)
    end, normal = center.copy(), np.zeros(3)
    if tool.shape == "capsule":
        end = np.asarray(tool.end, dtype=float).reshape(3)
        if not np.linalg.norm(end - center) > 0.0:
            raise LoadingError(f"{what}: a capsule's end equals its center {tuple(center)}: it has no length")
    if tool.shape == "plane":
        normal = np.asarray(tool.normal, dtype=float).reshape(3)
        length = float(np.linalg.norm(normal))
        if not length > 0.0:
            raise LoadingError(f"{what}: normal = {tuple(normal)}: a plane needs a non-zero normal")
        normal = normal / length
    elif not (math.isfinite(tool.radius) and tool.radius > 0.0):
        raise LoadingError(f"{what}: radius = {tool.radius!r}: must be a number > 0 m")
    if not (math.isfinite(tool.ramp) and tool.ramp >= 0.0):
        raise LoadingError(f"{what}: ramp = {tool.ramp!r}: must be a number >= 0 s")
    for name, a in (("center", center), ("end", end), ("travel", travel)):
        if not np.all(np.isfinite(a)):
            raise LoadingError(f"{what}: {name} = {tuple(a)}: must be finite")
    code = SHAPES.index(tool.shape)
    return code, center, end, normal, float(tool.radius), travel, float(tool.ramp), RAMP_SHAPES.index(tool.ramp_shape)


def surface_stiffness(points: np.ndarray, tets: np.ndarray, young: float, gamma: float) -> tuple:
    """(vertices (B,) int64, k (B,) float64 N/m) of the boundary vertices: k_i = gamma E A_i / h_i (the
    module's docstring), from points (N, 3) float64 m, tets (M, 4) int64 and E = ``young`` Pa."""
    faces = boundary_faces(tets)
    x = points[faces]
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    longest = np.max(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2), axis=1)
    n = len(points)
    lumped = np.bincount(faces.ravel(), weights=np.repeat(area / 3.0, 3), minlength=n)
    weighted = np.bincount(faces.ravel(), weights=np.repeat(area * longest, 3), minlength=n)
    total = np.bincount(faces.ravel(), weights=np.repeat(area, 3), minlength=n)
    vertices = np.flatnonzero(total > 0.0)
    h = weighted[vertices] / total[vertices]
    return vertices.astype(np.int64), gamma * young * lumped[vertices] / h


#: Positions along a tool's travel at which ``contacts`` measures the rest gap of the surface vertices.
PATH_SAMPLES = 65


def contacts(points: np.ndarray, tets: np.ndarray, tools, young: float, gamma: float = GAMMA, margin=None) -> Contacts:
    """The Contacts of ``tools`` (a sequence of Rigid) on a mesh: points (N, 3) float64 m, tets (M, 4)
    int64, the body's stiffest Young's modulus ``young`` Pa and the penalty factor ``gamma``. A tool's
    candidates are the boundary vertices whose rest position lies within ``margin`` m of its surface at
    one of PATH_SAMPLES positions along its travel (default: the travel's length plus twice the longest
    boundary edge, as far as a vertex can come toward the tool while the tool pushes the body)."""
    tools = list(tools)
    if not tools:
        return no_contacts()
    if not (math.isfinite(young) and young > 0.0 and math.isfinite(gamma) and gamma > 0.0):
        raise LoadingError(f"contacts: young = {young!r} Pa, gamma = {gamma!r}: both must be numbers > 0")
    arrays = [_tool_arrays(tool, i) for i, tool in enumerate(tools)]
    shape, center, end, normal, radius, travel, ramp, ramp_shape = (np.array(a) for a in zip(*arrays, strict=True))
    vertices, k = surface_stiffness(points, tets, young, gamma)
    faces = boundary_faces(tets)
    edge = float(np.max(np.linalg.norm(points[faces] - points[np.roll(faces, 1, axis=1)], axis=2)))
    vertex, owner, stiffness, patches = [], [], [], []
    position = np.full(len(points), -1, dtype=np.int64)
    taken = 0
    y = points[vertices]
    for i in range(len(tools)):
        reach = float(np.linalg.norm(travel[i])) + 2.0 * edge if margin is None else float(margin)
        near = np.zeros(len(vertices), dtype=bool)
        for s in np.linspace(0.0, 1.0, PATH_SAMPLES):
            g = rest_gap(shape[i], center[i] + s * travel[i], end[i] + s * travel[i], normal[i], radius[i], y)
            near |= g < reach
        vertex.append(vertices[near])
        owner.append(np.full(int(near.sum()), i, dtype=np.int64))
        stiffness.append(k[near])
        position[:] = -1
        position[vertices[near]] = taken + np.arange(int(near.sum()))
        mine = position[faces]
        patches.append(mine[np.all(mine >= 0, axis=1)])
        taken += int(near.sum())
    return Contacts(
        shape.astype(np.int64),
        center.astype(float),
        end.astype(float),
        normal.astype(float),
        radius.astype(float),
        travel.astype(float),
        ramp.astype(float),
        ramp_shape.astype(np.int64),
        np.concatenate(vertex).astype(np.int64),
        np.concatenate(owner),
        np.concatenate(stiffness).astype(float),
        np.concatenate(patches).astype(np.int64).reshape(-1, 3),
    )


def rest_gap(shape: int, center, end, normal, radius: float, y: np.ndarray) -> np.ndarray:
    """(B,) m: the signed distance of points y (B, 3) m from one tool's surface (numpy; ``_gap`` is the
    kernel's form of the same formula): a sphere |y - c| - r, a capsule the distance to its segment minus
    r, a plane (y - c) . n."""
    r = y - center
    if shape == 2:
        return r @ normal
    if shape == 1:
        axis = end - center
        t = np.clip(r @ axis / (axis @ axis), 0.0, 1.0)
        r = r - t[:, None] * axis
    return np.linalg.norm(r, axis=1) - radius


def check(c: Contacts, n_vertices: int) -> None:
    """LoadingError unless the candidate arrays index a mesh of ``n_vertices`` and the tools' arrays agree
    in length (the kernels do no bounds checks)."""
    k, s = len(c.shape), len(c.vertex)
    for name, a, length in (("vertex", c.vertex, s), ("tool", c.tool, s), ("stiffness", c.stiffness, s)):
        if a.shape != (length,):
            raise LoadingError(f"Loading.contacts.{name}: must be a ({length},) array, got {a.shape}")
    for name in ("center", "end", "normal", "travel"):
        if getattr(c, name).shape != (k, 3):
            raise LoadingError(f"Loading.contacts.{name}: must be a ({k}, 3) array, got {getattr(c, name).shape}")
    if c.faces.ndim != 2 or c.faces.shape[1] != 3:
        raise LoadingError(f"Loading.contacts.faces: must be an (F, 3) array, got {c.faces.shape}")
    for name, upper in (("vertex", n_vertices), ("tool", k), ("shape", len(SHAPES)), ("faces", s)):
        a = getattr(c, name)
        if len(a) and (a.min() < 0 or a.max() >= upper):
            bad = int(np.argmax((a < 0) | (a >= upper)))
            raise LoadingError(f"Loading.contacts.{name}[{bad}] = {a[bad]}: must lie in 0..{upper - 1}")
    if len(c.stiffness) and not np.all(np.isfinite(c.stiffness) & (c.stiffness >= 0.0)):
        bad = int(np.argmax(~(np.isfinite(c.stiffness) & (c.stiffness >= 0.0))))
        raise LoadingError(f"Loading.contacts.stiffness[{bad}] = {c.stiffness[bad]}: must be a number >= 0 N/m")


@nb.njit(inline="always", **_JIT)
def _gap(c, k, t, y, n):
    """The signed distance (m) of y (3,) m from tool k's surface at time t (s), negative inside; writes
    the unit normal n (3,) out of the tool at y (the gradient of the distance)."""
    s = ramp_fraction(t, c.ramp[k], c.ramp_shape[k])
    r0 = y[0] - c.center[k, 0] - s * c.travel[k, 0]
    r1 = y[1] - c.center[k, 1] - s * c.travel[k, 1]
    r2 = y[2] - c.center[k, 2] - s * c.travel[k, 2]
    if c.shape[k] == 2:
        for i in range(3):
            n[i] = c.normal[k, i]
        return r0 * n[0] + r1 * n[1] + r2 * n[2]
    if c.shape[k] == 1:
        e0, e1, e2 = c.end[k, 0] - c.center[k, 0], c.end[k, 1] - c.center[k, 1], c.end[k, 2] - c.center[k, 2]
        p = min(max((r0 * e0 + r1 * e1 + r2 * e2) / (e0 * e0 + e1 * e1 + e2 * e2), 0.0), 1.0)
        r0, r1, r2 = r0 - p * e0, r1 - p * e1, r2 - p * e2
    rho = math.sqrt(r0 * r0 + r1 * r1 + r2 * r2)
    if rho == 0.0:  # on the core itself: any direction is out; the force then has a fixed one
        n[0], n[1], n[2] = 0.0, 0.0, 1.0
        return -c.radius[k]
    n[0], n[1], n[2] = r0 / rho, r1 / rho, r2 / rho
    return rho - c.radius[k]


@nb.njit(inline="always", **_JIT)
def _candidate_gap(c, j, points, u, t, y, n):
    """(vertex, tool, gap m) of candidate j at u (N, 3) m and time t (s); writes its position y (3,) m and
    the tool's unit normal n (3,) there (``_gap``)."""
    i, k = c.vertex[j], c.tool[j]
    for d in range(3):
        y[d] = points[i, d] + u[i, d]
    return i, k, _gap(c, k, t, y, n)


@nb.njit(**_JIT)
def contact_force(c, points, u, t, f, reaction):
    """Add each candidate vertex's contact force at time t (s) to f (N, 3) N, from u (N, 3) m and the rest
    points (N, 3) float64 m; reaction (K, 3) N receives each tool's force on the body (their sum)."""
    reaction[:] = 0.0
    if c.vertex.shape[0] == 0:  # no rigid tool: no allocation in a step loop's every step
        return
    y, n = np.empty(3), np.empty(3)
    for j in range(c.vertex.shape[0]):
        i, k, g = _candidate_gap(c, j, points, u, t, y, n)
        if g < 0.0:
            push = -c.stiffness[j] * g
            for d in range(3):
                f[i, d] += push * n[d]
                reaction[k, d] += push * n[d]


@nb.njit(**_JIT)
def contact_kick(c, points, u, t, v, f, fext, free, mass, dt, damp, reaction):
    """An explicit step's contact force, with each penetrated vertex's contact taken implicitly: add to f
    (N, 3) N, for each candidate vertex inside its tool at u (N, 3) m and time t (s), the force
    f_c - dt k n (n . v'), k n n^T the contact's normal stiffness at u (``contact_tangent``) and v' the
    vertex's velocity after the kick, v' = damp (v + dt (f + f_c + f_ext) / m) - damp dt^2 k / m n (n . v')
    on its free components (free (N, 3), 0 or 1): solved in closed form (Sherman-Morrison). A kick that
    reads f then gives each such vertex exactly v' (symplectic Euler's update; central difference's two
    half kicks around it, with damp = 1). reaction (K, 3) N receives each tool's part, the force on the
    body. v (N, 3) m/s, fext (N, 3) N, mass (N,) kg.

    Taken explicitly, a penalty stiffer than the elements made symplectic Euler and central difference
    grow without bound at 0.9 of the critical step of M^-1 (K + K_c) (a sphere pressing a block:
    velocities of 3e3 m/s in 30 000 steps), though each of the two linear systems, in and out of contact,
    is stable there: switching between them pumps energy in. Taken implicitly, the contact is stable at
    any step (its own amplification has determinant 1 / (1 + dt^2 k / m)), and the step is the elements'
    alone."""
    reaction[:] = 0.0
    if c.vertex.shape[0] == 0:  # no rigid tool: no allocation in a step loop's every step
        return
    y, n, p, w = np.empty(3), np.empty(3), np.empty(3), np.empty(3)
    for j in range(c.vertex.shape[0]):
        i, k, g = _candidate_gap(c, j, points, u, t, y, n)
        if g >= 0.0:
            continue
        kj = c.stiffness[j]
        ck = damp * dt * dt * kj / mass[i]
        pw, pp = 0.0, 0.0
        for d in range(3):
            p[d] = n[d] * free[i, d]
            w[d] = damp * (v[i, d] + dt * (f[i, d] - kj * g * n[d] + fext[i, d]) / mass[i]) * free[i, d]
            pw += p[d] * w[d]
            pp += p[d] * p[d]
        nv = pw / (1.0 + ck * pp)  # n . v' = p . v' (v' is 0 on held components)
        for d in range(3):
            fd = -kj * g * n[d] - dt * kj * nv * n[d]
            f[i, d] += fd
            reaction[k, d] += fd


@nb.njit(**_JIT)
def contact_tangent(c, points, u, t, x, out):
    """Add K_c x to out (N, 3), x (N, 3), K_c = k n n^T per penetrated vertex at u (N, 3) m and time t
    (s): the normal part of the contact's tangent -d f_contact / d u. The whole tangent adds
    k (g / rho)(I - n n^T - a a^T), rho the distance to the tool's centre or axis and a the capsule's axis
    where the closest point lies inside its segment (else 0), which is negative inside a curved tool: at a deep
    penetration (a tool placed 1 mm into a coarse block at once, g / rho = -0.25) it made the kick's
    3 x 3 systems and implicit Euler's CG indefinite, and a run diverged at 0.9 of its step. Left out,
    both stay positive definite; a plane's tangent is exactly this."""
    if c.vertex.shape[0] == 0:  # no rigid tool: nothing to add in every CG iteration
        return
    y, n = np.empty(3), np.empty(3)
    for j in range(c.vertex.shape[0]):
        i, k, g = _candidate_gap(c, j, points, u, t, y, n)
        if g < 0.0:
            nx = n[0] * x[i, 0] + n[1] * x[i, 1] + n[2] * x[i, 2]
            for d in range(3):
                out[i, d] += c.stiffness[j] * nx * n[d]


def _tool_gaps(c: Contacts, points: np.ndarray, u: np.ndarray, t: float, k: int) -> tuple[np.ndarray, np.ndarray]:
    """(the candidates facing tool k (S,) bool, their gaps m) at u (N, 3) m and time t (s; np.inf: the end
    of the travel)."""
    mine = c.tool == k
    s = ramp_fraction(float(min(t, 1e300)), c.ramp[k], c.ramp_shape[k])
    y = points[c.vertex[mine]] + u[c.vertex[mine]]
    shift = s * c.travel[k]
    return mine, rest_gap(c.shape[k], c.center[k] + shift, c.end[k] + shift, c.normal[k], c.radius[k], y)


def contact_energy(c: Contacts, points: np.ndarray, u: np.ndarray, t: float) -> float:
    """sum k_i / 2 min(g_i, 0)^2, J, at u (N, 3) m and time t (s): the energy whose negative gradient
    ``contact_force`` is (the tests check the one against differences of the other)."""
    total = 0.0
    for k in range(c.count):
        mine, g = _tool_gaps(c, points, u, t, k)
        total += 0.5 * float(np.sum(c.stiffness[mine] * np.minimum(g, 0.0) ** 2))
    return total


def forces(c: Contacts, points: np.ndarray, u: np.ndarray, t: float) -> tuple[np.ndarray, np.ndarray]:
    """(the contact force (N, 3) N on every vertex, each tool's force on the body (K, 3) N) at u (N, 3) m
    and time t (s; np.inf: the tools at the end of their travel)."""
    f = np.zeros((len(points), 3))
    reaction = np.zeros((c.count, 3))
    contact_force(c, points, np.ascontiguousarray(u, dtype=np.float64), float(min(t, 1e300)), f, reaction)
    return f, reaction


def areas(c: Contacts, points: np.ndarray, u: np.ndarray, t: float) -> np.ndarray:
    """Each tool's contact area (K,) m^2 at u (N, 3) m and time t (s; np.inf: at the end of the travel):
    over the candidate boundary triangles (``Contacts.faces``) in the rest shape, the part where the linear
    interpolant of the vertices' gaps is negative (a triangle with one vertex inside holds the fraction
    g_a^2 / ((g_a - g_b)(g_a - g_c)) of its area; with two, one minus the outside vertex's fraction). A
    plane pressing a whole face gives that face's area, where the vertices' lumped areas added a third of
    every side triangle at its rim (24 % more on a coarse block)."""
    out = np.zeros(c.count)
    if c.count == 0 or not len(c.faces):
        return out
    g = np.empty(len(c.vertex))
    for k in range(c.count):
        mine, gaps = _tool_gaps(c, points, u, t, k)
        g[mine] = gaps
    x = points[c.vertex][c.faces]  # the rest shape's area, as the truth's (an integral over the reference boundary)
    area = 0.5 * np.linalg.norm(np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]), axis=1)
    out += np.bincount(c.tool[c.faces[:, 0]], weights=area * _inside_fraction(g[c.faces]), minlength=c.count)
    return out


def _inside_fraction(g: np.ndarray) -> np.ndarray:
    """(F,) the fraction of each triangle where the linear interpolant of its vertex values g (F, 3) is
    negative."""
    inside = g < 0.0
    count = inside.sum(axis=1)
    out = (count == 3).astype(float)
    for lone, flip in ((1, False), (2, True)):  # the vertex on its own side: inside (one) or outside (two)
        rows = np.flatnonzero(count == lone)
        if not len(rows):
            continue
        gr = g[rows]
        a = np.argmax(~inside[rows] if flip else inside[rows], axis=1)
        ga = gr[np.arange(len(rows)), a]
        gb, gc = gr[np.arange(len(rows)), (a + 1) % 3], gr[np.arange(len(rows)), (a + 2) % 3]
        part = ga * ga / ((ga - gb) * (ga - gc))
        out[rows] = 1.0 - part if flip else part
    return out


def travel_end(c: Contacts) -> float:
    """The time (s) when every tool has arrived (0 without tools)."""
    return float(c.ramp.max()) if c.count else 0.0


def below(c: Contacts | None, n: int) -> Contacts | None:
    """``c`` with only the candidates among the first ``n`` vertices (a model that keeps fewer vertices
    than the mesh its loading was made on: adaptive-tm's hanging midpoints follow their edges' ends), and
    only the triangles of those."""
    if c is None:
        return None
    keep = c.vertex < n
    renumber = np.cumsum(keep) - 1
    faces = c.faces[np.all(keep[c.faces], axis=1)]
    return c._replace(vertex=c.vertex[keep], tool=c.tool[keep], stiffness=c.stiffness[keep], faces=renumber[faces])
