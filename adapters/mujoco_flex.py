"""MuJoCo's 3D flex with its elasticity on an exported scene.

    .venv-engines/bin/python adapters/mujoco_flex.py SCENE_DIR RESULT.npz --solver implicitfast --dt 1e-4

The scene becomes an MJCF model as MuJoCo's own flex models are written (XML reference, "deformable/flex"
and "flex/elasticity"): one body per vertex, a ``<flex dim="3">`` over the scene's tetrahedra with
``<elasticity young=... poisson=...>``, which MuJoCo documents as Saint Venant-Kirchhoff on piecewise
linear elements (energy density mu tr(E^2) + lambda/2 tr(E)^2, E the Green strain). That is the scene's law
when it is StVK; a linear scene is mapped to it (the same at small strain), and the result says so.

- a free vertex's body carries a slide joint along each axis it may move on (a vertex held in some
  components only keeps the others), with the vertex's lumped mass (rho V / 4 of each tetrahedron it is
  in) and a negligible inertia;
- a held vertex is the world's; a vertex a tool drives is a body ``DRIVEN_MASS`` times heavier, put at the
  tool's place with the tool's velocity before every step (MuJoCo refuses mocap bodies in an elastic
  flex);
- a dynamic scene's Rayleigh damping: the stiffness-proportional part is the elasticity's ``damping``
  (documented as Rayleigh's coefficient, in seconds); the mass-proportional part is applied after every
  step (v / (1 + alpha dt), implicit), MuJoCo refusing joint damping on a flex's vertex bodies;
- gravity and loads arrive as the exported nodal forces (``xfrc_applied`` on each vertex's body); MuJoCo's
  gravity is off;
- a rigid tool is a mocap body with its geom (a sphere, a capsule, a plane), moved along its travel; its
  contact with the flex is MuJoCo's own (the flex's outer layer of tetrahedra against the geom, a soft
  constraint, frictionless: ``condim`` 1), as stiff as MuJoCo advises: ``solref`` with a time constant of two
  steps (``CONTACT_TIMECONST``), critically damped, ``solimp`` 0.99 (``CONTACT_IMPEDANCE``) on both sides.
  Its force on the body is what the constraint solver applies (``mj_contactForce``). Without rigid tools,
  contact is off;
- the solver knob is MuJoCo's integrator: ``discrete`` (MuJoCo 4's velocity-stepping integrator, the one
  in which flex elasticity is implicit; ``implicit`` and ``implicitfast`` no longer take it) or ``Euler``
  (semi-implicit, explicit in the elasticity); ``--dt`` its timestep.
"""

from __future__ import annotations

import numpy as np

from exported import RELAX_FRACTION, AdapterError, Exported, Stepper, drive, main

SOLVERS = ("discrete", "Euler")
#: A tool's vertex is a body this many times its lumped mass: the tissue's forces barely move it within a
#: step, and its place and velocity are the tool's again before the next (MuJoCo takes no mocap body in
#: an elastic flex, nor joint damping on a flex's bodies).
DRIVEN_MASS = 1e4

#: A contact's ``solref`` time constant, in steps: MuJoCo's documentation asks at least two for a stable soft
#: constraint, and the fewer, the stiffer the contact (its penetration at rest scales with its square).
CONTACT_TIMECONST = 2.0
#: A contact's ``solimp`` impedance, the same at every depth: a soft constraint's penetration at rest is
#: (1 - d) / d^2 times its time constant squared over the effective mass, per unit force, so 0.99 sinks a
#: tool 12 times less than MuJoCo's default 0.9 to 0.95 (its documentation's advice for hard contacts).
CONTACT_IMPEDANCE = 0.99


def contact_attributes(h: float) -> str:
    """The contact attributes of the flex and of every tool's geom, the same on both (MuJoCo mixes the two
    sides' ``solref`` and ``solimp``); ``h`` the step, s."""
    d = CONTACT_IMPEDANCE
    return f'contype="1" conaffinity="1" condim="1" solref="{CONTACT_TIMECONST * h:.17g} 1" solimp="{d} {d} 0.001"'


def tool_bodies(scene: Exported, h: float) -> str:
    """Each rigid tool as a mocap body at its place at t = 0, with its geom; ``h`` the step, s."""
    contact = contact_attributes(h)
    out = []
    for k, tool in enumerate(scene.rigid):
        pos = " ".join(f"{c:.17g}" for c in tool["center_m"])
        if tool["shape"] == "sphere":
            geom = f'type="sphere" size="{tool["radius_m"]:.17g}"'
        elif tool["shape"] == "capsule":
            axis = np.asarray(tool["end_m"], dtype=float) - np.asarray(tool["center_m"], dtype=float)
            geom = f'type="capsule" size="{tool["radius_m"]:.17g}" fromto="0 0 0 {" ".join(f"{c:.17g}" for c in axis)}"'
        elif tool["shape"] == "plane":  # a MuJoCo plane's solid side is below its local z: z is the normal
            geom = f'type="plane" size="0 0 1" zaxis="{" ".join(f"{c:.17g}" for c in tool["normal"])}"'
        else:
            raise AdapterError(f"rigid tool {k}: shape {tool['shape']!r} has no MuJoCo geom here")
        out.append(f'<body name="tool{k}" mocap="true" pos="{pos}"><geom name="tool{k}" {geom} {contact}/></body>')
    return "".join(out)


def mjcf(scene: Exported, solver: str, dt: float) -> tuple[str, list, list]:
    """The model's XML, and for every vertex its body's kind ("free", "world", "driven")."""
    mats = scene.spec["materials"]
    if len(mats) > 1:
        raise AdapterError("MuJoCo's flex takes one elasticity per flex; this scene has several materials")
    if mats[0]["law"] not in ("stvk", "linear"):
        raise AdapterError(f"MuJoCo's flex elasticity is StVK; the scene's law {mats[0]['law']!r} has no match there")
    held = scene.held()
    driven = np.zeros(len(scene.points), bool)
    driven[scene.tool_vertex] = True
    m = scene.lumped_masses()
    beta = scene.damping[1]
    bodies, names, kinds = [], [], []
    for i, p in enumerate(scene.points):
        xyz = " ".join(f"{c:.17g}" for c in p)
        if held[i].all() and not driven[i]:
            names.append("world")
            kinds.append("world")
            continue
        names.append(f"v{i}")
        kinds.append("driven" if driven[i] else "free")
        axes = range(3) if driven[i] else [c for c in range(3) if not held[i, c]]
        joints = "".join(
            f'<joint type="slide" axis="{" ".join("1" if a == c else "0" for a in range(3))}"/>' for c in axes
        )
        mass = m[i] * (DRIVEN_MASS if driven[i] else 1.0)
        inertia = max(mass * 1e-6, 1e-12)  # no rotation dof: any inertia MuJoCo accepts
        bodies.append(
            f'<body name="v{i}" pos="{xyz}"><inertial pos="0 0 0" mass="{mass:.17g}" '
            f'diaginertia="{inertia:.3g} {inertia:.3g} {inertia:.3g}"/>{joints}</body>'
        )
    vertex = " ".join(
        " ".join(f"{c:.17g}" for c in (p if kinds[i] == "world" else (0.0, 0.0, 0.0)))
        for i, p in enumerate(scene.points)
    )
    element = " ".join(str(int(k)) for k in scene.tets.ravel())
    mat = mats[0]
    flex_contact = contact_attributes(dt) + ' selfcollide="none"' if scene.rigid else 'contype="0" conaffinity="0"'
    xml = f"""<mujoco model="{scene.spec["scene"]}">
  <option timestep="{dt:.17g}" integrator="{solver}" gravity="0 0 0">
    {"" if scene.rigid else '<flag contact="disable"/>'}
  </option>
  <worldbody>{"".join(bodies)}{tool_bodies(scene, dt)}</worldbody>
  <deformable>
    <flex name="body" dim="3" radius="0" body="{" ".join(names)}" vertex="{vertex}" element="{element}">
      <contact {flex_contact}/>
      <elasticity young="{mat["young_pa"]:.17g}" poisson="{mat["poisson"]:.17g}" damping="{beta:.17g}"/>
    </flex>
  </deformable>
</mujoco>"""
    return xml, kinds, names


def vertex_joints(mujoco, model, kinds: np.ndarray, names: list) -> tuple[np.ndarray, np.ndarray]:
    """Each vertex's body (N,) (0, the world's, for a held one) in ``model`` (an MjModel of ``mjcf``), and
    each moving vertex's slide joints (J, 4) int64: vertex, component, qpos address, dof address."""
    body = np.array([mujoco.mj_name2id(model, mujoco.mjtObj.mjOBJ_BODY, n) if n != "world" else 0 for n in names])
    joints = []
    for i in np.flatnonzero(kinds != "world"):
        b = body[i]
        for j in range(model.body_jntadr[b], model.body_jntadr[b] + model.body_jntnum[b]):
            c = int(np.argmax(np.abs(model.jnt_axis[j])))
            joints.append((i, c, model.jnt_qposadr[j], model.jnt_dofadr[j]))
    return body, np.array(joints, dtype=np.int64).reshape(-1, 4)


class MujocoStepper(Stepper):
    """MuJoCo's model and data behind the driver's calls: a vertex's position and velocity are its body's
    joints' (qpos, qvel; the free and the driven vertices), the world's vertices stay where they are."""

    def __init__(self, scene: Exported, solver: str, dt: float, substeps: int):
        import mujoco

        self.mj, self.substeps = mujoco, substeps
        xml, kinds, names = mjcf(scene, solver, dt / substeps)
        try:
            self.model = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:
            raise AdapterError(f"MuJoCo refused the model: {' '.join(str(exc).split())}") from None
        self.data = mujoco.MjData(self.model)
        self.rest, self.kinds = scene.points, np.array(kinds)
        self.body, self.joints = vertex_joints(mujoco, self.model, self.kinds, names)
        free = np.flatnonzero(self.kinds == "free")
        self.data.xfrc_applied[self.body[free], :3] = scene.external_force[free]
        self.mass = scene.lumped_masses()
        self.alpha = scene.damping[0]
        self.x = scene.points.copy()
        self.v = np.zeros_like(scene.points)
        self.tool_geom = [
            mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_GEOM, f"tool{k}") for k in range(len(scene.rigid))
        ]
        self.tool_place = np.array([t["center_m"] for t in scene.rigid], dtype=float).reshape(-1, 3)
        mujoco.mj_forward(self.model, self.data)

    def step(self, dt: float) -> None:
        h = dt / self.substeps
        for _ in range(self.substeps):
            self.mj.mj_step(self.model, self.data)
            if self.alpha:
                self.data.qvel[self.joints[:, 3]] /= 1.0 + self.alpha * h
        i, c, qa, da = self.joints.T
        self.x[i, c] = self.rest[i, c] + self.data.qpos[qa]
        self.v[i, c] = self.data.qvel[da]

    def internal_force(self) -> np.ndarray:
        """The flex's elastic force on each vertex: its joints' passive force (``qfrc_passive``; a slide
        joint's generalised force is the Cartesian component), at the present state."""
        self.mj.mj_forward(self.model, self.data)
        f = np.zeros_like(self.rest)
        i, c, _, da = self.joints.T
        f[i, c] = self.data.qfrc_passive[da]
        return f

    def net_force(self) -> np.ndarray:
        """The net force on each free vertex at the present state: MuJoCo's smooth force (the flex's
        elasticity, the applied loads) plus its constraint force (the contacts), per slide joint."""
        self.mj.mj_forward(self.model, self.data)
        f = np.zeros_like(self.rest)
        i, c, _, da = self.joints.T
        free = self.kinds[i] == "free"
        f[i[free], c[free]] = self.data.qfrc_smooth[da[free]] + self.data.qfrc_constraint[da[free]]
        return f

    def set_rigid(self, offset: np.ndarray, velocity: np.ndarray) -> None:
        """A mocap body's place is set, not integrated: its velocity is MuJoCo's finite difference."""
        self.data.mocap_pos[: len(self.tool_place)] = self.tool_place + offset

    def rigid_force(self) -> np.ndarray:
        """Each tool's force on the flex: the constraint solver's normal force of every contact of its geom
        (``mj_contactForce``, in the contact frame whose first axis points from geom[0] to geom[1]) at the
        present state."""
        self.mj.mj_forward(self.model, self.data)
        out = np.zeros((len(self.tool_geom), 3))
        f6 = np.zeros(6)
        for i in range(self.data.ncon):
            con = self.data.contact[i]
            for k, g in enumerate(self.tool_geom):
                if g in (con.geom[0], con.geom[1]):
                    self.mj.mj_contactForce(self.model, self.data, i, f6)
                    on_second = con.frame.reshape(3, 3).T @ f6[:3]  # the force on geom[1], world frame
                    out[k] += on_second if con.geom[0] == g else -on_second
        return out

    def unstable(self) -> bool:
        """MuJoCo's own verdict: a bad acceleration, position or velocity makes it warn and reset the state
        to rest (mjWARN_BADQACC, BADQPOS, BADQVEL), which the positions alone would take for an answer."""
        w = self.mj.mjtWarning
        bad = (w.mjWARN_BADQACC, w.mjWARN_BADQPOS, w.mjWARN_BADQVEL)
        return any(self.data.warning[int(k)].number > 0 for k in bad)

    def positions(self) -> np.ndarray:
        return self.x.copy()

    def set_positions(self, x: np.ndarray) -> None:
        i, c, qa, _ = self.joints.T
        self.data.qpos[qa] = x[i, c] - self.rest[i, c]
        self.x = x.copy()

    def velocities(self) -> np.ndarray:
        return self.v.copy()

    def set_velocities(self, v: np.ndarray) -> None:
        i, c, _, da = self.joints.T
        self.data.qvel[da] = v[i, c]
        self.v = v.copy()

    def masses(self) -> np.ndarray:
        return self.mass


def stable_guess(scene: Exported, solver: str) -> float:
    """For ``Euler``, RELAX_FRACTION of the explicit wave step (``Exported.wave_step``); for ``discrete``,
    implicit in the elasticity, 1 ms."""
    if solver == "discrete":
        return 1e-3
    lam, mu, _ = scene.lame()
    return RELAX_FRACTION * scene.wave_step(lam + 2.0 * mu)


def mapped_law(scene: Exported) -> str:
    """The scene's law as the flex's elasticity takes it, in words."""
    law = scene.spec["law"]
    return "StVK, as the scene's" if law == "stvk" else f"StVK for the scene's {law} law (equal at small strain)"


def run(scene: Exported, args, progress):
    import mujoco

    if args.device != "cpu":
        raise AdapterError(
            f"device {args.device}: MuJoCo runs on the CPU (a GPU is MuJoCo Warp's: --engine mujoco-warp)"
        )
    dt = args.dt if args.dt else stable_guess(scene, args.solver)
    engine = MujocoStepper(scene, args.solver, dt, args.substeps)
    progress(f"{len(scene.points)} vertices, {len(scene.tets)} tetrahedra, {engine.model.nv} dofs, dt = {dt:.3g} s")
    result = drive(engine, scene, args, dt, progress)
    result["substeps"], result["device"] = args.substeps, "cpu"
    law = f"MuJoCo flex elasticity: {mapped_law(scene)}"
    return result, law, f"MuJoCo {mujoco.__version__} flex, {args.solver} (float64)"


if __name__ == "__main__":
    raise SystemExit(main(run, "MuJoCo's 3D flex on an exported scene", SOLVERS))
