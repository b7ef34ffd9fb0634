"""NVIDIA newton's tetrahedral soft bodies on an exported scene, on warp's device (``--device``: its CPU unless a
user with a GPU asks for ``cuda:0``).

    .venv-engines/bin/python adapters/newton_tets.py SCENE_DIR RESULT.npz --solver vbd --iterations 10

Three of newton's solvers, driven as its soft-body examples drive them (``ModelBuilder.add_soft_mesh``,
then ``solver.step(state_0, state_1, control, None, dt)`` with the states swapped, forces cleared and
the external ones set before each step):

- ``semi-implicit``: ``SolverSemiImplicit``, symplectic Euler on newton's stable Neo-Hookean force
  (Smith, de Goes & Kim, "Stable Neo-Hookean Flesh Simulation", 2018, with the log term). Its k_mu,
  k_lambda are not the Lame constants: matching its linearisation at rest (Smith et al., section 3.4)
  gives k_mu = 4/3 mu, k_lambda = lambda + 5/6 mu, which this adapter passes;
- ``vbd``: ``SolverVBD`` (Chen et al., "Vertex Block Descent", 2024): implicit Euler by per-vertex Newton
  sweeps, ``iterations`` per step, on the stable Neo-Hookean energy without the log term, which takes the
  Lame constants themselves (newton converts them, particle_vbd_kernels);
- ``xpbd``: ``SolverXPBD`` (Macklin et al. 2016): two compliant constraints per tetrahedron,
  C = tr(F^T F) - 3 with compliance 1/(V mu) and C = det F - 1 with 1/(V lambda). Its energy,
  mu/2 (tr(F^T F) - 3)^2 V, has no shear stiffness at small strain; the Lame constants are passed as its
  docstring asks, and the judge measures what follows.

Every law of the scene (linear, StVK) is mapped to that solver's Neo-Hookean; the result says which. A
dynamic scene's mass-proportional damping is applied after every step (v / (1 + alpha dt), implicit);
its stiffness-proportional damping has no exact counterpart in newton's per-tetrahedron k_damp and is
left out, which the result's law says.
Held vertices are made inactive (newton keeps them where they are); vertices held in some components only
are put back in those after every step. The scene's gravity and loads come as the exported nodal forces
(newton's own gravity is off). The engine runs in float32, as newton does.

A rigid tool is newton's own particle-shape contact, as its examples drive it: a kinematic body
(``add_body(is_kinematic=True)``) with the tool's shape, moved along its travel (``body_q``, ``body_qd``),
a ``CollisionPipeline`` that finds the vertices within ``soft_contact_gap`` of it before every step, and the
solver's penalty ke times the penetration on each (frictionless: mu, kd and kf 0). ke is one number in
newton; the adapter passes the penalty the truth and the built-in models use, gamma E A_i / h_i at a
vertex, as gamma E h with h the mean boundary edge (``contact_stiffness``). The tool's force is the
semi-implicit solver's contact force on the vertices at the present state (``eval_particle_body_contact_forces``), the
penalty VBD integrates too; XPBD projects its contacts and states no force.
"""

from __future__ import annotations

import numpy as np

from exported import RELAX_FRACTION, AdapterError, Exported, Stepper, drive, main, warp_device

SOLVERS = ("semi-implicit", "vbd", "xpbd")

#: The contact penalty's gamma: the truth's and the built-in models' (realtime.contact.GAMMA).
GAMMA = 100.0


def boundary_edge(scene: Exported) -> float:
    """The mean edge length of the body's boundary triangles, m."""
    faces = np.sort(scene.tets[:, [[0, 1, 2], [0, 1, 3], [0, 2, 3], [1, 2, 3]]].reshape(-1, 3), axis=1)
    uniq, count = np.unique(faces, axis=0, return_counts=True)
    tri = scene.points[uniq[count == 1]]
    edges = np.linalg.norm(tri - np.roll(tri, 1, axis=1), axis=2)
    return float(edges.mean())


def contact_stiffness(scene: Exported) -> float:
    """newton's one ke, N/m: GAMMA E h, the built-in models' gamma E A_i / h_i with A_i / h_i about h."""
    return GAMMA * max(m["young_pa"] for m in scene.spec["materials"]) * boundary_edge(scene)


def _quat_z_to(wp, d) -> object:
    """The rotation taking the z axis to the direction ``d`` (3,)."""
    d = np.asarray(d, dtype=float) / np.linalg.norm(d)
    axis = np.cross([0.0, 0.0, 1.0], d)
    s, c = float(np.linalg.norm(axis)), float(d[2])
    if s < 1e-12:
        return wp.quat_identity() if c > 0 else wp.quat_from_axis_angle(wp.vec3(1.0, 0.0, 0.0), float(np.pi))
    return wp.quat_from_axis_angle(wp.vec3(*(axis / s)), float(np.arctan2(s, c)))


def add_tools(builder, newton, wp, scene: Exported, origin: np.ndarray, ke: float) -> list:
    """Each rigid tool as a kinematic body with its shape, frictionless; returns each one's (body index,
    place (3,) m about ``origin`` at t = 0, rotation)."""
    if len(scene.rigid) > 1:
        raise AdapterError("newton's adapter moves one rigid tool; this scene has several")
    cfg = newton.ModelBuilder.ShapeConfig(ke=ke, kd=0.0, kf=0.0, mu=0.0)
    out = []
    for tool in scene.rigid:
        center = np.asarray(tool["center_m"], dtype=float) - origin
        if tool["shape"] == "capsule":
            axis = np.asarray(tool["end_m"], dtype=float) - np.asarray(tool["center_m"], dtype=float)
            place, rot = center + 0.5 * axis, _quat_z_to(wp, axis)
        elif tool["shape"] == "plane":
            place, rot = center, _quat_z_to(wp, tool["normal"])
        else:
            place, rot = center, wp.quat_identity()
        body = builder.add_body(xform=wp.transform(wp.vec3(*place), rot), is_kinematic=True)
        if tool["shape"] == "sphere":
            builder.add_shape_sphere(body, radius=tool["radius_m"], cfg=cfg)
        elif tool["shape"] == "capsule":
            builder.add_shape_capsule(
                body, radius=tool["radius_m"], half_height=0.5 * float(np.linalg.norm(axis)), cfg=cfg
            )
        else:
            builder.add_shape_plane(body=body, width=0.0, length=0.0, cfg=cfg)
        out.append((body, place, rot))
    return out


class NewtonStepper(Stepper):
    """newton's model and solver behind the driver's calls."""

    epsilon = float(np.finfo(np.float32).eps)

    def __init__(self, scene: Exported, solver: str, iterations: int, substeps: int, device):
        import newton
        import warp as wp

        self.wp, self.substeps, self.kind = wp, substeps, solver
        # the body about its centre: newton holds positions in float32, whose unit grows with the
        # coordinate; the vertices are given and read back about this origin (float64 on our side)
        self.origin = 0.5 * (scene.points.min(axis=0) + scene.points.max(axis=0))
        lam, mu, rho = scene.lame()
        if len(set(rho.tolist())) > 1:
            raise AdapterError("newton's add_soft_mesh takes one density per body; this scene has several")
        k_mu, k_lambda = (4.0 / 3.0 * mu, lam + 5.0 / 6.0 * mu) if solver == "semi-implicit" else (mu, lam)
        builder = newton.ModelBuilder(gravity=(0.0, 0.0, 0.0))
        builder.add_soft_mesh(
            pos=(0.0, 0.0, 0.0),
            rot=wp.quat_identity(),
            scale=1.0,
            vel=(0.0, 0.0, 0.0),
            vertices=(scene.points - self.origin).tolist(),
            indices=scene.tets.ravel().tolist(),
            density=float(rho[0]),
            k_mu=k_mu,
            k_lambda=k_lambda,
            k_damp=0.0,
            add_surface_mesh_edges=False,
            particle_radius=0.0,  # no contact acts in a scene: none between the body's own vertices
        )
        fixed = np.flatnonzero(scene.held().all(axis=1))
        flags = np.asarray(builder.particle_flags, dtype=np.int32)
        flags[fixed] &= ~int(newton.ParticleFlags.ACTIVE)
        builder.particle_flags = flags.tolist()
        for i in fixed:
            builder.particle_mass[i] = 0.0
        self.partial = scene.held() & ~scene.held().all(axis=1, keepdims=True)
        self.ke = contact_stiffness(scene) if scene.rigid else 0.0
        self.tools = add_tools(builder, newton, wp, scene, self.origin, self.ke)
        if solver == "vbd":
            builder.color()
        model = builder.finalize(device=device)
        if self.tools:
            model.soft_contact_ke = self.ke  # frictionless and undamped, as the truth's contact
            model.soft_contact_kd = model.soft_contact_kf = model.soft_contact_mu = 0.0
            self.pipeline = newton.CollisionPipeline(model, soft_contact_gap=boundary_edge(scene))
            self.contacts = self.pipeline.contacts()
        if solver == "semi-implicit":
            self.solver = newton.solvers.SolverSemiImplicit(model, enable_tri_contact=False)
        elif solver == "vbd":
            self.solver = newton.solvers.SolverVBD(model, iterations=iterations, particle_enable_tile_solve=False)
        else:
            self.solver = newton.solvers.SolverXPBD(model, iterations=iterations)
        self.model, self.control = model, model.control()
        self.states = [model.state(), model.state()]
        self.force = scene.external_force.astype(np.float32)
        self.alpha = scene.damping[0]
        self.mass = model.particle_mass.numpy().astype(float)
        self.rest = scene.points

    def step(self, dt: float) -> None:
        h = dt / self.substeps
        for _ in range(self.substeps):
            s0, s1 = self.states
            s0.clear_forces()
            s0.particle_f.assign(self.force)
            contacts = None
            if self.tools:
                self.wp.copy(s1.body_q, s0.body_q)
                self.wp.copy(s1.body_qd, s0.body_qd)
                self.pipeline.collide(s0, self.contacts)
                contacts = self.contacts
            self.solver.step(s0, s1, self.control, contacts, h)
            self.states.reverse()
            if self.alpha:  # the scene's mass-proportional damping, implicit: v / (1 + alpha h)
                self.set_velocities(self.velocities() / (1.0 + self.alpha * h))
        if self.partial.any():  # components held alone: put back after the step
            x, v = self.positions(), self.velocities()
            x[self.partial], v[self.partial] = self._held_x[self.partial], 0.0
            self.set_positions(x)
            self.set_velocities(v)

    def internal_force(self) -> np.ndarray | None:
        """The semi-implicit solver's own tetrahedral force (``eval_tetrahedra_forces``, the law it steps
        with) at the present state; None for VBD and XPBD, whose laws that kernel is not."""
        if self.kind != "semi-implicit":
            return None
        from newton._src.solvers.semi_implicit.solver_semi_implicit import eval_tetrahedra_forces

        state = self.states[0]
        f = self.wp.zeros_like(state.particle_f)
        eval_tetrahedra_forces(self.model, state, self.control, f)
        return f.numpy().astype(float)

    def set_rigid(self, offset: np.ndarray, velocity: np.ndarray) -> None:
        """The kinematic bodies' place and velocity (newton's spatial velocity: linear, then angular)."""
        wp = self.wp
        q = [wp.transform(wp.vec3(*(place + offset[k])), rot) for k, (_, place, rot) in enumerate(self.tools)]
        qd = [wp.spatial_vector(*velocity[k], 0.0, 0.0, 0.0) for k in range(len(self.tools))]
        for state in self.states:
            bq, bqd = state.body_q.numpy(), state.body_qd.numpy()
            for k, (body, _, _) in enumerate(self.tools):
                bq[body], bqd[body] = np.array(q[k]), np.array(qd[k])
            state.body_q.assign(bq)
            state.body_qd.assign(bqd)

    def rigid_force(self) -> np.ndarray:
        """The tool's force on the body: newton's particle-shape contact force on the vertices
        (``eval_particle_body_contact_forces``, the semi-implicit solver's; VBD integrates the same penalty)
        at the present state, summed (its damping kd is 0: the velocities do not enter). XPBD projects its
        contacts and has no such force: NaN, unknown."""
        if self.kind == "xpbd":
            return np.full((len(self.tools), 3), np.nan)
        from newton._src.solvers.semi_implicit.kernels_contact import eval_particle_body_contact_forces

        state = self.states[0]
        self.pipeline.collide(state, self.contacts)
        f = self.wp.zeros_like(state.particle_f)
        body_f = self.wp.zeros_like(state.body_f)
        eval_particle_body_contact_forces(self.model, state, self.contacts, f, body_f)
        return f.numpy().astype(float).sum(axis=0)[None]

    def positions(self) -> np.ndarray:
        return self.states[0].particle_q.numpy().astype(float) + self.origin

    def set_positions(self, x: np.ndarray) -> None:
        self._held_x = x
        self.states[0].particle_q.assign((x - self.origin).astype(np.float32))

    def velocities(self) -> np.ndarray:
        return self.states[0].particle_qd.numpy().astype(float)

    def set_velocities(self, v: np.ndarray) -> None:
        self.states[0].particle_qd.assign(v.astype(np.float32))

    def masses(self) -> np.ndarray:
        return self.mass


def stable_guess(scene: Exported, solver: str) -> float:
    """A time step, s: for the semi-implicit solver, RELAX_FRACTION of the explicit wave step
    (``Exported.wave_step``) with the Neo-Hookean constants it runs with, or of the contact's explicit step
    where that is smaller; for the implicit ones (VBD, XPBD), 1 ms, the step newton's
    examples take at 60 Hz with substeps."""
    if solver != "semi-implicit":
        return 1e-3
    lam, mu, _ = scene.lame()
    dt = scene.wave_step(lam + 5.0 / 6.0 * mu + 2.0 * 4.0 / 3.0 * mu)
    if scene.rigid:  # the explicit contact spring on the lightest vertex: 2 sqrt(m / ke)
        m = scene.lumped_masses()
        dt = min(dt, 2.0 * float(np.sqrt(m[m > 0].min() / contact_stiffness(scene))))
    return RELAX_FRACTION * dt


def run(scene: Exported, args, progress):
    import warp as wp

    wp.config.quiet = True
    import newton

    device = warp_device(wp, args.device)
    engine = NewtonStepper(scene, args.solver, args.iterations, args.substeps, device)
    dt = args.dt if args.dt else stable_guess(scene, args.solver)
    progress(f"{len(scene.points)} vertices, {len(scene.tets)} tetrahedra, dt = {dt:.3g} s (warp's {device.alias})")
    law = {
        "semi-implicit": "stable Neo-Hookean with log term (Smith et al. 2018), k_mu = 4/3 mu, k_lambda = lambda + 5/6 mu",
        "vbd": "stable Neo-Hookean (Smith et al. 2018) with the Lame constants",
        "xpbd": "XPBD constraints tr(F^T F) - 3 and det F - 1, compliances 1/(V mu), 1/(V lambda)",
    }[args.solver]
    if scene.damping[1]:
        law += "; the scene's stiffness-proportional damping left out"
    result = drive(engine, scene, args, dt, progress)
    result["iterations"] = args.iterations if args.solver != "semi-implicit" else None
    result["substeps"], result["device"] = args.substeps, device.alias
    return result, law, f"newton {newton.__version__} {args.solver} (warp {device.alias}, float32)"


if __name__ == "__main__":
    raise SystemExit(main(run, "newton's tetrahedral soft bodies on an exported scene", SOLVERS))
