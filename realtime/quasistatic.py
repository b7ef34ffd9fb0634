"""Quasi-static linear models: precomputed elementary responses (Cotin 1999) and condensation
(Bro-Nielsen 1996). Both answer "where is everything at equilibrium with the tools here?" in one
update, with no time stepping; their ``step`` is that update at the state's time.

Notation: K the P1 linear stiffness (3N x 3N), c the constrained dofs (fixed and tool components),
f the free dofs, u0 = K_ff^-1 f_ext the response to the constant loads.

Precomputed (Cotin, Delingette & Ayache 1999): for every free dof s of a surface vertex the
elementary response T[:, s] = K_ff^-1 e_s (all free dofs, to a unit force at s) is computed once. A
tool imposing displacements d on a set D of surface dofs needs forces F_D with T_DD F_D = d - u0_D;
then u = u0 + T[:, D] F_D, and F_D is the force the tool applies, the haptic feedback. This equals
the static solution with D added to the Dirichlet set (the Schur complement identity), to round-off.

Condensed (Bro-Nielsen 1996): keep the retained vertices r (surface and constrained), eliminate the
interior i: K* = K_rr - K_ri K_ii^-1 K_ir, f* = f_r - K_ri K_ii^-1 f_i. Solving K* on the free retained
dofs gives exactly the full static solution at the surface vertices; the interior is recovered on
demand by u_i = K_ii^-1 (f_i - K_ir u_r), outside the timed update. As in Bro-Nielsen's "fast
finite elements", the condensed system is solved once at build time for the loads and for unit
displacements of the tool dofs, so that an update is one (free retained x tool dofs) product.
"""

from __future__ import annotations

from functools import cached_property

import numba as nb
import numpy as np
import scipy.linalg as sla
import scipy.sparse as sp
import scipy.sparse.linalg as spla

from .errors import InputError, ModelRestriction
from .geometry import boundary_faces
from .model import Model, State

_JIT = dict(nogil=True, cache=True)
#: Elementary responses solved per block of right-hand sides while precomputing.
PRECOMPUTE_BLOCK = 512


def _surface_vertices(tets: np.ndarray) -> np.ndarray:
    return np.unique(boundary_faces(tets))


def _stiffness(model: Model) -> sp.csr_matrix:
    return model.extra["tensors"].matrix()


class _Targets:
    """The tools' prescribed dofs of a model, worked out once: ``dofs`` (D,) int64, sorted, and
    ``tools`` (D,) int64 the tool that prescribes each (the first, where two hold one dof)."""

    def __init__(self, model: Model):
        lo = model.loading
        self.mask = lo.tool_mask != 0.0
        dofs = (3 * lo.tool_vertex[:, None] + np.arange(3)[None, :])[self.mask]
        self.dofs, self.first = np.unique(dofs, return_index=True)
        self.tools = np.broadcast_to(lo.tool_id[:, None], self.mask.shape)[self.mask][self.first]

    def values(self, model: Model, t: float) -> np.ndarray:
        """The prescribed dofs' displacements (D,) m at time t."""
        return model.tool_displacement(t)[self.mask][self.first]


def _per_tool(model: Model, dofs: np.ndarray, tools: np.ndarray, forces: np.ndarray) -> np.ndarray:
    """The forces (D,) N on the prescribed dofs (D,) summed by tool (D,): (L, 3) N."""
    n_tools = len(model.loading.tool_kind)
    return np.bincount(3 * tools + dofs % 3, weights=forces, minlength=3 * n_tools).reshape(n_tools, 3)


class Precomputed:
    """Elementary responses of the free surface dofs of a linear model (Cotin et al. 1999).

    Attributes:
        free_dofs: (F,) int64 free dofs (not fixed by the scene's fixed regions).
        targets: the tools' prescribed dofs (_Targets).
        surface_dofs: (S,) int64 free dofs of surface vertices, the columns of T.
        T: (F, S) float64, m/N: responses of all free dofs to unit forces at the surface dofs.
        u0: (3N,) float64, m: response to the constant loads.
        column: (3N,) int64, column of T of each dof (-1 if none).
        row: (3N,) int64, row of T of each dof (-1 if not free).
    """

    def __init__(self, model: Model):
        lo = model.loading
        n = model.n_vertices
        fixed = np.zeros((n, 3), dtype=bool)
        fixed[:] = lo.free == 0.0
        tool = np.zeros((n, 3), dtype=bool)
        if len(lo.tool_vertex):
            tool[lo.tool_vertex] = lo.tool_mask != 0.0
        held = (fixed & ~tool).ravel()  # held by fixed regions; tool dofs stay free here
        self.targets = _Targets(model)
        self.free_dofs = np.flatnonzero(~held)
        surf = _surface_vertices(model.tets)
        sdofs = (3 * surf[:, None] + np.arange(3)).ravel()
        self.surface_dofs = sdofs[~held[sdofs]]
        tool_dofs = np.flatnonzero(tool.ravel())
        missing = np.setdiff1d(tool_dofs, self.surface_dofs)
        if len(missing):
            v = int(missing[0] // 3)
            raise ModelRestriction(
                f"precomputed: tool vertex {v} {model.points[v].tolist()} is not on the surface; "
                "elementary responses exist for surface vertices only"
            )
        K = _stiffness(model)[self.free_dofs][:, self.free_dofs].tocsc()
        lu = spla.splu(K)
        self.row = np.full(3 * n, -1, dtype=np.int64)
        self.row[self.free_dofs] = np.arange(len(self.free_dofs))
        self.column = np.full(3 * n, -1, dtype=np.int64)
        self.column[self.surface_dofs] = np.arange(len(self.surface_dofs))
        # T column by column block: the whole right-hand side, its solution and a C-ordered copy were
        # three (free x surface) arrays at once, 11 GB for a 12k-vertex beam; now T and one block
        self.T = np.empty((len(self.free_dofs), len(self.surface_dofs)))
        rows = self.row[self.surface_dofs]
        for start in range(0, len(self.surface_dofs), PRECOMPUTE_BLOCK):
            cols = np.arange(start, min(start + PRECOMPUTE_BLOCK, len(self.surface_dofs)))
            rhs = np.zeros((len(self.free_dofs), len(cols)), order="F")
            rhs[rows[cols], cols - start] = 1.0
            self.T[:, cols] = lu.solve(rhs)
        self.u0 = np.zeros(3 * n)
        self.u0[self.free_dofs] = lu.solve(lo.external_force.ravel()[self.free_dofs])
        self.n = n

    def solve(self, dofs: np.ndarray, values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (N, 3) m with ``dofs`` (D,) held at ``values`` (D,) m; and the tool forces (D,) N."""
        u = self.u0.copy()
        if len(dofs) == 0:
            return u.reshape(-1, 3), np.zeros(0)
        cols = self.column[dofs]
        TDD = self.T[self.row[dofs]][:, cols]
        F = np.linalg.solve(TDD, values - self.u0[dofs])
        u[self.free_dofs] += self.T[:, cols] @ F
        return u.reshape(-1, 3), F

    def advance(self, model: Model, t: float, u: np.ndarray) -> np.ndarray:
        """Write into u (N, 3) m the equilibrium with the tools where they are at time t (s); return the
        force (L, 3) N each tool exerts on the body there."""
        dofs, tools = self.targets.dofs, self.targets.tools
        u[:], forces = self.solve(dofs, self.targets.values(model, t))
        return _per_tool(model, dofs, tools, forces)

    def equilibrium(self, model: Model, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (N, 3) m at equilibrium at time t and the tools' total force (3,) N."""
        u, F = self.solve(self.targets.dofs, self.targets.values(model, t))
        R = np.zeros(3)
        np.add.at(R, self.targets.dofs % 3, F)
        return u, R

    def tool_force(self, vertex: int, displacement: np.ndarray) -> np.ndarray:
        """Force (3,) N needed to hold one surface vertex at ``displacement`` (3,) m: the haptic update."""
        dofs = 3 * vertex + np.arange(3)
        return _one_vertex_force(
            self.T, self.row[dofs], self.column[dofs], self.u0[dofs], np.asarray(displacement, float)
        )


@nb.njit(**_JIT)
def _one_vertex_force(T, rows, cols, u0, d):
    """Solve the 3x3 system T_kk F = d - u0_k by Cramer's rule (no allocation beyond the result)."""
    a = np.empty((3, 3))
    for r in range(3):
        for c in range(3):
            a[r, c] = T[rows[r], cols[c]]
    b0, b1, b2 = d[0] - u0[0], d[1] - u0[1], d[2] - u0[2]
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    out = np.empty(3)
    out[0] = (
        b0 * c00 + b1 * (a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]) + b2 * (a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1])
    ) / det
    out[1] = (
        b0 * c01 + b1 * (a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]) + b2 * (a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2])
    ) / det
    out[2] = (
        b0 * c02 + b1 * (a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]) + b2 * (a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0])
    ) / det
    return out


class Condensed:
    """Static linear problem condensed onto the surface (and constrained) vertices (Bro-Nielsen 1996).

    Attributes:
        retained: (R,) int64 retained dofs (surface and constrained vertices), interior: (I,) int64.
        K_star: (R, R) float64, N/m, the Schur complement; f_star: (R,) float64, N.
        targets: the tools' prescribed dofs (_Targets); K_tool (D, R) and f_tool (D,): the rows of K_star
            and f_star of those dofs, whose product with the retained displacements less f_tool is the
            force that holds them.
    """

    def __init__(self, model: Model):
        lo = model.loading
        n = model.n_vertices
        keep = np.zeros(n, dtype=bool)
        keep[_surface_vertices(model.tets)] = True
        keep[np.any(lo.free == 0.0, axis=1)] = True
        if len(lo.tool_vertex):
            keep[lo.tool_vertex] = True
        rdofs = (3 * np.flatnonzero(keep)[:, None] + np.arange(3)).ravel()
        idofs = (3 * np.flatnonzero(~keep)[:, None] + np.arange(3)).ravel()
        K = _stiffness(model)
        f = lo.external_force.ravel()
        Kii = K[idofs][:, idofs].tocsc()
        Kir = K[idofs][:, rdofs].tocsc()
        Kri = K[rdofs][:, idofs].tocsr()
        self.lu_ii = spla.splu(Kii)
        # K* a block of retained columns at a time: K_ii^-1 K_ir whole was an (interior x retained)
        # dense array, with its right-hand side and a copy beside it
        self.K_star = K[rdofs][:, rdofs].toarray()
        for start in range(0, len(rdofs), PRECOMPUTE_BLOCK):
            cols = slice(start, min(start + PRECOMPUTE_BLOCK, len(rdofs)))
            self.K_star[:, cols] -= Kri @ self.lu_ii.solve(Kir[:, cols].toarray(order="F"))
        self.f_star = f[rdofs] - Kri @ self.lu_ii.solve(f[idofs])
        self.retained, self.interior = rdofs, idofs
        self._Kir, self._fi = K[idofs][:, rdofs].tocsr(), f[idofs]
        held = (lo.free.ravel() == 0.0)[rdofs]
        self.free_r = np.flatnonzero(~held)
        self.held_r = np.flatnonzero(held)
        self.K_fc = self.K_star[np.ix_(self.free_r, self.held_r)]
        self.n = n
        # Bro-Nielsen's precomputation: the free retained response to the loads (z0) and to unit
        # displacements of the tool dofs (G), so that an update is z0 + G d, a (F x 3P) product
        self.targets = _Targets(model)
        tool_dofs, self.tool_ids = self.targets.dofs, self.targets.tools
        pos = {int(d): k for k, d in enumerate(self.retained)}
        self.tool_cols = np.array([np.flatnonzero(self.held_r == pos[int(d)])[0] for d in tool_dofs], dtype=np.int64)
        self.tool_dofs = tool_dofs
        tool_rows = self.held_r[self.tool_cols]
        self.K_tool, self.f_tool = self.K_star[tool_rows], self.f_star[tool_rows]  # (D, R), (D,)

    @cached_property
    def _solution(self) -> tuple:
        """(Cholesky factor of K* on the free retained dofs, z0 (F,) m, G (F, D)), made when a static
        answer is first asked: a body that nothing holds has a force and an energy but no equilibrium.
        Its K* is singular, which a factorisation may or may not notice in round-off (the reference
        BLAS passed, OpenBLAS did not): InputError instead, whichever BLAS runs."""
        free = self.K_star[np.ix_(self.free_r, self.free_r)]
        scale = float(np.abs(np.diag(free)).max()) if free.size else 0.0
        if len(self.held_r) == 0 or free.size == 0:
            raise InputError(
                "condensed: no vertex is fixed or driven by a tool: the body's rigid motions are free and it "
                "has no static equilibrium"
            )
        unheld = "the fixed and tool vertices do not hold every rigid motion of the body"
        try:
            chol = sla.cho_factor(free)
        except np.linalg.LinAlgError as exc:
            raise InputError(f"condensed: the condensed stiffness is singular ({exc}): {unheld}") from None
        if np.abs(np.diag(chol[0])).min() ** 2 <= 1e3 * np.finfo(float).eps * scale:
            raise InputError(f"condensed: the condensed stiffness is singular to round-off: {unheld}")
        z0 = sla.cho_solve(chol, self.f_star[self.free_r])
        G = (
            -sla.cho_solve(chol, self.K_fc[:, self.tool_cols])
            if len(self.tool_dofs)
            else np.zeros((len(self.free_r), 0))
        )
        return chol, z0, G

    def update(self, tool_values: np.ndarray) -> np.ndarray:
        """Retained displacements (R,) m with the tool dofs at ``tool_values`` (in ``tool_dofs`` order) and
        the fixed dofs at zero: z0 + G d."""
        u = np.zeros(len(self.retained))
        u[self.held_r[self.tool_cols]] = tool_values
        _, z0, G = self._solution
        u[self.free_r] = z0 + G @ tool_values
        return u

    def solve_surface(self, held_values: np.ndarray) -> np.ndarray:
        """Retained displacements (R,) m with the held retained dofs at ``held_values`` (H,) m."""
        u = np.zeros(len(self.retained))
        u[self.held_r] = held_values
        u[self.free_r] = sla.cho_solve(self._solution[0], self.f_star[self.free_r] - self.K_fc @ held_values)
        return u

    def tool_reactions(self, model: Model, u: np.ndarray) -> np.ndarray:
        """Force (L, 3) N each tool exerts on the body, from the retained displacements in ``u`` (N, 3) m
        alone (``QuasiStatic.step`` leaves the interior at zero): on a tool's dof the condensed equation
        reads K* u_r = f* + R, so R = K* u_r - f* on those rows (a (D x R) product), exact whatever the
        interior holds."""
        u_r = np.ascontiguousarray(u, dtype=float).ravel()[self.retained]
        return _per_tool(model, self.tool_dofs, self.tool_ids, self.K_tool @ u_r - self.f_tool)

    def advance(self, model: Model, t: float, u: np.ndarray) -> np.ndarray:
        """Write into u (N, 3) m the retained displacements with the tools where they are at time t (s),
        the interior left at zero (recovered on demand by ``full``); return the force (L, 3) N each tool
        exerts on the body."""
        u_r = self.update(self.targets.values(model, t))
        u[:] = 0.0
        u.reshape(-1)[self.retained] = u_r
        return _per_tool(model, self.tool_dofs, self.tool_ids, self.K_tool @ u_r - self.f_tool)

    def equilibrium(self, model: Model, t: float) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (N, 3) m at equilibrium at time t (all vertices) and the tools' total force (3,) N."""
        held = np.zeros(model.n_vertices * 3)
        held[self.targets.dofs] = self.targets.values(model, t)
        u = self.full(self.solve_surface(held[self.retained[self.held_r]]))
        return u, model.reaction(u)

    def full(self, u_r: np.ndarray) -> np.ndarray:
        """All displacements (N, 3) m: the interior recovered from the retained ones."""
        u = np.zeros(3 * self.n)
        u[self.retained] = u_r
        u[self.interior] = self.lu_ii.solve(self._fi - self._Kir @ u_r)
        return u.reshape(-1, 3)


class QuasiStatic:
    """Integrator of the quasi-static models: each step jumps to the equilibrium with the tools at t."""

    name = "quasi-static"

    def __init__(self, alpha: float = 0.0, beta: float = 0.0):
        self.alpha, self.beta = alpha, beta  # no dynamics: accepted for a common interface, unused

    def critical_dt(self, model: Model, omega2: float | None = None) -> float:
        return np.inf  # unconditionally stable: there is no time integration

    def set_forces(self, model: Model, forces) -> None:
        raise InputError(
            f"set_forces: {model.name} precomputed its response to the loads when it was built; build it "
            "again with the new external_force"
        )

    def set_tool(self, model: Model, tool: int, translation=None, angle=None) -> None:
        raise InputError(
            f"set_tool: {model.name} follows the tools' ramps (its update is a function of the tools' "
            "displacements); build it again with the new targets"
        )

    def step(self, model: Model, state: State, dt: float, n: int = 1, dt_crit: float | None = None) -> np.ndarray:
        """Jump ``state`` to the equilibrium with the tools where they are at t + n dt. Returns the
        force (L, 3) float64 N each tool exerts on the body there (Model.tool_reactions: static, as the
        model is)."""
        from .integrators import _check_step

        model.check_current()
        dt, n = _check_step(model, state, dt, n)
        t = state.t + n * dt
        out = model.extra["quasistatic"].advance(model, t, state.u)
        state.v[:] = 0.0
        state.t = t
        state.steps += n
        return out

    def equilibrium(self, model: Model, t: float = np.inf) -> tuple[np.ndarray, np.ndarray]:
        """Displacement (N, 3) m at equilibrium (all vertices) and the tools' total force (3,) N."""
        return model.extra["quasistatic"].equilibrium(model, t)
