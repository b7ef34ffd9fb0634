"""Static solves of an elasticity problem (a mixin of ``reference.fem.ElasticityProblem``): one linear
solve for the linear law without penalty, else Newton with load stepping and step halving.
"""

from __future__ import annotations

import math
import time

import numpy as np
import ufl
from dolfinx import fem
from dolfinx.fem.petsc import LinearProblem
from mpi4py import MPI

from .contact import TIGHTEN
from .errors import ReferenceSolveError
from .solver import (
    DIVERGED,
    Newton,
    _mumps_info,
    _watched,
    chosen_options,
    fallback_options,
    grow_ksp_workspace,
    peak_memory_bytes,
)


class StaticSolves:
    """The static solves of a ``ProblemForms``."""

    def solve_linear(self, petsc_options=None) -> dict:
        """One linear solve (law = linear): K u = f with the Dirichlet conditions."""
        if not self.linear:
            raise ValueError("solve_linear needs law = linear and no volume penalty; use solve_newton")
        opts, record = chosen_options(self.n_dofs, petsc_options, linear=True, comm=self.comm)
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
        while reason < 0 and (fallback := fallback_options(opts, self.n_dofs, petsc_options, self.comm)) is not None:
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
        memory = peak_memory_bytes(self.comm)
        out = {"solver": "linear", **record, "petsc_options": opts, "iterations": 1, "peak_memory_bytes": memory}
        return {**out, "linear_iterations": problem.solver.getIterationNumber(), "min_det_F": self.min_det_F()}

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
        opts, record = chosen_options(self.n_dofs, petsc_options, comm=self.comm)  # record: before any fallback
        solver = self._newton(opts)
        t0 = time.perf_counter()
        done, inc = 0.0, 1.0 / steps
        history, curve = [], []  # curve: the rigid tools' force and area at each of their stations
        stations = self.contact.stations() if self.contact is not None else ()
        start_at_full_load = start_at_full_load and not stations  # a curve is the path from rest
        if start_at_full_load:
            done = self._full_load_from_coarse(solver, rtol, max_it, history)
        while done < 1.0 - 1e-14:
            target = min(1.0, done + inc, *(s for s in stations if s > done + 1e-12))
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
                step = {"load": target, "iterations": int(its), "factorisations": res["factorisations"]}
                history.append({**step, "min_det_F": jmin})
                said = f"{int(its)} Newton iterations, {step['factorisations']} factorisations ({elapsed:.1f} s)"
                self._log(f"{self._said()} load {target:.4g}: {said}")
                done = target
                inc = min(2.0 * inc, 1.0)
                curve += [{"fraction": target, **self.contact.read(self.u)}] if target in stations else []
                continue
            self.u.x.array[:] = saved
            inc *= 0.5
            self._log(
                f"reference: load {target:.4g}: {_failure(res, ok, jmin, solver)}, load increment halved to {inc:.3g}"
            )
            if inc < min_increment or elapsed > time_limit:
                why = f"increments down to {inc:.1e}" if inc < min_increment else f"{elapsed:.0f} s, the limit"
                raise self._no_equilibrium(done, why, steps)
        contact = {**self._tighten(solver, rtol, max_it), "contact_curve": curve} if self.contact is not None else {}
        self.timings["solve_s"] = time.perf_counter() - t0
        return {
            **contact,
            "solver": "newton",
            **record,
            "petsc_options": opts,
            "load_steps": history,
            "iterations": sum(h["iterations"] for h in history),
            "factorisations": solver.factorisations,  # failed load steps' included
            "undone_steps": solver.undone,
            "linear_iterations": solver.linear_iterations,
            "peak_memory_bytes": peak_memory_bytes(self.comm),
            "rtol": rtol,
            "min_det_F": history[-1]["min_det_F"],
        }

    def _newton(self, opts: dict) -> Newton:
        """The static residual's Newton with these PETSc options (GAMG given the rigid-body modes)."""
        jacobian = ufl.derivative(self.residual, self.u, ufl.TrialFunction(self.V))
        modes = self.rigid_body_modes() if opts.get("pc_type") == "gamg" else None
        modulus = max(m.lam + 2.0 * m.mu for m, _ in self.parts)
        return Newton(self.comm, self.residual, self.u, self.bcs, jacobian, opts, near_nullspace=modes, modulus=modulus)

    def _tighten(self, solver: Newton, rtol: float, max_it: int) -> dict:
        """The rigid tools' penalty made TIGHTEN and TIGHTEN^2 times stiffer, Newton solved again from the
        last answer each time (reference.contact): the answer is the last one, and its penalty error is
        read from the last two, the error falling as 1/gamma. Returns {"contact": each solve's force (T, 3)
        N, area (T,) m^2 and gamma, "penalty_error": {"force": (T,) N, "area": (T,) m^2, "u": m, the
        largest nodal change over TIGHTEN - 1}, "penalty_order": the order in 1/gamma the three forces
        show (1 expected; None when the first two agree to round-off)}."""
        reads, answers = [self.contact.read(self.u)], [self.u.x.array.copy()]
        for _ in range(2):
            its = self._raise_penalty(solver, float(self.contact.gamma.value) * TIGHTEN, rtol, max_it)
            reads.append(self.contact.read(self.u))
            answers.append(self.u.x.array.copy())
            self._log(f"{self._said()} contact penalty x{TIGHTEN ** len(answers[1:]):g}: {its} Newton iterations")
        f = [np.linalg.norm(r["force"], axis=1) for r in reads]
        first, last = np.abs(f[1] - f[0]), np.abs(f[2] - f[1])
        order = (
            float(np.log(first.max() / last.max()) / np.log(TIGHTEN)) if last.max() > 0 and first.max() > 0 else None
        )
        du = self.comm.allreduce(float(np.abs(answers[2] - answers[1]).max(initial=0.0)), op=MPI.MAX)
        error = {
            "force": (last / (TIGHTEN - 1.0)).tolist(),
            "area": (np.abs(np.subtract(reads[2]["area"], reads[1]["area"])) / (TIGHTEN - 1.0)).tolist(),
            "u": du / (TIGHTEN - 1.0),
        }
        return {"contact": reads, "penalty_error": error, "penalty_order": order}

    def _raise_penalty(self, solver: Newton, target: float, rtol: float, max_it: int) -> int:
        """gamma raised to ``target`` by Newton from the present answer, in geometric steps halved (in
        their logarithm) when Newton fails: a node just outside the contact enters it with the stiffer
        penalty and a whole step can overshoot, as a load step can. Returns the Newton iterations."""
        its, step = 0, target / float(self.contact.gamma.value)
        while float(self.contact.gamma.value) < target * (1.0 - 1e-12):
            saved, before = self.u.x.array.copy(), float(self.contact.gamma.value)
            self.contact.gamma.value = min(before * step, target)
            res = solver.solve(rtol, max_it)
            its += res["iterations"]
            if res["converged"] and np.all(np.isfinite(self.u.x.array)):
                continue
            self.u.x.array[:], self.contact.gamma.value = saved, before
            step = math.sqrt(step)
            if step < 1.0 + 1e-3:
                raise ReferenceSolveError(
                    f"reference: the contact penalty found no equilibrium beyond gamma = {before:g} on its way to "
                    f"{target:g} (P{self.degree}, {self.n_dofs} dofs): a finer mesh under the tool may help"
                )
        return its

    def _said(self) -> str:
        """How a load step's line starts: "reference: P2, 58605 dofs,"."""
        return f"reference: P{self.degree}, {self.n_dofs} dofs,"

    def _no_equilibrium(self, done: float, why: str, steps: int) -> ReferenceSolveError:
        """The error of a Newton solve that gave up at load fraction ``done`` (``why``)."""
        return ReferenceSolveError(
            f"reference: Newton found no equilibrium without inverted elements beyond load fraction "
            f"{done:.4g} ({why}; law = "
            f"{self.law}, P{self.degree}, refine {self.refine}, {self.n_dofs} dofs): the load may "
            f"be too large for this mesh and law, or elements invert; try a smaller load, a finer mesh, "
            f"law = linear, or more load steps (--load-steps {max(4 * steps, 10)})"
        )

    def _full_load_from_coarse(self, solver: Newton, rtol: float, max_it: int, history: list) -> float:
        """Newton at the full load from the u a coarser level left: the load fraction reached (1, its
        step recorded in ``history``), or 0 with u back at rest when it fails there."""
        self.load_factor.value = 1.0
        self.set_tool_fraction(1.0)
        res = solver.solve(rtol, max_it)
        ok = res["converged"] and bool(np.all(np.isfinite(self.u.x.array)))
        jmin = self.min_det_F() if ok else float("nan")
        if ok and jmin > 0.0:
            step = {"load": 1.0, "iterations": res["iterations"], "factorisations": res["factorisations"]}
            history.append({**step, "min_det_F": jmin, "nested": True})
            self._log(
                f"{self._said()} full load from the coarser solution: {res['iterations']} Newton iterations, "
                f"{res['factorisations']} factorisations"
            )
            return 1.0
        self._log("reference: Newton from the coarser solution failed; load stepping from rest")
        self.u.x.array[:] = 0.0
        return 0.0

    def solve(self, **kwargs) -> dict:
        """solve_linear for the linear law without penalty, solve_newton otherwise."""
        if self.linear:
            return self.solve_linear(petsc_options=kwargs.get("petsc_options"))
        return self.solve_newton(**kwargs)


def _failure(res: dict, ok: bool, jmin: float, solver: Newton) -> str:
    """What went wrong in a failed load step, for its line on stderr."""
    if ok:
        return f"Newton found inverted elements (min det F = {jmin:.3g})"
    if res.get("diverged"):
        return f"Newton diverged after {res['factorisations']} factorisations (residual {DIVERGED:.0e} x its best)"
    if "ksp_reason" in res:
        return f"the linear solver failed (PETSc KSP reason {res['ksp_reason']}{_mumps_info(solver.ksp)})"
    return f"Newton failed ({res['factorisations']} factorisations)"
