"""Newmark time integration of an elasticity problem (a mixin of ``reference.fem.ElasticityProblem``):
one factorisation and back-substitutions for the linear law, Newton at every step otherwise.
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import numpy as np
import ufl
from dolfinx import fem
from petsc4py import PETSc

from .errors import ReferenceSolveError
from .progress import Heartbeat, Progress
from .solver import Newton, _mumps_info, chosen_options, configure, grow_ksp_workspace

#: The relative residual to which the initial acceleration's mass solve is taken: round-off for a system
#: whose scaled condition number is in the tens.
INITIAL_ACCELERATION_RTOL = 1e-13


@dataclass(frozen=True)
class Trajectory:
    """What ``solve_dynamic`` returns: the output times (T,) s from t = 0, the displacements (T, K, 3) m
    at the requested points, the tools' reactions (T, 3) N, and ``info`` (the solver, its steps,
    iterations, factorisations and PETSc options)."""

    times: np.ndarray
    values: np.ndarray
    reactions: np.ndarray
    info: dict


class _LinearNewmark:
    """A linear Newmark step: the effective matrix assembled and factored once, a back-substitution for
    each step (more MUMPS workspace when the factorisation asks for it)."""

    def __init__(self, ep, residual, J, opts, modes):
        u, zero = ep.u, fem.Function(ep.V)
        self.ep, self.opts = ep, opts
        self.a_form = fem.form(ufl.replace(J, {u: zero}))
        self.A = fem.petsc.assemble_matrix(self.a_form, bcs=ep.bcs)
        self.A.assemble()
        if modes is not None:
            self.A.setNearNullSpace(modes)
        self.ksp = PETSc.KSP().create(ep.comm)
        self.ksp.setOperators(self.A)
        self.ksp.setOptionsPrefix(f"tb_dyn_{id(ep)}_")
        configure(self.ksp, opts)
        self.L_form = fem.form(-ufl.replace(residual, {u: zero}))
        self.b = fem.petsc.create_vector(self.L_form)
        self.factorisations = 1

    def step(self, step: int, t: float) -> int:
        """Solve the step at time t into u; returns its iterations (1)."""
        ep, b, ksp, u = self.ep, self.b, self.ksp, self.ep.u
        with b.localForm() as loc:
            loc.set(0.0)
        fem.petsc.assemble_vector(b, self.L_form)
        fem.petsc.apply_lifting(b, [self.a_form], bcs=[ep.bcs])
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem.petsc.set_bc(b, ep.bcs)
        if step == 1:  # the factorisation, in the first solve
            with Heartbeat(f"reference: factorising the Newmark matrix ({ep.n_dofs} dofs)", ep.comm.rank):
                ksp.solve(b, u.vector)
        else:
            ksp.solve(b, u.vector)
        while ksp.getConvergedReason() < 0 and grow_ksp_workspace(ksp, ep._log):
            self.A.zeroEntries()  # the same operator in a new state: the preconditioner factorises it again
            fem.petsc.assemble_matrix(self.A, self.a_form, bcs=ep.bcs)
            self.A.assemble()
            ksp.solve(b, u.vector)
        if ksp.getConvergedReason() < 0:
            raise ReferenceSolveError(
                f"reference: Newmark's linear solve failed at t = {t:.4g} s (PETSc reason "
                f"{ksp.getConvergedReason()}{_mumps_info(ksp)}, options {self.opts}); try --petsc-option "
                "pc_type=lu"
            )
        u.x.scatter_forward()
        return 1

    def progress(self, t: float, end: float, iterations: int) -> str:
        return f", t = {t:.4g} s of {end:.4g}; one factorisation, back-substitutions"


class _NewtonNewmark:
    """A non-linear Newmark step: Newton on the step's residual from the last state."""

    def __init__(self, solver: Newton, u_old, rtol: float, dt: float, n_steps: int):
        self.solver, self.u_old, self.rtol, self.dt, self.n_steps = solver, u_old, rtol, dt, n_steps

    @property
    def factorisations(self) -> int:
        return self.solver.factorisations

    def step(self, step: int, t: float) -> int:
        u = self.solver.u
        # predictor: the last state (extrapolating with the last acceleration carries the mesh's
        # highest modes, which average-acceleration Newmark does not damp: Newton failed from it)
        u.x.array[:] = self.u_old.x.array
        res = self.solver.solve(self.rtol, 25)
        if not res["converged"] or not np.all(np.isfinite(u.x.array)):
            raise ReferenceSolveError(
                f"reference: Newmark's Newton did not converge at t = {t:.4g} s (step {step} of "
                f"{self.n_steps}, dt = {self.dt:.3g} s): a smaller output_every (it sets dt), a smaller load or "
                "a finer mesh may help"
            )
        return int(res["iterations"])

    def progress(self, t: float, end: float, iterations: int) -> str:
        return f", t = {t:.4g} s: {iterations} Newton iterations, {self.solver.factorisations} factorisations"


class DynamicSolves:
    """The dynamic solve of a ``ProblemForms``."""

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
    ) -> Trajectory:
        """Newmark time integration from rest (average acceleration by default: beta = 1/4, gamma = 1/2,
        second order, no numerical damping), consistent mass, Rayleigh damping C = a M + b K0 (K0 the
        stiffness at rest, so the damping is the same linear operator in every law), tools ramped as
        the scene says, loads applied at t = 0.

        Linear law without penalty: the effective matrix M/(beta dt^2) + C gamma/(beta dt) + K is
        assembled and factored once. Otherwise Newton on the same residual at every step.
        ``before_loop``: called when the set-up is done and the time loop begins (a heartbeat's stop).
        Returns the Trajectory at ``points``, the first output at t = 0; ``self.velocity`` and
        ``self.acceleration`` hold the final state. The tools' dofs move with their exact velocity and
        acceleration (``Displacement.kinematics``). Reactions are quasi-static, as the engine's are: the
        tools' force on the body's stiffness and loads, without the inertia of the region they drive.
        """
        beta, gamma = newmark
        V = self.V
        old = fem.Function(V), fem.Function(V), fem.Function(V)  # u, v, a at the last step
        coefficients = (1.0 / (beta * dt * dt), 1.0 / (beta * dt), (1.0 - 2.0 * beta) / (2.0 * beta), dt, gamma)
        residual = self._newmark_residual(old, coefficients, rayleigh)
        opts, record = chosen_options(self.n_dofs, petsc_options, linear=self.linear, comm=self.comm)
        modes = self.rigid_body_modes() if opts.get("pc_type") == "gamg" else None
        times, values, reactions = [0.0], [self.evaluate(points)], [self.reaction()]
        self._newmark_start(old)
        J = ufl.derivative(residual, self.u, ufl.TrialFunction(V))
        n_steps = int(round(end / dt))
        every = max(int(round(output_every / dt)), 1)
        t0 = time.perf_counter()
        if self.linear:
            stepper = _LinearNewmark(self, residual, J, opts, modes)
        else:
            part = self._newmark_linear_part(*old, coefficients, rayleigh)
            newton = Newton(
                self.comm, self.residual, self.u, self.bcs, J, opts,
                near_nullspace=modes, dynamic=True, external=self.residual, linear_part=part,
            )  # fmt: skip
            stepper = _NewtonNewmark(newton, old[0], newton_rtol, dt, n_steps)
        if before_loop is not None:
            before_loop()
        iterations = 0
        progress = Progress("reference: Newmark step", n_steps, self.comm.rank)
        for step in range(1, n_steps + 1):
            t = step * dt
            self.set_tool_fraction_at(t)
            if self.linear:
                progress.tick(step - 1, stepper.progress(t, end, iterations))
            iterations += stepper.step(step, t)
            if not self.linear:
                progress.tick(step, stepper.progress(t, end, iterations))
            self._newmark_update(old, coefficients, t)
            if step % every == 0 or step == n_steps:
                times.append(t)
                values.append(self.evaluate(points))
                reactions.append(self.reaction())
        self.timings["solve_s"] = time.perf_counter() - t0
        self.velocity, self.acceleration = old[1], old[2]  # the state at the end, m/s and m/s^2
        info = {
            "solver": "newmark",
            **record,
            "beta": beta,
            "gamma": gamma,
            "dt": dt,
            "steps": n_steps,
            "iterations": iterations,
            "factorisations": stepper.factorisations,
            "petsc_options": opts,
            "rayleigh": list(rayleigh),
        }
        return Trajectory(np.array(times), np.array(values), np.array(reactions), info)

    def _newmark_residual(self, old, coefficients, rayleigh):
        """The static residual plus M a + C v at the step's acceleration a and velocity v of the iterate u
        (a = c1 (u - u_old) - c2 v_old - c3 a_old, v = v_old + dt ((1 - gamma) a_old + gamma a))."""
        u_old, v_old, a_old = old
        c1, c2, c3, dt, gamma = coefficients
        a_m, b_k = rayleigh
        u, w = self.u, ufl.TestFunction(self.V)
        accel = c1 * (u - u_old) - c2 * v_old - c3 * a_old
        veloc = v_old + dt * ((1.0 - gamma) * a_old + gamma * accel)
        residual = self.residual + self.mass_weighted(ufl.inner(accel, w))
        if a_m:
            residual += a_m * self.mass_weighted(ufl.inner(veloc, w))
        if b_k:  # the rest stiffness K0 as a form: inner(C : eps(veloc), eps(w)), each material's C
            residual += b_k * self.internal_work(veloc, w, law="linear")
        return residual

    def _newmark_start(self, old) -> None:
        """The state at t = 0: the tools where their ramps start, the initial acceleration from
        M a0 = f_ext - f_int(0) (the tools' accelerations zero at rest), the tools' own motion.

        M is the consistent mass, whose condition number with its diagonal scaled away is bounded
        independently of h: conjugate gradients with Jacobi solve it in tens of iterations, where the
        Newmark matrix's solver options factorised it (as long as the Newmark factorisation itself, 15 s
        of the stiff beam's refined level at 121 000 P2 dofs). With no load at t = 0 (tools ramped from
        rest, no gravity or traction) the right-hand side is zero and so is a0: nothing is solved."""
        _, v_old, a_old = old
        V = self.V
        w = ufl.TestFunction(V)
        self.set_tool_fraction_at(0.0)
        bcs = self._homogeneous_bcs()
        rhs = fem.form(-ufl.replace(self.residual, {self.u: fem.Function(V)}))
        b = fem.petsc.assemble_vector(rhs)
        b.ghostUpdate(addv=PETSc.InsertMode.ADD, mode=PETSc.ScatterMode.REVERSE)
        fem.petsc.set_bc(b, bcs)
        a_old.x.array[:] = 0.0
        if b.norm() > 0.0:
            mass = fem.form(self.mass_weighted(ufl.inner(ufl.TrialFunction(V), w)))
            M = fem.petsc.assemble_matrix(mass, bcs=bcs)
            M.assemble()
            ksp = PETSc.KSP().create(self.comm)
            ksp.setOperators(M)
            ksp.setType("cg")
            ksp.getPC().setType("jacobi")
            ksp.setTolerances(rtol=INITIAL_ACCELERATION_RTOL, atol=0.0, max_it=2000)
            ksp.solve(b, a_old.vector)
            if ksp.getConvergedReason() < 0:
                raise ReferenceSolveError(
                    f"reference: the initial acceleration's mass solve failed (PETSc reason {ksp.getConvergedReason()} "
                    f"after {ksp.getIterationNumber()} conjugate-gradient iterations)"
                )
            a_old.x.scatter_forward()
            ksp.destroy()
            M.destroy()
        b.destroy()
        for tool, c, d, x in self._tool_points:  # the tools' own motion at t = 0
            _, vel, acc = tool.kinematics(x, 0.0)
            v_old.x.array[d] = vel[:, c]
            a_old.x.array[d] = acc[:, c]

    def _newmark_update(self, old, coefficients, t: float) -> None:
        """After a step's solve: its acceleration and velocity, and the new state becomes the old one."""
        u_old, v_old, a_old = old
        c1, c2, c3, dt, gamma = coefficients
        u = self.u
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
