"""MuJoCo Warp's 3D flex on an exported scene, on warp's device (``--device``: its CPU unless a user with a GPU
asks for ``cuda:0``).

    .venv-engines/bin/python adapters/mujoco_warp_flex.py SCENE_DIR RESULT.npz --solver discrete --dt 1e-3

MuJoCo Warp (``mujoco_warp``) is MuJoCo's physics rewritten in NVIDIA warp, for GPUs: the same model,
compiled by MuJoCo from the same MJCF (``mujoco_flex.mjcf``: one body per vertex, a ``<flex dim="3">``
with ``<elasticity>``, StVK on linear tetrahedra), put on warp's device (``put_model``, ``put_data``) and
stepped by ``mujoco_warp.step`` as its own examples step it, in float32 (with the ``discrete`` integrator,
the CG solver, which MuJoCo Warp requires of a flex on bodies). On warp's CPU device its kernels run one
thread each: its step times there say nothing of a GPU's.

The loads, held vertices, tools and damping are MuJoCo's adapter's: the loads as ``xfrc_applied`` on each
vertex's body, a tool's vertex a heavy body put at the tool's place before every step, the mass-proportional
damping applied after every step. A rigid tool is not taken here (its contact's force is not read back
from MuJoCo Warp's contacts yet): a contact scene is not applicable.
"""

from __future__ import annotations

import numpy as np

from exported import AdapterError, Exported, Stepper, drive, main, warp_device
from mujoco_flex import SOLVERS, mapped_law, mjcf, stable_guess, vertex_joints


class MujocoWarpStepper(Stepper):
    """MuJoCo Warp's model and data on warp's ``device`` behind the driver's calls: a vertex's position
    and velocity are its body's joints' (qpos, qvel), as in MuJoCo's adapter."""

    epsilon = float(np.finfo(np.float32).eps)

    def __init__(self, scene: Exported, solver: str, dt: float, substeps: int, device):
        import mujoco
        import mujoco_warp as mjw
        import warp as wp

        if scene.rigid:
            raise AdapterError("MuJoCo Warp's adapter does not take a rigid tool yet")
        self.wp, self.mjw, self.substeps = wp, mjw, substeps
        xml, kinds, names = mjcf(scene, solver, dt / substeps)
        try:
            mjm = mujoco.MjModel.from_xml_string(xml)
        except ValueError as exc:
            raise AdapterError(f"MuJoCo refused the model: {' '.join(str(exc).split())}") from None
        if solver == "discrete":  # MuJoCo Warp takes a flex whose vertices are bodies only with CG there
            mjm.opt.solver = mujoco.mjtSolver.mjSOL_CG
        mjd = mujoco.MjData(mjm)
        self.rest, self.kinds = scene.points, np.array(kinds)
        body, self.joints = vertex_joints(mujoco, mjm, self.kinds, names)
        free = np.flatnonzero(self.kinds == "free")
        mjd.xfrc_applied[body[free], :3] = scene.external_force[free]
        self.device = device
        with wp.ScopedDevice(self.device):
            try:
                self.model = mjw.put_model(mjm)
                self.data = mjw.put_data(mjm, mjd)
            except (NotImplementedError, ValueError) as exc:
                raise AdapterError(f"MuJoCo Warp does not take this model: {exc}") from None
        self.mass = scene.lumped_masses()
        self.alpha = scene.damping[0]
        self.x = scene.points.copy()
        self.v = np.zeros_like(scene.points)

    def _read(self) -> None:
        i, c, qa, da = self.joints.T
        self.x[i, c] = self.rest[i, c] + self.data.qpos.numpy()[0, qa]
        self.v[i, c] = self.data.qvel.numpy()[0, da]

    def step(self, dt: float) -> None:
        h = dt / self.substeps
        with self.wp.ScopedDevice(self.device):
            for _ in range(self.substeps):
                self.mjw.step(self.model, self.data)
                if self.alpha:
                    qvel = self.data.qvel.numpy()
                    qvel[0, self.joints[:, 3]] /= 1.0 + self.alpha * h
                    self.data.qvel.assign(qvel)
        self._read()

    def _forward(self) -> None:
        with self.wp.ScopedDevice(self.device):
            self.mjw.forward(self.model, self.data)

    def internal_force(self) -> np.ndarray:
        """The flex's elastic force on each vertex: its joints' passive force at the present state."""
        self._forward()
        f = np.zeros_like(self.rest)
        i, c, _, da = self.joints.T
        f[i, c] = self.data.qfrc_passive.numpy()[0, da]
        return f

    def net_force(self) -> np.ndarray:
        """The net force on each free vertex: the smooth force plus the constraint force, per slide joint."""
        self._forward()
        f = np.zeros_like(self.rest)
        i, c, _, da = self.joints.T
        free = self.kinds[i] == "free"
        net = self.data.qfrc_smooth.numpy()[0] + self.data.qfrc_constraint.numpy()[0]
        f[i[free], c[free]] = net[da[free]]
        return f

    def positions(self) -> np.ndarray:
        return self.x.copy()

    def set_positions(self, x: np.ndarray) -> None:
        i, c, qa, _ = self.joints.T
        qpos = self.data.qpos.numpy()
        qpos[0, qa] = x[i, c] - self.rest[i, c]
        self.data.qpos.assign(qpos)
        self.x = x.copy()

    def velocities(self) -> np.ndarray:
        return self.v.copy()

    def set_velocities(self, v: np.ndarray) -> None:
        i, c, _, da = self.joints.T
        qvel = self.data.qvel.numpy()
        qvel[0, da] = v[i, c]
        self.data.qvel.assign(qvel)
        self.v = v.copy()

    def masses(self) -> np.ndarray:
        return self.mass


def run(scene: Exported, args, progress):
    import warp

    warp.config.quiet = True
    import mujoco_warp

    device = warp_device(warp, args.device)
    dt = args.dt if args.dt else stable_guess(scene, args.solver)
    engine = MujocoWarpStepper(scene, args.solver, dt, args.substeps, device)
    progress(f"{len(scene.points)} vertices, {len(scene.tets)} tetrahedra, dt = {dt:.3g} s (warp's {device.alias})")
    result = drive(engine, scene, args, dt, progress)
    result["substeps"], result["device"] = args.substeps, device.alias
    version = getattr(mujoco_warp, "__version__", None) or _version("mujoco-warp")
    engine_name = f"MuJoCo Warp {version} flex, {args.solver} (warp {warp.__version__} {device.alias}, float32)"
    return result, f"MuJoCo Warp flex elasticity: {mapped_law(scene)}", engine_name


def _version(dist: str) -> str:
    from importlib.metadata import version

    return version(dist)


if __name__ == "__main__":
    raise SystemExit(main(run, "MuJoCo Warp's 3D flex on an exported scene", SOLVERS))
