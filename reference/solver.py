"""The reference's linear and non-linear solves in dolfinx 0.5.2: which PETSc solver for which size,
what is done when it fails (more MUMPS workspace, a direct solve where it fits, a stronger multigrid),
and Newton's method with a modified tangent (``Newton``).

Solvers are chosen on purpose: MUMPS's symmetric LDL^T factorisation (PETSc's own LU is four times
slower on a 40k-dof P2 Jacobian), named in ``solver_options`` and so in every result's metadata.
"""

from __future__ import annotations

import math

import numpy as np
from dolfinx import fem
from mpi4py import MPI
from petsc4py import PETSc

from .errors import ReferenceSolveError
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
#: The share of the available memory a factorisation may be predicted to take (``direct_bytes``): a solve
#: factorises with MUMPS wherever its factor fits there, whatever its size, and takes GAMG_OPTIONS only
#: where it does not. Measured on a 2-core AMD EPYC with OpenBLAS, the direct path was the faster at every
#: size that fits: the slender beam's refined level (276 000 P2 dofs, StVK, 2 factorisations and 4 to 7
#: solves) 30 s against GAMG's 59; a linear Newmark run, one factorisation and a back-substitution a
#: step, is the direct path's best case (GAMG took 1081 s where the factor takes 48 s on the stiff beam).
#: (With Debian's reference BLAS, which the Makefile replaces, MUMPS was four times slower and GAMG won
#: above about 60 000 dofs, the fixed limit this replaced.)
DIRECT_MEMORY_SHARE = 0.5
#: A solve whose iterative solver failed is tried with a factorisation predicted to take up to this share
#: of the available memory (it did not fit in DIRECT_MEMORY_SHARE: the last resort before stronger multigrid).
FALLBACK_MEMORY_SHARE = 0.8


#: The prediction of a factor's size scales the factor measured at 39 000 P2 dofs (11.6 M entries) by
#: n^(4/3), nested dissection's fill in 3D, and doubles it for MUMPS's workspace: 2.5 GB at 276 000 dofs.
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


def direct_fits(n_dofs: int, share: float | None = None, comm=None) -> bool:
    """Whether a factorisation of ``n_dofs`` unknowns is predicted to fit in ``share`` (default
    DIRECT_MEMORY_SHARE) of the available memory; the same answer on every rank of ``comm`` (the least
    memory any of them sees), since all must choose one solver."""
    share = DIRECT_MEMORY_SHARE if share is None else share
    have = available_bytes()
    if comm is not None and comm.size > 1:
        have = comm.allreduce(have, op=MPI.MIN)
    return direct_bytes(n_dofs) <= share * have


def fallback_options(opts: dict, n_dofs: int, user: dict | None, comm=None) -> tuple[dict, str] | None:
    """What a solve whose iterative solver failed with ``opts`` tries next, and a phrase naming it: a
    direct factorisation where it is predicted to fit in FALLBACK_MEMORY_SHARE of the available memory,
    else GAMG_STRONGER. None when the user chose the solver (``--petsc-option pc_type=...``), the solve
    was direct, or it was already the stronger multigrid."""
    if (
        "pc_type" in (user or {})
        or opts.get("pc_type") != "gamg"
        or opts.get("ksp_max_it") == GAMG_STRONGER["ksp_max_it"]
    ):
        return None
    need, have = direct_bytes(n_dofs), available_bytes()
    if direct_fits(n_dofs, FALLBACK_MEMORY_SHARE, comm):
        direct = f"a direct factorisation (MUMPS, about {need / 1e9:.2g} GB of the {have / 1e9:.3g} GB available)"
        return {**DIRECT_OPTIONS, **(user or {})}, direct
    stronger = (
        f"stronger multigrid (a direct factor would take about {need / 1e9:.2g} GB of the {have / 1e9:.3g} available)"
    )
    return {**GAMG_STRONGER, "ksp_rtol": opts.get("ksp_rtol", GAMG_STRONGER["ksp_rtol"]), **(user or {})}, stronger


def peak_memory_bytes(comm) -> int:
    """The most memory the ranks of ``comm`` have held at once, summed over them, bytes (each process's
    peak resident set, ``getrusage``'s ru_maxrss, KiB on Linux): what a solve asked of the machine."""
    import resource

    return int(comm.allreduce(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024, op=MPI.SUM))


def solver_family(opts: dict) -> str:
    """Which kind of solve PETSc options ask for: "direct" (a factorisation) or "iterative" (a Krylov
    method). A reference records the kind its size chose before any fallback (``chosen``), and a cached
    one is read only where the same size would choose the same kind on this machine now: the answers
    differ by the iterative tolerance, and the free memory decides."""
    return "direct" if opts.get("ksp_type") == "preonly" or opts.get("pc_type") in ("lu", "cholesky") else "iterative"


def chosen_options(n_dofs: int, user: dict | None = None, linear: bool = False, comm=None) -> tuple[dict, dict]:
    """``solver_options`` and the record of the choice a solve keeps in its meta: its size, whether it is
    linear and the kind chosen before any fallback (``solver_family``)."""
    opts = solver_options(n_dofs, user, linear=linear, comm=comm)
    return opts, {"n_dofs": n_dofs, "linear": linear, "chosen": solver_family(opts)}


def solver_options(n_dofs: int, user: dict | None = None, linear: bool = False, comm=None) -> dict:
    """The PETSc options of a solve with ``n_dofs`` unknowns: MUMPS LDL^T wherever its factor is predicted
    to fit in DIRECT_MEMORY_SHARE of the available memory (``direct_fits``), GAMG elsewhere, and the
    user's options (``--petsc-option KEY=VALUE``) over the choice; a user's ``pc_type`` replaces the
    choice whole. ``linear``: the solve is the answer itself, not a Newton step, so GAMG's tolerance is
    1e-12. A linear problem therefore factorises once and back-substitutes (a linear Newmark run at
    every step) wherever the factor fits. ``comm``: the ranks that solve together (one choice for all)."""
    base = DIRECT_OPTIONS if direct_fits(n_dofs, comm=comm) else GAMG_OPTIONS
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


#: ``roundoff_floor``'s multiple of machine epsilon.
ROUNDOFF = 10.0


def roundoff_floor(modulus: float, length: float) -> float:
    """The residual (N) a stress-free rest state may show in floating point: ROUNDOFF eps times the
    largest P-wave modulus ``modulus`` (Pa) times the body's extent ``length`` (m) squared. A law whose
    rest stress cancels only to round-off (the stable neo-Hookean's k_mu - k_mu/4 + k_lam (1 - alpha)) leaves
    about eps k h^2 on each vertex; where nothing loads the body yet (a contact scene before its tool
    touches) every force scale is that round-off, which rtol times it can never reach (the liver under a
    sphere: Newton failed at every load down to 6e-5 of the travel). On the liver 5e-12 N, against
    rtol times its tool force, 1e-10 N: a loaded solve is untouched."""
    return ROUNDOFF * float(np.finfo(float).eps) * modulus * length * length


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
        modulus: float = 0.0,
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
        # an iterative solve (GAMG, where no factor fits) costs its iterations, not a factorisation: Newton
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
        # N: a free residual at or below it is round-off, accepted whatever the scale (``modulus``, Pa: the
        # largest P-wave modulus of the body, which a Newton on another residual leaves 0)
        self.floor = roundoff_floor(modulus, self.length)

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
        load = self._external_load()
        first = previous = previous_held = before = best = None
        fresh_step = False  # whether the last step was taken with the tangent at its own u
        start = self.factorisations
        n_dofs = self.A.getSize()[0]
        progress = Progress(f"reference: Newton ({n_dofs} dofs) iteration", None, self.comm.rank)
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
            gap = self._right_hand_side(undo)
            size = max(self._norms(u.vector)[1], self.length)
            scale = max(load, held, first, 1e-300)
            ok = np.isfinite(free) and np.isfinite(gap)
            out = {"iterations": it, "factorisations": self.factorisations - start, "scale": scale}
            if ok and free <= max(rtol * scale, self.floor) and gap <= 1e-12 * size:
                return {**out, "converged": True, "residual": free}
            if diverged:
                return {**out, "converged": False, "residual": free, "diverged": True}
            if not ok or self.factorisations - start >= max_it:
                break
            self._choose_tangent(free, previous, rtol * scale)
            fresh_step = self.at == "current"
            before, previous, previous_held = u.x.array.copy(), free, held
            reason = self._newton_step()
            if reason is not None:  # an inner solve or a factorisation that failed
                out["ksp_reason"] = reason
                out["factorisations"] = self.factorisations - start
                break
        return {**out, "converged": False, "residual": free}

    def _external_load(self) -> float:
        """The external load's norm (N) at the stress-free rest state: the residual's scale. In statics the
        load factor moves between calls, so F(0) is assembled each time; otherwise once."""
        if self.external_load is not None:
            return self.external_load
        u = self.u
        saved = u.x.array.copy()
        u.x.array[:] = 0.0
        load = math.hypot(*self._assemble_raw(self.L_external))
        u.x.array[:] = saved
        if self.L_external is not None:
            self.external_load = load
        return load

    def _right_hand_side(self, undo: bool) -> float:
        """The Newton right-hand side in b: the residual at u (assembled again after an undone step, raw
        holding where that step led), lifted by the constraints' gap; returns the gap's norm (m)."""
        u = self.u
        if undo:
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
        return gap

    def _choose_tangent(self, free: float, previous: float | None, target: float) -> None:
        """Keep the factorised tangent, or factorise at u (modified Newton's rule, ``solve``); an
        iterative solve rebuilds its preconditioner when its iterations grow and tightens its tolerance
        toward ``target`` (N)."""
        slow = previous is not None and free > previous / (SLOW_DYNAMIC if self.dynamic else SLOW)
        if self.iterative:
            tired = self.pc_first_its is not None and self.ksp.getIterationNumber() > 2 * self.pc_first_its + 10
            self._tangent(rebuild=not self.reuse or tired)  # the operator is current: only the
            # preconditioner can grow stale, and the linear iterations say when
            self.ksp.setTolerances(rtol=self._inner_rtol(free, previous, target))
        elif self.at != "current" and (self.at is None or not self.reuse or slow):
            self._factorise()

    def _newton_step(self) -> int | None:
        """u -= the Newton correction (more MUMPS workspace when a factorisation asks for it); the
        KSP's failure reason, or None."""
        u = self.u
        self._linear_solve()
        while self.ksp.getConvergedReason() < 0 and self._more_workspace():
            self._factorise()  # the tangent at the same u, factorised with the larger workspace
            self._linear_solve()
        if self.ksp.getConvergedReason() < 0:
            # the factor is unusable, and so is the analysis behind it (a tangent taken where the law has
            # no value, NaN from ln J at an inverted point, leaves MUMPS a pivot order drawn from NaNs,
            # which PETSc keeps for every later factorisation of the same pattern): the next solve, from
            # a state that was fine, analyses and factorises afresh there
            self.at = None
            self.ksp.getPC().reset()
            return int(self.ksp.getConvergedReason())
        self.linear_iterations += self.ksp.getIterationNumber()
        if self.iterative and self.pc_first_its is None:
            self.pc_first_its = self.ksp.getIterationNumber()
        u.vector.axpy(-1.0, self.du)
        # the constrained rows are identity rows whose solution is u - g: u now holds g, exactly (not
        # to the round-off of u - (u - g) or an inner tolerance), so the next lifting is not needed
        fem.petsc.set_bc(u.vector, self.bcs)
        u.x.scatter_forward()
        self.at = "older"  # the factorised tangent is now the one at an earlier u
        return None


def _mumps_info(ksp) -> str:
    """ ", MUMPS INFOG(1) = .., INFOG(2) = .." for a KSP whose preconditioner is MUMPS's factorisation,
    else ""."""
    factor = _factor_of(ksp)
    try:
        return f", MUMPS INFOG(1) = {factor.getMumpsInfog(1)}, INFOG(2) = {factor.getMumpsInfog(2)}"
    except (AttributeError, PETSc.Error):  # no factor, or not MUMPS's
        return ""
