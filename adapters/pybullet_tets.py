"""PyBullet's deformable bodies (Bullet's ``btDeformableMultiBodyDynamicsWorld``) on an exported scene.

    .venv-engines/bin/python adapters/pybullet_tets.py SCENE_DIR RESULT.npz --dt 1e-4

Driven as PyBullet's own deformable examples drive it: ``resetSimulation(RESET_USE_DEFORMABLE_WORLD)``,
the body read by ``loadSoftBody`` from a VTK tetrahedral mesh with its neo-Hookean force, held vertices
anchored to the world (``createSoftBodyAnchor``), and ``stepSimulation`` at the step ``setTimeStep`` sets.

- The law: Bullet's ``btDeformableNeoHookeanForce``, W = mu/2 (I_C - 3) + lambda/2 (J - 1 - 3/4 mu/lambda)^2
  - mu/2 ln(I_C + 1): Smith, de Goes & Kim's stable neo-Hookean with its log term (2018, eq. 14). Its
  constants are not the Lame ones: matched at rest (section 3.4) they are mu = 4/3 mu_s, lambda = lambda_s +
  5/6 mu_s, which this adapter passes (NeoHookeanMu, NeoHookeanLambda); its damping (NeoHookeanDamping) is 0.
- The integrator: Bullet's deformable solver as PyBullet leaves it (``btDeformableBodySolver`` with
  ``m_implicit`` false, which no PyBullet call changes): the elastic force at the start of the step, the
  damping and the constraints implicit. It is explicit in the elasticity: its step is bound by the
  critical one.
- The mass: ``loadSoftBody(mass=M)`` spreads the body's mass evenly over its nodes (``setTotalMass``), not by
  volume; gravity, Bullet's own, acts on those masses. On a mesh whose vertices hold unequal volumes the
  load is not the scene's: that is PyBullet's answer as its users get it, and the distance from P1 of its own
  law (the scene's consistent load) shows it.

What PyBullet cannot be given is refused with the reason, in one line (exit 2, "not applicable"): loads
other than gravity (it takes no nodal force), a vertex held in some directions only (an anchor holds all
three), a tool (a node's place is set only with every other's, ``resetMeshData``, and its velocity only as
the whole body's rigid motion), a rigid tool, several materials (one force per body), and a dynamic
scene's damping (the velocities cannot be scaled). Node velocities are not read by PyBullet's API: they
are the positions' difference over the step, which for its update x += h v is the velocity itself; the
relaxation's kinetic damping brings the body to rest with ``resetBaseVelocity`` (zero linear and angular
velocity: every node still).
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np

from exported import RELAX_FRACTION, AdapterError, Exported, Stepper, drive, gravity_only, main

SOLVERS = ("explicit",)


def write_vtk(path: Path, points: np.ndarray, tets: np.ndarray) -> None:
    """The mesh as the legacy VTK unstructured grid Bullet's reader takes (``CreateFromVtkFile``: one point a
    line, cells of 4), in the scene's vertex order."""
    lines = ["# vtk DataFile Version 2.0", "tissuebench", "ASCII", "DATASET UNSTRUCTURED_GRID"]
    lines.append(f"POINTS {len(points)} double")
    lines += [" ".join(f"{c:.17g}" for c in q) for q in points]
    lines.append(f"CELLS {len(tets)} {5 * len(tets)}")
    lines += ["4 " + " ".join(str(int(i)) for i in t) for t in tets]
    lines.append(f"CELL_TYPES {len(tets)}")
    lines += ["10"] * len(tets)
    path.write_text("\n".join(lines) + "\n")


def check(scene: Exported) -> None:
    """AdapterError naming what of the scene PyBullet cannot be given (the module docstring)."""
    held = scene.held()
    partial = held.any(axis=1) & ~held.all(axis=1)
    if scene.rigid:
        raise AdapterError("PyBullet's adapter does not take a rigid tool")
    if len(scene.tool_vertex):
        raise AdapterError(
            "PyBullet moves no vertex along a tool's path: a node's place is set only with every other's "
            "(resetMeshData) and its velocity only as the body's rigid motion"
        )
    if partial.any():
        raise AdapterError(
            f"PyBullet's anchor holds a node in all three directions: this scene holds {int(partial.sum())} "
            "vertices in some only"
        )
    if len(set(np.asarray(scene.material_index).tolist())) > 1:
        raise AdapterError("PyBullet's soft body takes one neo-Hookean force: this scene has several materials")
    if any(scene.damping):
        raise AdapterError("PyBullet's node velocities cannot be scaled: this dynamic scene's damping is not taken")


class PyBulletStepper(Stepper):
    """One deformable body in PyBullet's DIRECT server behind the driver's calls (float64: PyBullet is built
    with Bullet's double precision)."""

    def __init__(self, scene: Exported, dt: float, substeps: int):
        import pybullet as p

        check(scene)
        self.p, self.h, self.substeps = p, dt / substeps, substeps
        self.client = p.connect(p.DIRECT)
        p.resetSimulation(p.RESET_USE_DEFORMABLE_WORLD, physicsClientId=self.client)
        p.setGravity(*gravity_only(scene, "PyBullet's soft body"), physicsClientId=self.client)
        p.setTimeStep(self.h, physicsClientId=self.client)
        lam, mu, rho = scene.lame()
        self.total = float((rho * scene.volumes()).sum())
        with tempfile.TemporaryDirectory(prefix="pybullet-") as work:
            mesh = Path(work) / "body.vtk"
            write_vtk(mesh, scene.points, scene.tets)
            self.body = p.loadSoftBody(
                str(mesh),
                mass=self.total,
                useNeoHookean=1,
                NeoHookeanMu=float(4.0 / 3.0 * mu[0]),
                NeoHookeanLambda=float(lam[0] + 5.0 / 6.0 * mu[0]),
                NeoHookeanDamping=0.0,
                useSelfCollision=0,
                frictionCoeff=0.0,
                physicsClientId=self.client,
            )
        self.x = self._read()
        if self.x.shape != scene.points.shape or np.abs(self.x - scene.points).max() > 1e-12 * scene.size:
            raise AdapterError("PyBullet read the mesh's vertices in another order or place than the export's")
        self.held = scene.held().all(axis=1)
        for i in np.flatnonzero(self.held):
            p.createSoftBodyAnchor(self.body, int(i), -1, -1, physicsClientId=self.client)
        # a body at rest is put to sleep by Bullet's deactivation: a relaxation passes through rest
        p.changeDynamics(
            self.body, -1, activationState=p.ACTIVATION_STATE_DISABLE_SLEEPING, physicsClientId=self.client
        )
        self.v = np.zeros_like(self.x)
        # setTotalMass spreads the mass evenly; an anchored node's is 0 (createSoftBodyAnchor)
        self.mass = np.where(self.held, 0.0, self.total / len(self.x))

    def _read(self) -> np.ndarray:
        p = self.p
        _, xs = p.getMeshData(self.body, -1, flags=p.MESH_DATA_SIMULATION_MESH, physicsClientId=self.client)
        return np.array(xs, dtype=float)

    def step(self, dt: float) -> None:
        for _ in range(self.substeps):
            self.p.stepSimulation(physicsClientId=self.client)
            x = self._read()
            self.v, self.x = (x - self.x) / self.h, x  # x_{n+1} = x_n + h v_{n+1}: the velocity itself

    def positions(self) -> np.ndarray:
        return self.x.copy()

    def set_positions(self, x: np.ndarray) -> None:
        if np.array_equal(x, self.x):
            return
        self.p.resetMeshData(self.body, np.asarray(x, dtype=float).tolist(), physicsClientId=self.client)
        self.x = np.asarray(x, dtype=float).copy()

    def velocities(self) -> np.ndarray:
        return self.v.copy()

    def set_velocities(self, v: np.ndarray) -> None:
        """Only what PyBullet can do: every free node still (``resetBaseVelocity`` with zero linear and angular
        velocity sets each node's to that rigid motion), or the velocities left as they are; AdapterError
        for any other."""
        free = ~self.held
        if not np.any(v[free]):
            self.p.resetBaseVelocity(self.body, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0], physicsClientId=self.client)
            self.v = np.zeros_like(self.v)
        elif not np.array_equal(v[free], self.v[free]):
            raise AdapterError("PyBullet sets a soft body's node velocities only to a rigid motion")

    def masses(self) -> np.ndarray:
        return self.mass


def stable_guess(scene: Exported) -> float:
    """RELAX_FRACTION of the explicit wave step with the constants Bullet runs with (``Exported.wave_step``)."""
    lam, mu, _ = scene.lame()
    return RELAX_FRACTION * scene.wave_step(lam + 5.0 / 6.0 * mu + 2.0 * 4.0 / 3.0 * mu)


def run(scene: Exported, args, progress):
    from importlib.metadata import version

    if args.device != "cpu":
        raise AdapterError(f"device {args.device}: PyBullet runs on the CPU")
    dt = args.dt if args.dt else stable_guess(scene)
    engine = PyBulletStepper(scene, dt, args.substeps)
    progress(f"{len(scene.points)} vertices, {len(scene.tets)} tetrahedra, dt = {dt:.3g} s")
    result = drive(engine, scene, args, dt, progress)
    result["substeps"], result["device"] = args.substeps, "cpu"
    law = "stable Neo-Hookean with log term (Smith et al. 2018), mu = 4/3 mu, lambda = lambda + 5/6 mu; mass even over the nodes"
    return result, law, f"PyBullet {version('pybullet')} deformable body, explicit in the elasticity (float64)"


if __name__ == "__main__":
    raise SystemExit(main(run, "PyBullet's deformable bodies on an exported scene", SOLVERS))
