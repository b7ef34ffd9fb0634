"""Every dolfinx call of tissuebench, in one module (dolfinx 0.5.2, Debian's python3-dolfinx).

A port to dolfinx 0.9/0.10 (where VectorFunctionSpace, u.vector and NewtonSolver changed) touches this
file only. The rest of ``reference`` hands it a mesh, a material and a ``Problem`` and gets numpy
arrays back.

Solvers are chosen on purpose: MUMPS's symmetric LDL^T factorisation (PETSc's own LU is four times
slower on a 40k-dof P2 Jacobian), named in ``solver_options`` and so in every result's metadata.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem, geometry
from dolfinx import mesh as dmesh
from dolfinx.fem.petsc import LinearProblem
from mpi4py import MPI
from petsc4py import PETSc

from meshes.regions import locate, spanned
from meshes.tetmesh import TetMesh
from realtime.material import Material, Materials

from .errors import ReferenceSolveError
from .materials import LAWS, volume_penalty_energy
from .problem import Force, Problem, Traction
from .progress import Heartbeat, Progress, line

#: Every tangent the reference factorises is symmetric: its residual is the derivative of an energy
#: (hyperelastic laws, the volume penalty, dead loads) plus symmetric linear terms (consistent mass,
#: Rayleigh damping with the rest stiffness), and the constraints zero rows and columns alike. MUMPS's
#: LDL^T with pivoting (PETSc's "cholesky" on a matrix not flagged SPD, MUMPS SYM=2) takes indefinite
#: tangents too. Measured on the dynamic benchmark's 39 000 P2 dofs against MUMPS LU: half the
#: factor's entries (11.6 M against 23.0 M), factorisation 1.4 s against 2.1 s, a back-substitution
#: 18 ms against 28 ms, the same residual (4e-14).
DIRECT_OPTIONS = {"ksp_type": "preonly", "pc_type": "cholesky", "pc_factor_mat_solver_type": "mumps"}
#: Large problems: GMRES (the StVK tangent need not be definite) preconditioned by smoothed-aggregation
#: algebraic multigrid with the six rigid-body modes as its near null space, the standard setup for
#: elasticity (threshold 0.01 drops weak couplings from the aggregation graph: 42 instead of 101
#: iterations on the slender beam's 276 000 P2 dofs). An inner tolerance of 1e-8 makes Newton inexact
#: but not slower to converge to its own residual test, which decides.
GAMG_OPTIONS = {
    "ksp_type": "gmres",
    "ksp_rtol": 1e-8,
    "ksp_max_it": 2000,
    "pc_type": "gamg",
    "pc_gamg_type": "agg",
    "pc_gamg_agg_nsmooths": 1,
    "pc_gamg_threshold": 0.01,
    "pc_gamg_reuse_interpolation": True,
    "mg_levels_ksp_type": "chebyshev",
    "mg_levels_pc_type": "jacobi",
    "mg_levels_esteig_ksp_type": "cg",
}
#: Degrees of freedom up to which a solve factorises with MUMPS; above, GAMG_OPTIONS. Measured on 2
#: cores: at 95 000 P2 dofs (the twisted cylinder refined) MUMPS factorises in 28 s and solves in 0.1,
#: GAMG sets up in 5 and solves in 2; at 276 000 (the slender beam refined), 70 and 0.3 against 15
#: and 6. Newton needs 2 factorisations and 5 to 7 solves there, so GAMG wins above about 60 000.
DIRECT_LIMIT = 60_000


#: An iterative solve that failed (GMRES breaking down, too many iterations) is tried again where a
#: direct factor is predicted to fit in half the available memory, else with GAMG_STRONGER. The
#: prediction scales the factor measured above (11.6 M entries at 39 000 P2 dofs) by n^(4/3), nested
#: dissection's fill in 3D, and doubles it for MUMPS's workspace: 2.5 GB at 276 000 dofs.
FACTOR_ENTRIES_AT = (39_000, 11.6e6)
#: GAMG_OPTIONS made stronger for a solve that failed with them: GMRES restarted less often, more
#: iterations, every coupling aggregated, more smoothing on each level.
GAMG_STRONGER = {
    **GAMG_OPTIONS,
    "ksp_gmres_restart": 200,
    "ksp_max_it": 20000,
    "pc_gamg_threshold": 0.0,
    "mg_levels_ksp_max_it": 4,
}


def direct_bytes(n_dofs: int) -> float:
    """The memory, bytes, MUMPS is predicted to take to factorise ``n_dofs`` unknowns (FACTOR_ENTRIES_AT)."""
    n0, entries = FACTOR_ENTRIES_AT
    return 2.0 * 8.0 * entries * (n_dofs / n0) ** (4.0 / 3.0)


def available_bytes() -> float:
    """The memory the system has available, bytes (MemAvailable; all of it where that is not known)."""
    import os

    try:
        with open("/proc/meminfo") as fh:
            for row in fh:
                if row.startswith("MemAvailable:"):
                    return float(row.split()[1]) * 1024.0
    except OSError:
        pass
    return float(os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES"))


def fallback_options(opts: dict, n_dofs: int, user: dict | None) -> tuple[dict, str] | None:
    """What a solve whose iterative solver failed with ``opts`` tries next, and a phrase naming it: a
    direct factorisation where it is predicted to fit in half the available memory, else GAMG_STRONGER.
    None when the user chose the solver (``--petsc-option pc_type=...``), the solve was direct, or it
    was already the stronger multigrid."""
    if (
        "pc_type" in (user or {})
        or opts.get("pc_type") != "gamg"
        or opts.get("ksp_max_it") == GAMG_STRONGER["ksp_max_it"]
    ):
        return None
    need, have = direct_bytes(n_dofs), available_bytes()
    if need <= 0.5 * have:
        direct = f"a direct factorisation (MUMPS, about {need / 1e9:.2g} GB of the {have / 1e9:.3g} GB available)"
        return {**DIRECT_OPTIONS, **(user or {})}, direct
    stronger = (
        f"stronger multigrid (a direct factor would take about {need / 1e9:.2g} GB, over half of {have / 1e9:.3g})"
    )
    return {**GAMG_STRONGER, "ksp_rtol": opts.get("ksp_rtol", GAMG_STRONGER["ksp_rtol"]), **(user or {})}, stronger


def solver_options(n_dofs: int, user: dict | None = None, linear: bool = False, reused: bool = False) -> dict:
    """The PETSc options of a solve with ``n_dofs`` unknowns: MUMPS LDL^T up to DIRECT_LIMIT, GAMG above,
    and the user's options (``--petsc-option KEY=VALUE``) over the choice; a user's ``pc_type`` replaces
    the choice whole. ``linear``: the solve is the answer itself, not a Newton step, so GAMG's
    tolerance is 1e-12. ``reused``: one matrix is solved many times (a linear Newmark run): it is
    factorised once wherever the factor is predicted to fit in half the available memory
    (``direct_bytes``), whatever its size, since every later solve is a back-substitution (a stiff
    beam's 110 000 P2 dofs took GAMG's iterations at each of thousands of steps, 1081 s)."""
    fits = reused and direct_bytes(n_dofs) <= 0.5 * available_bytes()
    base = DIRECT_OPTIONS if n_dofs <= DIRECT_LIMIT or fits else GAMG_OPTIONS
    if linear and base is GAMG_OPTIONS:
        base = {**GAMG_OPTIONS, "ksp_rtol": 1e-12}
    user = dict(user or {})
    if "pc_type" in user:
        base = {}
    return {**base, **user}


#: Unknowns above which a solve that factorises or sets up a preconditioner is watched by a heartbeat
#: (reference.progress.Heartbeat): such a call can take minutes (the raptor's MUMPS fallback, 370 000
#: dofs), and starting the watcher costs tens of milliseconds, nothing beside it.
HEARTBEAT_DOFS = 20_000


def _watched(first: bool, n_dofs: int, what: str, rank: int):
    """A heartbeat around a solve when it is the first with its operator and the operator is large,
    else nothing."""
    import contextlib

    if first and n_dofs > HEARTBEAT_DOFS:
        return Heartbeat(f"reference: {what} ({n_dofs} dofs)", rank)
    return contextlib.nullcontext()


#: Modified Newton keeps a factorised tangent while each step cuts the residual at least this much.
SLOW = 10.0
#: The same in a Newmark step, where the tangent moves little from one step to the next and a
#: factorisation costs as much as dozens of iterations with an old one (2 s against about 0.06 s for
#: an iteration's assembly, lifting and back-substitution at 39 000 P2 dofs): a step need only halve
#: the residual.
SLOW_DYNAMIC = 2.0
#: MUMPS's INFOG(1) when a workspace it sized from its analysis's estimate proved too small during the
#: factorisation (-8, -14, -15 integer, -9 real, -17, -20 message buffers; MUMPS 5 users' guide, section
#: "Error diagnostics"). In parallel the estimate depends on the partition, which varies from run to run:
#: block-press's P2 solve on 2 ranks failed with -9 in 6 of 126 runs, then at every load increment
#: (the same partition, the same estimate).
MUMPS_WORKSPACE_ERRORS = (-8, -9, -14, -15, -17, -20)
#: ICNTL(14), the percentage MUMPS adds to its estimated workspace, is doubled from its default of 20 up to
#: this before a workspace failure counts as the linear solver's.
MUMPS_MAX_RELAXATION = 320


def grow_mumps_workspace(factor, log) -> bool:
    """After a factorisation that failed: if ``factor`` (a MUMPS factor matrix) ran out of a workspace
    (INFOG(1) in MUMPS_WORKSPACE_ERRORS; INFOG is the same on every rank, so every rank decides alike),
    double its ICNTL(14) for the next factorisation, say so through ``log`` and return True; False for
    any other failure, a solver that is not MUMPS, or ICNTL(14) already at MUMPS_MAX_RELAXATION."""
    try:
        code, short = factor.getMumpsInfog(1), factor.getMumpsInfog(2)
        relax = factor.getMumpsIcntl(14)
    except (AttributeError, PETSc.Error):
        return False
    if code not in MUMPS_WORKSPACE_ERRORS or relax >= MUMPS_MAX_RELAXATION:
        return False
    factor.setMumpsIcntl(14, min(2 * max(relax, 10), MUMPS_MAX_RELAXATION))
    log(
        f"reference: MUMPS's workspace was too small (INFOG(1) = {code}, INFOG(2) = {short}); factorising "
        f"again with ICNTL(14) = {factor.getMumpsIcntl(14)}% instead of {relax}%"
    )
    return True


def _factor_of(ksp):
    """The factor matrix of ``ksp``'s preconditioner, or None if it factorises nothing (GAMG)."""
    try:
        return ksp.getPC().getFactorMatrix()
    except PETSc.Error:
        return None


def grow_ksp_workspace(ksp, log) -> bool:
    """grow_mumps_workspace on the factor of ``ksp``'s preconditioner; False if it has none (GAMG)."""
    factor = _factor_of(ksp)
    return factor is not None and grow_mumps_workspace(factor, log)


#: A step with a fresh tangent that raises the free residual this many times above the lowest it reached
#: since the call's first step has left Newton's basin: the call gives up (the load step is then cut).
DIVERGED = 1e3


def configure(ksp, options: dict) -> None:
    """Apply ``options`` (PETSc option names without prefix) to ``ksp`` through its prefix, then take
    them out of PETSc's global table: it holds 512 entries per process, and a study that solves a few
    hundred problems in one process would fill it."""
    prefix = ksp.getOptionsPrefix()
    table = PETSc.Options()
    for key, val in options.items():
        table[f"{prefix}{key}"] = val
    ksp.setFromOptions()
    for key in options:
        table.delValue(f"{prefix}{key}")


class Newton:
    """Newton's method on a residual form with a test on the residual itself.

    Converged when the free components of the residual F(u) (N) are below ``rtol`` times the problem's
    force scale, the largest of: the external load's norm (gravity, tractions: |F(0)| in statics, the
    ``external`` form at 0 in a Newmark step, whose F(0) holds inertia), the force on the
    constrained components (the tools' and supports' reactions) and the first iterate's residual; and
    when the constrained components hold their prescribed values (to 1e-12 of their norm, or of the body's
    extent where they are zero and an iterative solve leaves round-off on them). Constraint gaps (m) and forces (N) are
    never added in one norm, and a tiny first load increment cannot make round-off look like a failure
    (dolfinx's incremental test compared |du_k| with rtol |du_1|). Each step solves J du = F with the
    constraints lifted, by ``petsc_options`` (default MUMPS LDL^T).
    """

    def __init__(
        self,
        comm,
        residual,
        u,
        bcs,
        jacobian,
        petsc_options: dict,
        reuse: bool = True,
        near_nullspace=None,
        dynamic: bool = False,
        external=None,
        linear_part=None,
    ):
        self.comm, self.u, self.bcs, self.reuse, self.options = comm, u, bcs, reuse, dict(petsc_options)
        self.dynamic = dynamic  # Newmark steps: SLOW_DYNAMIC instead of SLOW
        self.factorisations = self.undone = self.linear_iterations = 0
        self.at = None  # where the factorised tangent was taken: None (nowhere yet), "current" or "older" u
        self.L, self.a = fem.form(residual), fem.form(jacobian)
        # the form whose value at u = 0 is the external load: the residual itself in statics; a Newmark
        # residual at u = 0 also holds the inertia of snapping back to rest in one step, M u_old /
        # (beta dt^2), which is no load and grows with the displacement (it was 100 N against a step's
        # 0.3 N imbalance in the dynamic benchmark, and set the test 300 times looser than stated)
        self.L_external = None if external is None else fem.form(external)
        # terms of the residual linear in u that are cheaper as matrix products than as integrals (a
        # Newmark step's inertia and damping): linear_part(vec) adds them to an assembled residual's
        # owned entries
        self.linear_part = linear_part
        self.external_load = None  # N: |external at 0|, which no Newmark step changes (computed once)
        self.A = fem.petsc.create_matrix(self.a)
        self.near_nullspace = near_nullspace
        self.b = fem.petsc.create_vector(self.L)
        self.raw = fem.petsc.create_vector(self.L)
        self.du = u.vector.copy()
        self.gap = u.vector.copy()
        self.ksp = PETSc.KSP().create(comm)
        self.ksp.setOptionsPrefix(f"tb_newton_{id(self)}_")
        # an iterative solve (GAMG above DIRECT_LIMIT) costs its iterations, not a factorisation: Newton
        # then takes the current tangent at every step and keeps the preconditioner instead (inexact
        # Newton, Eisenstat and Walker's inner tolerances down to the options' ksp_rtol)
        self.iterative = self.options.get("ksp_type", "preonly") != "preonly"
        self.ksp_rtol = float(self.options.get("ksp_rtol", 1e-8))
        self.pc_first_its = None  # the linear iterations of the first solve after the last set-up
        V = u.function_space
        n_owned = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        self.n_owned = n_owned
        self.constrained = np.zeros(n_owned, dtype=bool)
        for bc in bcs:
            idx = np.asarray(bc.dof_indices()[0])
            self.constrained[idx[idx < n_owned]] = True
        # m, the largest extent of any rank's part of the mesh: the floor of the constraint test, which
        # a held value of zero would otherwise make relative to the round-off an iterative solve leaves
        x = V.mesh.geometry.x
        self.length = comm.allreduce(float(np.ptp(x, axis=0).max()) if len(x) else 0.0, op=MPI.MAX)

    def _norms(self, vec) -> tuple[float, float]:
        """MPI-reduced norms of the free and the constrained owned components of a PETSc vector."""
        arr = vec.array_r
        free = float(np.sum(arr[~self.constrained] ** 2))
        held = float(np.sum(arr[self.constrained] ** 2))
        return math.sqrt(self.comm.allreduce(free, op=MPI.SUM)), math.sqrt(self.comm.allreduce(held, op=MPI.SUM))

    def _assemble_raw(self, form=None):
        """F(u) (N) into ``raw`` (``form``, default the residual); returns its free and held norms."""
        with self.raw.localForm() as loc:
            loc.set(0.0)
        fem.petsc.assemble_vector(self.raw, self.L if form is None else form)
        self.raw.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        if form is None and self.linear_part is not None:
            self.linear_part(self.raw)
        return self._norms(self.raw)

    def _linear_solve(self) -> None:
        """du = J^-1 b with the current operator (factorised or preconditioned on first use; that first
        solve of a large operator is watched by a heartbeat, since it can take minutes in one call)."""
        fresh, self._fresh = getattr(self, "_fresh", False), False
        try:
            with _watched(fresh, self.A.getSize()[0], "factorising the tangent", self.comm.rank):
                self.ksp.solve(self.b, self.du)
        except PETSc.Error as exc:  # a preconditioner that cannot be built (GAMG on a tiny mesh)
            raise ReferenceSolveError(
                f"reference: the linear solver failed (PETSc error {exc.ierr} in its setup, options "
                f"{self.options}); try --petsc-option pc_type=lu"
            ) from None

    def _more_workspace(self) -> bool:
        """grow_ksp_workspace on this solver's KSP (rank 0 says so on stderr)."""

        return grow_ksp_workspace(self.ksp, lambda msg: line(msg, self.comm.rank))

    def _factorise(self) -> None:
        """Assemble the tangent at the current u and have the next solve factorise it."""
        self.A.zeroEntries()
        fem.petsc.assemble_matrix(self.A, self.a, bcs=self.bcs)
        self.A.assemble()
        if self.near_nullspace is not None:
            self.A.setNearNullSpace(self.near_nullspace)  # after assembly, or GAMG does not see it
        self.ksp.setOperators(self.A)
        if not self.factorisations:  # once the operator is known: GAMG reads its block size then
            configure(self.ksp, self.options)
        self.factorisations += 1
        self.at = "current"
        self._fresh = True

    def _tangent(self, rebuild: bool) -> None:
        """Iterative solves: assemble the tangent at the current u as the operator, and rebuild the
        preconditioner from it only when ``rebuild`` (counted as a factorisation)."""
        if rebuild or self.at is None:
            self._factorise()
            self.ksp.getPC().setReusePreconditioner(False)
            self.pc_first_its = None
            return
        self.A.zeroEntries()
        fem.petsc.assemble_matrix(self.A, self.a, bcs=self.bcs)
        self.A.assemble()
        self.ksp.getPC().setReusePreconditioner(True)
        self.at = "current"

    def _inner_rtol(self, free: float, previous: float | None, target: float) -> float:
        """Eisenstat and Walker's second choice of the linear solve's relative tolerance for an inexact
        Newton step (SIAM J. Sci. Comput. 17, 1996): 0.9 (|F_k| / |F_k-1|)^2, at most 1e-2; never tighter
        than the step needs to reach the target (a quarter of it) nor than the options' ksp_rtol."""
        eta = 1e-2 if not previous else min(1e-2, 0.9 * (free / previous) ** 2)  # none before the first step
        return min(0.5, max(eta, 0.25 * target / max(free, 1e-300), self.ksp_rtol))

    def solve(self, rtol: float = 1e-10, max_it: int = 25) -> dict:
        """Iterate from the current u; returns iterations, factorisations, converged, residual and
        scale (N).

        With ``reuse`` (the default) the last factorised tangent is kept across iterations, load steps
        and time steps (modified Newton) while each step cuts the free residual at least SLOW times; a
        step that cuts it less is kept and the tangent is refactorised at the new u, and a step with an
        old tangent that makes the residual grow is undone and redone with a fresh one. The convergence
        test is the same either way, so the answer is the same to ``rtol``. ``max_it`` bounds the
        factorisations of one call; its iterations are bounded by four times as many. A call whose fresh
        Newton step raises the residual DIVERGED times above its best since the first step stops early
        with ``diverged`` (the first step is not judged: from a converged neighbour under a new load it
        can raise the residual by orders of magnitude and still lead to the root).
        """
        u = self.u
        load = self.external_load
        if load is None:  # statics: the load factor moves between calls, so F(0) is assembled each time
            saved = u.x.array.copy()
            u.x.array[:] = 0.0
            load = math.hypot(*self._assemble_raw(self.L_external))  # the external load (stress-free rest state)
            u.x.array[:] = saved
            if self.L_external is not None:
                self.external_load = load
        first = previous = previous_held = before = best = None
        fresh_step = False  # whether the last step was taken with the tangent at its own u
        start = self.factorisations
        progress = Progress("reference: Newton iteration", None, self.comm.rank)
        for it in range(4 * max_it + 1):
            free, held = self._assemble_raw()
            progress.tick(it, f": free residual {free:.3g} N, {self.factorisations - start} factorisations")
            undo = previous is not None and not fresh_step and not (np.isfinite(free) and free <= previous)
            if undo:
                u.x.array[:] = before  # an old tangent led astray: undo its step, take Newton's
                u.x.scatter_forward()
                free, held = previous, previous_held
                self.undone += 1
                self._factorise()
            first = free if first is None else first
            diverged = fresh_step and best is not None and free > DIVERGED * best
            if previous is not None and not undo and np.isfinite(free):  # a state a kept step reached
                best = free if best is None else min(best, free)
            if undo:  # raw holds the residual where the undone step led
                with self.b.localForm() as loc:
                    loc.set(0.0)
                fem.petsc.assemble_vector(self.b, self.L)
                if self.linear_part is not None:  # owned entries; the ghosts' parts are added below
                    self.linear_part(self.b)
            else:  # raw is F(u) already: its owners hold the ghosts' parts, which must not be added twice
                self.raw.copy(self.b)
                with self.b.localForm() as loc:
                    loc.array[self.n_owned :] = 0.0
            with self.gap.localForm() as loc:
                loc.set(0.0)
            fem.petsc.set_bc(self.gap, self.bcs, u.vector, -1.0)  # constrained rows: u - g, m
            gap = self._norms(self.gap)[1]
            if gap > 0.0:  # the lifting adds A (g - u): nothing once u holds its held values exactly
                fem.petsc.apply_lifting(self.b, [self.a], bcs=[self.bcs], x0=[u.vector], scale=-1.0)
            self.b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
            fem.petsc.set_bc(self.b, self.bcs, u.vector, -1.0)
            size = max(self._norms(u.vector)[1], self.length)
            scale = max(load, held, first, 1e-300)
            ok = np.isfinite(free) and np.isfinite(gap)
            out = {"iterations": it, "factorisations": self.factorisations - start, "scale": scale}
            if ok and free <= rtol * scale and gap <= 1e-12 * size:
                return {**out, "converged": True, "residual": free}
            if diverged:
                return {**out, "converged": False, "residual": free, "diverged": True}
            if not ok or self.factorisations - start >= max_it:
                break
            slow = previous is not None and free > previous / (SLOW_DYNAMIC if self.dynamic else SLOW)
            if self.iterative:
                tired = self.pc_first_its is not None and self.ksp.getIterationNumber() > 2 * self.pc_first_its + 10
                self._tangent(rebuild=not self.reuse or tired)  # the operator is current: only the
                # preconditioner can grow stale, and the linear iterations say when
                self.ksp.setTolerances(rtol=self._inner_rtol(free, previous, rtol * scale))
            elif self.at != "current" and (self.at is None or not self.reuse or slow):
                self._factorise()
            fresh_step = self.at == "current"
            before, previous, previous_held = u.x.array.copy(), free, held
            self._linear_solve()
            while self.ksp.getConvergedReason() < 0 and self._more_workspace():
                self._factorise()  # the tangent at the same u, factorised with the larger workspace
                self._linear_solve()
            if self.ksp.getConvergedReason() < 0:  # an inner solve or a factorisation that failed
                out["ksp_reason"] = int(self.ksp.getConvergedReason())
                out["factorisations"] = self.factorisations - start
                break
            self.linear_iterations += self.ksp.getIterationNumber()
            if self.iterative and self.pc_first_its is None:
                self.pc_first_its = self.ksp.getIterationNumber()
            u.vector.axpy(-1.0, self.du)
            # the constrained rows are identity rows whose solution is u - g: u now holds g, exactly (not
            # to the round-off of u - (u - g) or an inner tolerance), so the next lifting is not needed
            fem.petsc.set_bc(u.vector, self.bcs)
            u.x.scatter_forward()
            self.at = "older"  # the factorised tangent is now the one at an earlier u
        return {**out, "converged": False, "residual": free}


def _mumps_info(ksp) -> str:
    """ ", MUMPS INFOG(1) = .., INFOG(2) = .." for a KSP whose preconditioner is MUMPS's factorisation,
    else ""."""
    factor = _factor_of(ksp)
    try:
        return f", MUMPS INFOG(1) = {factor.getMumpsInfog(1)}, INFOG(2) = {factor.getMumpsInfog(2)}"
    except (AttributeError, PETSc.Error):  # no factor, or not MUMPS's
        return ""


def dolfinx_mesh(mesh: TetMesh, comm=MPI.COMM_WORLD, refine: int = 0):
    """A distributed dolfinx mesh of a TetMesh (rank 0 holds the input), refined ``refine`` times
    uniformly (each tetrahedron into eight)."""
    domain_el = ufl.Mesh(ufl.VectorElement("Lagrange", "tetrahedron", 1))
    if comm.rank == 0:
        x, cells = mesh.points, mesh.tets
    else:
        x, cells = np.zeros((0, 3)), np.zeros((0, 4), dtype=np.int64)
    if refine and comm.size > 1:
        # refined on one process, then distributed: dolfinx's parallel refinement picks each octahedron's
        # diagonal by the partition's numbering, and the partition varies from run to run, so the refined
        # mesh, and the answer, did too (5e-5 relative on cantilever-pull's refined P1)
        if comm.rank == 0:
            fine = dolfinx_mesh(mesh, MPI.COMM_SELF, refine)
            x = fine.geometry.x[:, :3].copy()
            cells = fine.geometry.dofmap.array.reshape(-1, 4).astype(np.int64)
        return dmesh.create_mesh(comm, cells, x, domain_el)
    domain = dmesh.create_mesh(comm, cells, x, domain_el)
    for _ in range(refine):
        domain.topology.create_entities(1)
        domain = dmesh.refine(domain)
    return domain


def _marker(region, mesh: TetMesh):
    """A dolfinx marker (x (3, K) -> bool (K,)): the points on the scene mesh's entities spanned by the
    region's vertices (meshes.regions.spanned), so that the reference constrains on its P2 or refined
    mesh exactly what the scene mesh's selection spans, the set the real-time models constrain."""
    selected = region.vertices(mesh)
    return lambda x: spanned(mesh, selected, x.T)


@dataclass
class Solution:
    """What a reference solve returns (numpy arrays on every rank)."""

    values: np.ndarray  # (K, 3) displacement at the requested points, m
    reaction: np.ndarray  # (3,) total force of the tools on the body, N
    info: dict  # dofs, iterations, residuals, timings, solver options


class ElasticityProblem:
    """A static elasticity problem discretised by dolfinx.

    Args:
        mesh: the scene's TetMesh (the coarse geometry; regions with tags refer to it).
        material: the Material, whose ``law`` picks the energy (linear or stvk); or Materials, one for each
            tetrahedron of ``mesh``: each cell of the (refined) domain then takes the material of the
            scene tetrahedron that holds its midpoint, and integrates that material's own energy, fibres
            and density over its cells (exact per-cell coefficients; ``parts``).
        problem: constraints and loads.
        degree: Lagrange degree, 1 or 2.
        refine: uniform refinements of the mesh before discretising.
        comm: MPI communicator.
    """

    def __init__(
        self,
        mesh: TetMesh,
        material: Material | Materials,
        problem: Problem,
        degree: int = 1,
        refine: int = 0,
        comm=MPI.COMM_WORLD,
    ):
        self.mesh, self.material, self.problem = mesh, material, problem
        self.degree, self.refine, self.comm = degree, refine, comm
        t0 = time.perf_counter()
        self.domain = dolfinx_mesh(mesh, comm, refine)
        self._size = float(np.ptp(mesh.points, axis=0).max())  # m, the body's largest extent
        self.V = fem.VectorFunctionSpace(self.domain, ("Lagrange", degree))
        self.u = fem.Function(self.V, name="displacement")
        self.parts = self._material_parts()
        self.load_factor = fem.Constant(self.domain, PETSc.ScalarType(1.0))
        self._tool_functions = []
        self.load_areas = []  # m^2, the loaded area of each force or traction load
        self._located = None  # the last points evaluate() located, and where (see _locate)
        self._reaction_form = None
        self._det_F = None  # the det F expression of min_det_F
        self.bcs = self._boundary_conditions()
        self.residual = self._residual_form()
        self.timings = {"setup_s": time.perf_counter() - t0}

    # ---- forms ----

    def _constant(self, value):
        return fem.Constant(self.domain, PETSc.ScalarType(value))

    def _material_parts(self):
        """[(Material, cell measure)]: the whole domain for one Material; for Materials, one subdomain per
        material present, each cell tagged with the material of the scene tetrahedron holding its
        midpoint (a cell of a refined domain lies inside one scene tetrahedron)."""
        if isinstance(self.material, Material):
            return [(self.material, ufl.dx)]
        mats = Materials.of(self.material, self.mesh.n_tets)
        n_local = self.domain.topology.index_map(3).size_local
        cells = np.arange(n_local, dtype=np.int32)
        parent = locate(self.mesh, dmesh.compute_midpoints(self.domain, 3, cells))
        if np.any(parent < 0):
            raise ReferenceSolveError(f"{int(np.sum(parent < 0))} cells of the domain lie in no scene tetrahedron")
        tags = dmesh.meshtags(self.domain, 3, cells, (mats.index[parent] + 1).astype(np.int32))
        dx = ufl.Measure("dx", domain=self.domain, subdomain_data=tags)
        return [(m, dx(k + 1)) for k, m in enumerate(mats.materials) if np.any(mats.index == k)]

    @property
    def linear(self) -> bool:
        """True when every material's energy is quadratic (linear law, no volume penalty)."""
        return all(m.law == "linear" and m.volume_penalty == 0.0 for m, _ in self.parts)

    @property
    def law(self) -> str:
        """The law's name: the materials' law, or their laws joined by '+'."""
        return "+".join(sorted({m.law for m, _ in self.parts}))

    def fiber(self, m: Material):
        """The unit fibre direction of material m as a UFL vector: its one direction, or around its axis
        a(x) = axis x (x - point) / |axis x (x - point)| at every quadrature point (the continuous field;
        a law is only evaluated off the axis, where it is defined)."""
        if m.fiber_axis is None:
            return ufl.as_vector(m.fiber_vector.tolist())
        x = ufl.SpatialCoordinate(self.domain)
        t = ufl.cross(ufl.as_vector(list(m.fiber_axis)), x - ufl.as_vector(list(m.fiber_point)))
        return t / ufl.sqrt(ufl.dot(t, t))

    def dx_law(self, m: Material, dx):
        """The measure dx of material m's law integrals. With fibres around an axis the integrand holds a
        non-polynomial field whose UFL degree estimate runs past 20: the StVK residual of constant
        fibres is a polynomial of degree 4 (degree - 1) in the cell, and two more orders integrate the
        field's smooth variation."""
        if m.fiber_axis is None:
            return dx
        return dx(metadata={"quadrature_degree": 4 * (self.degree - 1) + 2})

    def energy_density(self, F, m: Material):
        """Material m's energy per unit reference volume (J/m^3) at the deformation gradient F."""
        psi = LAWS[m.law](
            F, self._constant(m.lam), self._constant(m.mu), self.fiber(m), self._constant(m.dlam), self._constant(m.dmu)
        )
        if m.volume_penalty > 0.0:
            psi += volume_penalty_energy(F, self._constant(m.volume_penalty))
        return psi

    def internal_work(self, u, v, law=None):
        """sum over the materials of the integral of P(F(u)) : grad v, P = dW/dF of each material's
        energy (``law``: a LAWS name to use instead of each material's own, without the penalty)."""
        form = 0
        for m, dx in self.parts:
            F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
            psi = self.energy_density(F, m) if law is None else self._law_only(F, m, law)
            form += ufl.inner(ufl.diff(psi, F), ufl.grad(v)) * self.dx_law(m, dx)
        return form

    def _law_only(self, F, m: Material, law: str):
        return LAWS[law](
            F, self._constant(m.lam), self._constant(m.mu), self.fiber(m), self._constant(m.dlam), self._constant(m.dmu)
        )

    def mass_weighted(self, integrand):
        """sum over the materials of the integral of rho integrand (integrand a scalar UFL form)."""
        return sum(self._constant(m.density) * integrand * dx for m, dx in self.parts)

    def _residual_form(self):
        v = ufl.TestFunction(self.V)
        residual = self.internal_work(self.u, v)
        g = self.problem.gravity()
        if np.any(g != 0.0):
            residual -= self.load_factor * self.mass_weighted(ufl.inner(self._constant(tuple(g)), v))
        surface_loads = [ld for ld in self.problem.loads if isinstance(ld, (Force, Traction))]
        if surface_loads:
            fdim = 2
            self.domain.topology.create_connectivity(fdim, 3)
            facets, values = [], []
            boundary = dmesh.exterior_facet_indices(self.domain.topology)
            centres = dmesh.compute_midpoints(self.domain, fdim, boundary)
            for k, ld in enumerate(surface_loads, start=1):
                # a boundary facet is loaded when its scene-mesh parent face has its three vertices in the
                # region: the face the engine loads (a facet's centroid lies inside its parent face)
                f = boundary[spanned(self.mesh, ld.region.vertices(self.mesh), centres)]
                facets.append(f)
                values.append(np.full(len(f), k, dtype=np.int32))
            facets = np.concatenate(facets)
            order = np.argsort(facets)
            tags = dmesh.meshtags(self.domain, fdim, facets[order], np.concatenate(values)[order])
            ds = ufl.Measure("ds", domain=self.domain, subdomain_data=tags)
            for k, ld in enumerate(surface_loads, start=1):
                area = self.comm.allreduce(fem.assemble_scalar(fem.form(self._constant(1.0) * ds(k))), op=MPI.SUM)
                self.load_areas.append(area)
                if area <= 0.0:
                    raise ReferenceSolveError(
                        f"{type(ld).__name__.lower()} load {ld.region.describe()}: no boundary face in the region"
                    )
                t = np.asarray(ld.value, dtype=float)
                if isinstance(ld, Force):
                    t = t / area  # a total force spread as a uniform traction
                residual -= self.load_factor * ufl.inner(self._constant(tuple(t)), v) * ds(k)
        return residual

    # ---- boundary conditions ----

    def _component_dofs(self, region, c):
        Vc, _ = self.V.sub(c).collapse()
        dofs = fem.locate_dofs_geometrical((self.V.sub(c), Vc), _marker(region, self.mesh))
        return Vc, dofs

    def _boundary_conditions(self):
        bcs = []
        for fx in self.problem.fixed:
            for c, name in enumerate("xyz"):
                if name in fx.components:
                    Vc, dofs = self._component_dofs(fx.region, c)
                    zero = fem.Function(Vc)
                    bcs.append(fem.dirichletbc(zero, dofs, self.V.sub(c)))
        self.tool_dofs = []
        self._tool_points = []  # (tool, component, dofs in V, their rest points (K, 3))
        nodes = self.V.tabulate_dof_coordinates()
        for tool in self.problem.tools:
            for c, name in enumerate("xyz"):
                if name in tool.components:
                    Vc, dofs = self._component_dofs(tool.region, c)
                    g = fem.Function(Vc)
                    self._tool_functions.append((tool, c, g))
                    bcs.append(fem.dirichletbc(g, dofs, self.V.sub(c)))
                    d = np.asarray(dofs[0])
                    self.tool_dofs.append((c, d))
                    self._tool_points.append((tool, c, d, nodes[d // 3]))
        self.set_tool_fraction(1.0)
        return bcs

    def set_tool_fraction(self, s: float) -> None:
        """Move every tool to fraction s of its final displacement (angle, for rotations)."""
        for tool, c, g in self._tool_functions:
            g.interpolate(lambda x, tool=tool, c=c: tool.at_fraction(x.T, s)[:, c])

    # ---- solves ----

    def solve_linear(self, petsc_options=None) -> dict:
        """One linear solve (law = linear): K u = f with the Dirichlet conditions."""
        if not self.linear:
            raise ValueError("solve_linear needs law = linear and no volume penalty; use solve_newton")
        opts = solver_options(self.n_dofs, petsc_options, linear=True)
        du = ufl.TrialFunction(self.V)
        zero = fem.Function(self.V)
        a = ufl.replace(ufl.derivative(self.residual, self.u, du), {self.u: zero})
        L = -ufl.replace(self.residual, {self.u: zero})
        t0 = time.perf_counter()
        problem = LinearProblem(a, L, bcs=self.bcs, u=self.u, petsc_options=opts)
        if opts.get("pc_type") == "gamg":
            problem.A.setNearNullSpace(self.rigid_body_modes())
        with _watched(True, self.n_dofs, "the linear solve", self.comm.rank):
            problem.solve()
        reason = problem.solver.getConvergedReason()
        while reason < 0 and grow_ksp_workspace(problem.solver, self._log):
            problem.solve()  # assembles the matrix again, so the preconditioner factorises it again
            reason = problem.solver.getConvergedReason()
        tried = [f"{opts.get('pc_type')} (PETSc reason {reason})"]
        while reason < 0 and (fallback := fallback_options(opts, self.n_dofs, petsc_options)) is not None:
            opts, what = fallback
            self._log(f"reference: the iterative solve failed (PETSc reason {reason}); trying {what}")
            problem = LinearProblem(a, L, bcs=self.bcs, u=self.u, petsc_options=opts)
            if opts.get("pc_type") == "gamg":
                problem.A.setNearNullSpace(self.rigid_body_modes())
            with _watched(True, self.n_dofs, what.split(" (")[0], self.comm.rank):
                problem.solve()
            reason = problem.solver.getConvergedReason()
            tried.append(f"{what.split(' (')[0]} (PETSc reason {reason})")
        if reason < 0:
            raise ReferenceSolveError(
                f"linear solve failed ({self.n_dofs} dofs): tried {', then '.join(tried)}; a coarser mesh, "
                "--petsc-option pc_type=lu, or more memory for a direct solve may help"
            )
        self.timings["solve_s"] = time.perf_counter() - t0
        # recorded, not enforced: linear elasticity has no notion of inversion, but a user should see
        # when its answer means elements turned inside out
        return {"solver": "linear", "petsc_options": opts, "iterations": 1, "min_det_F": self.min_det_F()}

    def solve_newton(
        self,
        steps: int = 1,
        rtol: float = 1e-10,
        max_it: int = 25,
        min_increment: float = 1e-4,
        petsc_options=None,
        time_limit: float = 600.0,
        start_at_full_load: bool = False,
    ) -> dict:
        """Newton with load stepping and step halving on failure (the load fraction goes 0 -> 1).

        ``start_at_full_load``: u already holds a good guess (a coarser level's solution): try the full
        load from it first, and fall back to load stepping from rest if Newton fails there.

        Convergence: ``Newton``'s residual test (free residual below rtol times the force scale).
        Raises ReferenceSolveError naming the load fraction reached and what to change when the
        increment became smaller than ``min_increment`` or the solve took more than ``time_limit``
        seconds. Each load step's Newton iterations go to stderr.
        """
        opts = solver_options(self.n_dofs, petsc_options)
        du = ufl.TrialFunction(self.V)
        solver = Newton(
            self.comm,
            self.residual,
            self.u,
            self.bcs,
            ufl.derivative(self.residual, self.u, du),
            opts,
            near_nullspace=self.rigid_body_modes() if opts.get("pc_type") == "gamg" else None,
        )
        t0 = time.perf_counter()
        done, inc = 0.0, 1.0 / steps
        history = []
        if start_at_full_load:
            self.load_factor.value = 1.0
            self.set_tool_fraction(1.0)
            res = solver.solve(rtol, max_it)
            ok = res["converged"] and bool(np.all(np.isfinite(self.u.x.array)))
            jmin = self.min_det_F() if ok else float("nan")
            if ok and jmin > 0.0:
                history.append(
                    {
                        "load": 1.0,
                        "iterations": res["iterations"],
                        "factorisations": res["factorisations"],
                        "min_det_F": jmin,
                        "nested": True,
                    }
                )
                self._log(
                    f"reference: full load from the coarser solution: {res['iterations']} Newton iterations, "
                    f"{res['factorisations']} factorisations"
                )
                done = 1.0
            else:
                self._log("reference: Newton from the coarser solution failed; load stepping from rest")
                self.u.x.array[:] = 0.0
        while done < 1.0 - 1e-14:
            target = min(1.0, done + inc)
            saved = self.u.x.array.copy()
            self.load_factor.value = target
            self.set_tool_fraction(target)
            res = solver.solve(rtol, max_it)
            its, ok = res["iterations"], res["converged"]
            elapsed = time.perf_counter() - t0
            ok = ok and bool(np.all(np.isfinite(self.u.x.array)))
            # a root with inverted elements solves the equations but is no deformation of the body
            # (StVK has one under strong compression): it counts as a failure
            jmin = self.min_det_F() if ok else float("nan")
            if ok and jmin > 0.0:
                history.append(
                    {"load": target, "iterations": int(its), "factorisations": res["factorisations"], "min_det_F": jmin}
                )
                self._log(
                    f"reference: load {target:.4g}: {int(its)} Newton iterations, {res['factorisations']} "
                    f"factorisations ({elapsed:.1f} s)"
                )
                done = target
                inc = min(2.0 * inc, 1.0)
                continue
            self.u.x.array[:] = saved
            inc *= 0.5
            if ok:
                what = f"Newton found inverted elements (min det F = {jmin:.3g})"
            elif res.get("diverged"):
                what = (
                    f"Newton diverged after {res['factorisations']} factorisations (residual {DIVERGED:.0e} x its best)"
                )
            elif "ksp_reason" in res:
                what = f"the linear solver failed (PETSc KSP reason {res['ksp_reason']}{_mumps_info(solver.ksp)})"
            else:
                what = f"Newton failed ({res['factorisations']} factorisations)"
            self._log(f"reference: load {target:.4g}: {what}, load increment halved to {inc:.3g}")
            if inc < min_increment or elapsed > time_limit:
                why = f"increments down to {inc:.1e}" if inc < min_increment else f"{elapsed:.0f} s, the limit"
                raise ReferenceSolveError(
                    f"reference: Newton found no equilibrium without inverted elements beyond load fraction "
                    f"{done:.4g} ({why}; law = "
                    f"{self.law}, P{self.degree}, refine {self.refine}, {self.n_dofs} dofs): the load may "
                    f"be too large for this mesh and law, or elements invert; try a smaller load, a finer mesh, "
                    f"law = linear, or more load steps (--load-steps {max(4 * steps, 10)})"
                )
        self.timings["solve_s"] = time.perf_counter() - t0
        return {
            "solver": "newton",
            "petsc_options": opts,
            "load_steps": history,
            "iterations": sum(h["iterations"] for h in history),
            "factorisations": solver.factorisations,  # failed load steps' included
            "undone_steps": solver.undone,
            "linear_iterations": solver.linear_iterations,
            "rtol": rtol,
            "min_det_F": history[-1]["min_det_F"],
        }

    def solve(self, **kwargs) -> dict:
        """solve_linear for the linear law without penalty, solve_newton otherwise."""
        if self.linear:
            return self.solve_linear(petsc_options=kwargs.get("petsc_options"))
        return self.solve_newton(**kwargs)

    def rigid_body_modes(self):
        """The six rigid-body modes as a PETSc near null space (GAMG's coarse space for elasticity)."""
        x = self.V.tabulate_dof_coordinates()
        vecs = [fem.Function(self.V) for _ in range(6)]
        for k in range(3):
            vecs[k].x.array.reshape(-1, 3)[:, k] = 1.0
        rot = [(0, 1), (1, 2), (2, 0)]
        for k, (i, j) in enumerate(rot):
            arr = vecs[3 + k].x.array.reshape(-1, 3)
            arr[:, i] = -x[:, j]
            arr[:, j] = x[:, i]
        petsc_vecs = []
        for v in vecs:
            v.x.scatter_forward()
            # a copy owns its memory: v.vector wraps the Function's array, which dies with this frame
            petsc_vecs.append(v.vector.copy())
        return PETSc.NullSpace().create(vectors=_orthonormal(petsc_vecs), comm=self.comm)

    def energy(self) -> float:
        """Total elastic energy of the current displacement, J (MPI-reduced)."""
        F = ufl.Identity(3) + ufl.grad(self.u)
        energy = sum(self.energy_density(F, m) * self.dx_law(m, dx) for m, dx in self.parts)
        local = fem.assemble_scalar(fem.form(energy))
        return self.comm.allreduce(local, op=MPI.SUM)

    def solve_dynamic(
        self,
        dt: float,
        end: float,
        output_every: float,
        points: np.ndarray,
        rayleigh=(0.0, 0.0),
        newmark=(0.25, 0.5),
        petsc_options=None,
        newton_rtol: float = 1e-10,
        before_loop=None,
    ):
        """Newmark time integration from rest (average acceleration by default: beta = 1/4, gamma = 1/2,
        second order, no numerical damping), consistent mass, Rayleigh damping C = a M + b K0 (K0 the
        stiffness at rest, so the damping is the same linear operator in every law), tools ramped as
        the scene says, loads applied at t = 0.

        Linear law without penalty: the effective matrix M/(beta dt^2) + C gamma/(beta dt) + K is
        assembled and factored once. Otherwise Newton on the same residual at every step.
        ``before_loop``: called when the set-up is done and the time loop begins (a heartbeat's stop).
        Returns times (T,), displacements (T, K, 3) at ``points`` and reactions (T, 3), the first
        output at t = 0; ``self.velocity`` and ``self.acceleration`` hold the final state. The tools'
        dofs move with their exact velocity and acceleration (``Displacement.kinematics``). Reactions
        are quasi-static, as the engine's are: the tools' force on the body's stiffness and loads,
        without the inertia of the region they drive.
        """
        beta, gamma = newmark
        a_m, b_k = rayleigh
        V = self.V
        u_old, v_old, a_old = fem.Function(V), fem.Function(V), fem.Function(V)
        w = ufl.TestFunction(V)
        c1, c2, c3 = 1.0 / (beta * dt * dt), 1.0 / (beta * dt), (1.0 - 2.0 * beta) / (2.0 * beta)

        def accel(u):
            return c1 * (u - u_old) - c2 * v_old - c3 * a_old

        def veloc(u):
            return v_old + dt * ((1.0 - gamma) * a_old + gamma * accel(u))

        u = self.u
        residual = self.residual + self.mass_weighted(ufl.inner(accel(u), w))
        if a_m:
            residual += a_m * self.mass_weighted(ufl.inner(veloc(u), w))
        if b_k:  # the rest stiffness K0 as a form: inner(C : eps(veloc), eps(w)), each material's C
            residual += b_k * self.internal_work(veloc(u), w, law="linear")
        linear = self.linear
        opts = solver_options(self.n_dofs, petsc_options, linear=linear, reused=linear)
        modes = self.rigid_body_modes() if opts.get("pc_type") == "gamg" else None
        times, values, reactions = [0.0], [self.evaluate(points)], [self.reaction()]
        self.set_tool_fraction_at(0.0)
        # initial acceleration: M a0 = f_ext - f_int(0) with the tools' accelerations zero at rest
        a_trial = ufl.TrialFunction(V)
        mass_form = self.mass_weighted(ufl.inner(a_trial, w))
        zero = fem.Function(V)
        rhs0 = -ufl.replace(self.residual, {self.u: zero})
        LinearProblem(mass_form, rhs0, bcs=self._homogeneous_bcs(), u=a_old, petsc_options=opts).solve()
        for tool, c, d, x in self._tool_points:  # the tools' own motion at t = 0
            _, vel, acc = tool.kinematics(x, 0.0)
            v_old.x.array[d] = vel[:, c]
            a_old.x.array[d] = acc[:, c]
        du = ufl.TrialFunction(V)
        J = ufl.derivative(residual, u, du)
        n_steps = int(round(end / dt))
        every = max(int(round(output_every / dt)), 1)
        t0 = time.perf_counter()
        if linear:
            a_form = fem.form(ufl.replace(J, {u: zero}))
            A = fem.petsc.assemble_matrix(a_form, bcs=self.bcs)
            A.assemble()
            if modes is not None:
                A.setNearNullSpace(modes)
            ksp = PETSc.KSP().create(self.comm)
            ksp.setOperators(A)
            ksp.setOptionsPrefix(f"tb_dyn_{id(self)}_")
            configure(ksp, opts)
            L_form = fem.form(-ufl.replace(residual, {u: zero}))
            b = fem.petsc.create_vector(L_form)
        else:
            solver = Newton(
                self.comm,
                self.residual,
                u,
                self.bcs,
                J,
                opts,
                near_nullspace=modes,
                dynamic=True,
                external=self.residual,
                linear_part=self._newmark_linear_part(u_old, v_old, a_old, (c1, c2, c3, dt, gamma), rayleigh),
            )
        if before_loop is not None:
            before_loop()
        iterations = 0
        progress = Progress("reference: Newmark step", n_steps, self.comm.rank)
        for step in range(1, n_steps + 1):
            t = step * dt
            self.set_tool_fraction_at(t)
            if linear:
                progress.tick(step - 1, f", t = {t:.4g} s of {end:.4g}; one factorisation, back-substitutions")
                with b.localForm() as loc:
                    loc.set(0.0)
                fem.petsc.assemble_vector(b, L_form)
                fem.petsc.apply_lifting(b, [a_form], bcs=[self.bcs])
                b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
                fem.petsc.set_bc(b, self.bcs)
                if step == 1:  # the factorisation, in the first solve
                    with Heartbeat(f"reference: factorising the Newmark matrix ({self.n_dofs} dofs)", self.comm.rank):
                        ksp.solve(b, u.vector)
                else:
                    ksp.solve(b, u.vector)
                while ksp.getConvergedReason() < 0 and grow_ksp_workspace(ksp, self._log):
                    A.zeroEntries()  # the same operator in a new state: the preconditioner factorises it again
                    fem.petsc.assemble_matrix(A, a_form, bcs=self.bcs)
                    A.assemble()
                    ksp.solve(b, u.vector)
                if ksp.getConvergedReason() < 0:
                    raise ReferenceSolveError(
                        f"reference: Newmark's linear solve failed at t = {t:.4g} s (PETSc reason "
                        f"{ksp.getConvergedReason()}{_mumps_info(ksp)}, options {opts}); try --petsc-option "
                        "pc_type=lu"
                    )
                u.x.scatter_forward()
                iterations += 1
            else:
                # predictor: the last state (extrapolating with the last acceleration carries the mesh's
                # highest modes, which average-acceleration Newmark does not damp: Newton failed from it)
                u.x.array[:] = u_old.x.array
                res = solver.solve(newton_rtol, 25)
                its, ok = res["iterations"], res["converged"]
                if not ok or not np.all(np.isfinite(u.x.array)):
                    raise ReferenceSolveError(
                        f"reference: Newmark's Newton did not converge at t = {t:.4g} s (step {step} of "
                        f"{n_steps}, dt = {dt:.3g} s): a smaller output_every (it sets dt), a smaller load or "
                        "a finer mesh may help"
                    )
                iterations += int(its)
                progress.tick(
                    step, f", t = {t:.4g} s: {iterations} Newton iterations, {solver.factorisations} factorisations"
                )
            a_new = c1 * (u.x.array - u_old.x.array) - c2 * v_old.x.array - c3 * a_old.x.array
            v_old.x.array[:] = v_old.x.array + dt * ((1.0 - gamma) * a_old.x.array + gamma * a_new)
            a_old.x.array[:] = a_new
            # a tool's region moves as the problem says, not as Newmark would infer from its positions
            # (a linear ramp would read as velocities 2V, 0, 2V...): its exact velocity and acceleration
            for tool, c, d, x in self._tool_points:
                _, vel, acc = tool.kinematics(x, t)
                v_old.x.array[d] = vel[:, c]
                a_old.x.array[d] = acc[:, c]
            u_old.x.array[:] = u.x.array
            if step % every == 0 or step == n_steps:
                times.append(t)
                values.append(self.evaluate(points))
                reactions.append(self.reaction())
        self.timings["solve_s"] = time.perf_counter() - t0
        self.velocity, self.acceleration = v_old, a_old  # the state at the end, m/s and m/s^2
        info = {
            "solver": "newmark",
            "beta": beta,
            "gamma": gamma,
            "dt": dt,
            "steps": n_steps,
            "iterations": iterations,
            "factorisations": 1 if linear else solver.factorisations,
            "petsc_options": opts,
            "rayleigh": list(rayleigh),
        }
        return np.array(times), np.array(values), np.array(reactions), info

    def _newmark_linear_part(self, u_old, v_old, a_old, coefficients, rayleigh):
        """What a Newmark residual adds to the static one, as matrix products: M (a + a_m v) + b_k K0 v,
        with a = c1 (u - u_old) - c2 v_old - c3 a_old and v = v_old + dt ((1 - gamma) a_old + gamma a) the
        step's acceleration and velocity at the iterate u (the same terms as the forms the tangent
        differentiates, and equal to them to round-off: K0 is its form's matrix, and M, which couples no
        two components, is the scalar space's mass matrix applied to each component). Assembled as
        integrals they took a third of each residual's assembly (9.3 ms against 5.8 at 39 000 P2 dofs)
        and packed four functions' values per cell; the vector space's M, with the 3 x 3 blocks of its
        sparsity, took 3.8 ms a product. Returns add(vec), which adds them to a residual's owned
        entries."""
        c1, c2, c3, dt, gamma = coefficients
        a_m, b_k = rayleigh
        V, w, trial = self.V, ufl.TestFunction(self.V), ufl.TrialFunction(self.V)
        S = fem.FunctionSpace(self.domain, ("Lagrange", self.degree))  # V's nodes, one component
        M = fem.petsc.assemble_matrix(fem.form(self.mass_weighted(ufl.TrialFunction(S) * ufl.TestFunction(S))))
        M.assemble()
        K0 = None
        if b_k:
            zero, probe = fem.Function(V), fem.Function(V)
            stiffness = ufl.derivative(self.internal_work(probe, w, law="linear"), probe, trial)
            K0 = fem.petsc.assemble_matrix(fem.form(ufl.replace(stiffness, {probe: zero})))
            K0.assemble()
        n = V.dofmap.index_map.size_local * V.dofmap.index_map_bs
        x, y = M.createVecs()
        vel = None if K0 is None else K0.createVecRight()

        def add(vec):
            a = c1 * (self.u.x.array[:n] - u_old.x.array[:n]) - c2 * v_old.x.array[:n] - c3 * a_old.x.array[:n]
            v = v_old.x.array[:n] + dt * ((1.0 - gamma) * a_old.x.array[:n] + gamma * a)
            inertia = a + a_m * v
            out = vec.array
            for c in range(3):  # V's dofs are its nodes' x, y, z in turn
                x.array[:] = inertia[c::3]
                M.mult(x, y)
                out[c::3] += y.array_r
            if K0 is not None:
                vel.array[:] = b_k * v
                K0.multAdd(vel, vec, vec)

        return add

    def _homogeneous_bcs(self):
        """The same constrained dofs as self.bcs, with value zero."""
        out = []
        for fx in self.problem.fixed:
            for c, name in enumerate("xyz"):
                if name in fx.components:
                    Vc, dofs = self._component_dofs(fx.region, c)
                    out.append(fem.dirichletbc(fem.Function(Vc), dofs, self.V.sub(c)))
        for tool in self.problem.tools:
            for c, name in enumerate("xyz"):
                if name in tool.components:
                    Vc, dofs = self._component_dofs(tool.region, c)
                    out.append(fem.dirichletbc(fem.Function(Vc), dofs, self.V.sub(c)))
        return out

    def set_tool_fraction_at(self, t: float) -> None:
        """Move every tool to where its ramp puts it at time t (s)."""
        for tool, c, g in self._tool_functions:
            g.interpolate(lambda x, tool=tool, c=c: tool.value(x.T, t)[:, c])

    def start_from(self, coarse: ElasticityProblem) -> None:
        """Set u to another problem's solution evaluated at this one's nodes (nested iteration: the
        refined problem starts where the coarse one ended). Collective: in parallel every rank's nodes
        (owned and ghosts) are gathered, evaluated on the coarse problem's distributed mesh by all
        ranks, and each rank takes its own back."""
        nodes = self.V.tabulate_dof_coordinates()
        if self.comm.size == 1:
            self.u.x.array[:] = coarse.evaluate(nodes).ravel()
            return
        counts = self.comm.allgather(len(nodes))
        values = coarse.evaluate(np.concatenate(self.comm.allgather(nodes)))
        start = sum(counts[: self.comm.rank])
        self.u.x.array[:] = values[start : start + len(nodes)].ravel()

    def min_det_F(self) -> float:
        """The smallest det F = det(I + grad u) at the vertices and centroids of the cells (MPI-reduced).
        For P1 it is exact (F is constant per cell); for P2, det F is a cubic and these five points sample it."""
        if self._det_F is None:  # compiled once per problem, evaluated after every load step
            points = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0.25, 0.25, 0.25]], dtype=np.float64)
            self._det_F = fem.Expression(ufl.det(ufl.Identity(3) + ufl.grad(self.u)), points)
        n_local = self.domain.topology.index_map(3).size_local
        local = self._det_F.eval(np.arange(n_local, dtype=np.int32)).min() if n_local else np.inf
        return float(self.comm.allreduce(float(local), op=MPI.MIN))

    def _log(self, msg: str) -> None:
        """Progress to stderr, from rank 0 only, one whole line (reference.progress)."""
        line(msg, self.comm.rank)

    # ---- post-processing (MPI-safe) ----

    @property
    def n_dofs(self) -> int:
        return self.V.dofmap.index_map.size_global * self.V.dofmap.index_map_bs

    def _locate(self, pts: np.ndarray) -> tuple:
        """Where this rank evaluates each of ``pts`` (K, 3) m: (points, local cells) for the points inside
        its cells, the same for the points that round-off puts a hair outside every cell (the closest
        cell within 1e-9 of the mesh's size: a refined mesh's boundary midpoint against the coarse
        cells), and the number of ranks that evaluate each point (K,). Kept for the last point set: a
        dynamic solve evaluates the same points at every output."""
        if self._located is not None and np.array_equal(self._located[0], pts):
            return self._located[1]
        tree = geometry.BoundingBoxTree(self.domain, 3)
        cand = geometry.compute_collisions(tree, pts)
        cells = geometry.compute_colliding_cells(self.domain, cand, pts)
        found = np.array([len(cells.links(i)) > 0 for i in range(len(pts))], dtype=bool)
        inside = np.flatnonzero(found)
        first = np.array([cells.links(i)[0] for i in inside], dtype=np.int32)
        count = np.zeros(len(pts))
        self.comm.Allreduce(found.astype(float), count, op=MPI.SUM)
        missing = np.flatnonzero(count == 0)
        near_idx, near_cells = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int32)
        if len(missing):
            at = pts[missing]
            n_local = self.domain.topology.index_map(3).size_local
            own = np.arange(n_local, dtype=np.int32)
            closest = geometry.compute_closest_entity(
                tree, geometry.create_midpoint_tree(self.domain, 3, own), self.domain, at
            )
            near = np.zeros(len(missing), dtype=bool)
            if n_local:
                d2 = geometry.squared_distance(self.domain, 3, closest, at)
                near = (closest >= 0) & (d2 <= (1e-9 * self._size) ** 2)
            hits = np.zeros(len(missing))
            self.comm.Allreduce(near.astype(float), hits, op=MPI.SUM)
            count[missing] = hits
            near_idx, near_cells = missing[near], closest[near].astype(np.int32)
        if np.any(count == 0):
            bad = int(np.argmax(count == 0))
            raise ReferenceSolveError(f"point {bad} {pts[bad]} lies outside the reference mesh")
        where = (inside, first, near_idx, near_cells, count)
        self._located = (pts.copy(), where)
        return where

    def evaluate(self, points: np.ndarray, function=None) -> np.ndarray:
        """Values (K, 3) of the displacement at points (K, 3) m, on every rank.

        Each rank evaluates the points inside its cells; a sum over ranks with a count divides out the
        points found on two ranks (the field is continuous, so their values agree).
        """
        u = self.u if function is None else function
        pts = np.ascontiguousarray(points, dtype=np.float64)
        inside, first, near_idx, near_cells, count = self._locate(pts)
        vals = np.zeros((len(pts), 3))
        if len(inside):
            vals[inside] = u.eval(pts[inside], first)
        if len(near_idx):
            vals[near_idx] = u.eval(pts[near_idx], near_cells)
        total = np.zeros_like(vals)
        self.comm.Allreduce(vals, total, op=MPI.SUM)
        return total / count[:, None]

    def reaction(self) -> np.ndarray:
        """Total force (3,) N the tools exert on the body: the residual summed over their dofs."""
        if not self.tool_dofs:
            return np.zeros(3)
        if self._reaction_form is None:  # compiled once: a dynamic solve asks at every output
            self._reaction_form = fem.form(self.residual)
        r = fem.petsc.assemble_vector(self._reaction_form)
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        arr = r.array_r
        n_owned = self.V.dofmap.index_map.size_local * self.V.dofmap.index_map_bs
        out = np.zeros(3)
        seen = set()
        for c, dofs in self.tool_dofs:
            own = dofs[dofs < n_owned]
            new = [d for d in own if d not in seen]  # a vertex in two tools counts once
            seen.update(new)
            out[c] += float(np.sum(arr[np.asarray(new, dtype=np.int64)])) if new else 0.0
        return self.comm.allreduce(out, op=MPI.SUM)

    def stiffness_matrix(self):
        """Serial only: the stiffness at u = 0 without boundary conditions as scipy CSR, and the dof
        coordinates (n_dofs / 3, 3) in dolfinx's node order (dof 3 k + c is node k, component c)."""
        import scipy.sparse as sp

        if self.comm.size != 1:
            raise RuntimeError("stiffness_matrix is serial")
        du = ufl.TrialFunction(self.V)
        zero = fem.Function(self.V)
        a = ufl.replace(ufl.derivative(self.residual, self.u, du), {self.u: zero})
        A = fem.petsc.assemble_matrix(fem.form(a))
        A.assemble()
        indptr, indices, data = A.getValuesCSR()
        K = sp.csr_matrix((data, indices, indptr), shape=A.getSize())
        return K, self.V.tabulate_dof_coordinates()

    def residual_vector(self, u_nodes: np.ndarray | None = None):
        """Serial only: residual (internal minus external force, N) at the dolfinx node order, (n, 3).
        If ``u_nodes`` (n, 3) m is given it is loaded into u first (node order of dof coordinates)."""
        if self.comm.size != 1:
            raise RuntimeError("residual_vector is serial")
        if u_nodes is not None:
            self.u.x.array[:] = np.asarray(u_nodes, dtype=float).ravel()
        r = fem.petsc.assemble_vector(fem.form(self.residual))
        r.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        return r.array_r.reshape(-1, 3).copy()


def _orthonormal(vecs):
    """Modified Gram-Schmidt on PETSc vectors (in place); returns them."""
    for i, v in enumerate(vecs):
        for u in vecs[:i]:
            v.axpy(-v.dot(u), u)
        v.normalize()
    return vecs


def manufactured_errors(
    law: str, degree: int, n: int, material: Material, comm=MPI.COMM_WORLD, refine: int = 0, points=None
) -> dict:
    """Solve -div P(u) = f on the unit cube (n^3 cubes of six tetrahedra, then ``refine`` uniform
    refinements) with u = u_exact on the boundary, f = -div P(u_exact) derived in UFL, and return the L2
    and H1-seminorm errors; with ``points`` (K, 3), also the solution and u_exact there ("values", "exact").

    u_exact = 0.05 (sin(pi x) sin(pi y) z, x y (1 - z) cos(pi z), sin(pi z) (x + y^2)) is smooth and
    large enough (5% strain) for the StVK terms to matter. Errors are integrated against the exact
    expression with quadrature of degree 2 degree + 6, so that the error of the error is negligible.
    """
    domain = dmesh.create_unit_cube(comm, n, n, n, dmesh.CellType.tetrahedron)
    for _ in range(refine):
        domain.topology.create_entities(1)
        domain = dmesh.refine(domain)
    V = fem.VectorFunctionSpace(domain, ("Lagrange", degree))
    x = ufl.SpatialCoordinate(domain)
    pi = ufl.pi
    ue = 0.05 * ufl.as_vector(
        (
            ufl.sin(pi * x[0]) * ufl.sin(pi * x[1]) * x[2],
            x[0] * x[1] * (1 - x[2]) * ufl.cos(pi * x[2]),
            ufl.sin(pi * x[2]) * (x[0] + x[1] ** 2),
        )
    )
    lam, mu = fem.Constant(domain, PETSc.ScalarType(material.lam)), fem.Constant(domain, PETSc.ScalarType(material.mu))
    a0 = ufl.as_vector((0.0, 0.0, 0.0))

    def P(u):
        F = ufl.variable(ufl.Identity(3) + ufl.grad(u))
        return ufl.diff(LAWS[law](F, lam, mu, a0, 0.0, 0.0), F)

    f = -ufl.div(P(ue))
    u = fem.Function(V)
    v = ufl.TestFunction(V)
    # f is smooth: degree 2 p + 4 integrates it far below the discretisation error (UFL's own estimate
    # for div P(u_exact) of sines asks for thousands of points per cell)
    dxf = ufl.dx(metadata={"quadrature_degree": 2 * degree + 4})
    residual = ufl.inner(P(u), ufl.grad(v)) * dxf - ufl.inner(f, v) * dxf
    fdim = 2
    domain.topology.create_connectivity(fdim, 3)
    facets = dmesh.exterior_facet_indices(domain.topology)
    dofs = fem.locate_dofs_topological(V, fdim, facets)
    g = fem.Function(V)
    g.interpolate(fem.Expression(ue, V.element.interpolation_points()))
    bc = fem.dirichletbc(g, dofs)
    u.x.array[:] = g.x.array  # start from the interpolant: Newton converges in a few steps
    solver = Newton(comm, residual, u, [bc], ufl.derivative(residual, u, ufl.TrialFunction(V)), DIRECT_OPTIONS)
    res = solver.solve(1e-12, 25)
    its, ok = res["iterations"], res["converged"]
    if not ok:
        raise ReferenceSolveError(f"manufactured solution: Newton failed ({law}, P{degree}, n = {n})")
    dx = ufl.dx(metadata={"quadrature_degree": 2 * degree + 6})
    e = u - ue
    l2 = np.sqrt(comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(e, e) * dx)), op=MPI.SUM))
    h1 = np.sqrt(comm.allreduce(fem.assemble_scalar(fem.form(ufl.inner(ufl.grad(e), ufl.grad(e)) * dx)), op=MPI.SUM))
    out = {
        "h": 1.0 / (n * 2**refine),
        "l2": float(l2),
        "h1": float(h1),
        "dofs": V.dofmap.index_map.size_global * 3,
        "newton_iterations": int(its),
    }
    if points is not None:
        pts = np.ascontiguousarray(points, dtype=np.float64)
        tree = geometry.BoundingBoxTree(domain, 3)
        cells = geometry.compute_colliding_cells(domain, geometry.compute_collisions(tree, pts), pts)
        first = np.array([cells.links(i)[0] for i in range(len(pts))], dtype=np.int32)
        out["values"] = u.eval(pts, first)
        X = pts.T
        out["exact"] = 0.05 * np.stack(
            [
                np.sin(np.pi * X[0]) * np.sin(np.pi * X[1]) * X[2],
                X[0] * X[1] * (1 - X[2]) * np.cos(np.pi * X[2]),
                np.sin(np.pi * X[2]) * (X[0] + X[1] ** 2),
            ],
            axis=1,
        )
    return out
