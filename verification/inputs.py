"""A scene becomes each solver's inputs here: the engines' SceneInputs (``scene_inputs``), whose
constraints and loads are a ``Loading`` consistent with the P1 FEM (``build_loading``), and the check
that a static scene's held body has an equilibrium (``check_held``). The reference takes the scene's
``Problem`` (``Scene.problem``, ``Scene.problem_on``) and meshes.

Gravity becomes m_i g with the lumped masses rho V / 4, exactly the P1 load vector of a constant body
force; a traction t on boundary triangles inside the region becomes t A / 3 on each of their
vertices, exactly the P1 load vector of a constant traction; a force F is the traction F / A over
those triangles (A their total area). So on the same mesh the tensor-mass statics and the P1
reference solve the same linear system.
"""

from __future__ import annotations

import numpy as np

from meshes import TetMesh
from realtime.contact import Rigid, contacts
from realtime.errors import InputError
from realtime.geometry import face_areas
from realtime.material import Materials
from realtime.model import RAMP_SHAPES, TOOL_ROTATION, TOOL_TRANSLATION, Loading, lumped_masses
from realtime.models import linear_tm
from reference.problem import Displacement, Fixed, Force, Gravity, Problem, Traction, component_mask
from verification.engines.protocol import SceneInputs, TimeMode


def region_faces(mesh: TetMesh, region) -> np.ndarray:
    """Boundary triangles (F, 3) whose three vertices lie in the region."""
    inside = np.zeros(mesh.n_vertices, dtype=bool)
    inside[region.vertices(mesh)] = True
    faces = mesh.boundary
    return faces[np.all(inside[faces], axis=1)]


def build_loading(mesh: TetMesh, density: float, problem: Problem, young: float | None = None) -> Loading:
    """The Loading of ``problem`` on ``mesh`` (the module's docstring), with lumped masses of ``density``
    kg/m^3 (one number or (M,) float64); the rigid tools' penalty (realtime.contact) scaled by ``young``
    Pa, the body's stiffest Young's modulus (needed only where the problem has rigid tools)."""
    n = mesh.n_vertices
    free = np.ones((n, 3))
    fext = np.zeros((n, 3))
    for fx in problem.fixed:
        assert isinstance(fx, Fixed)
        free[fx.region.vertices(mesh)] *= 1.0 - component_mask(fx.components)
    mass = lumped_masses(mesh.points, mesh.tets, density)
    tool = {k: [] for k in ("vertex", "mask", "id")}
    tools = {k: [] for k in ("kind", "vector", "axis", "center", "angle", "ramp", "shape")}
    for ld in problem.loads:
        if isinstance(ld, Gravity):
            fext += mass[:, None] * np.asarray(ld.value)
        elif isinstance(ld, (Force, Traction)):
            faces = region_faces(mesh, ld.region)
            if len(faces) == 0:
                raise InputError(
                    f"{type(ld).__name__.lower()} load {ld.region.describe()}: no boundary face in the region"
                )
            area = face_areas(mesh.points, faces)
            t = np.asarray(ld.value, dtype=float)
            if isinstance(ld, Force):
                t = t / area.sum()
            np.add.at(fext, faces.ravel(), np.repeat(area / 3.0, 3)[:, None] * t)
        elif isinstance(ld, Displacement):
            idx = ld.region.vertices(mesh)
            k = len(tools["kind"])
            mask = component_mask(ld.components)
            tool["vertex"].append(idx)
            tool["mask"].append(np.tile(mask, (len(idx), 1)))
            tool["id"].append(np.full(len(idx), k))
            free[idx] *= 1.0 - mask
            tools["kind"].append(TOOL_ROTATION if ld.is_rotation else TOOL_TRANSLATION)
            tools["vector"].append(ld.translation or (0.0, 0.0, 0.0))
            tools["axis"].append(ld.axis or (0.0, 0.0, 1.0))
            tools["center"].append(ld.center or (0.0, 0.0, 0.0))
            tools["angle"].append(np.radians(ld.angle))
            tools["ramp"].append(ld.ramp)
            tools["shape"].append(RAMP_SHAPES.index(ld.ramp_shape))
    contacts = _contacts(mesh, problem, young)
    if tools["kind"]:
        return Loading(
            free=free,
            external_force=fext,
            contacts=contacts,
            tool_vertex=np.concatenate(tool["vertex"]).astype(np.int64),
            tool_mask=np.concatenate(tool["mask"]).astype(np.float64),
            tool_id=np.concatenate(tool["id"]).astype(np.int64),
            tool_kind=np.asarray(tools["kind"], dtype=np.int64),
            tool_vector=np.asarray(tools["vector"], dtype=np.float64),
            tool_axis=np.asarray(tools["axis"], dtype=np.float64),
            tool_center=np.asarray(tools["center"], dtype=np.float64),
            tool_angle=np.asarray(tools["angle"], dtype=np.float64),
            tool_ramp=np.asarray(tools["ramp"], dtype=np.float64),
            tool_ramp_shape=np.asarray(tools["shape"], dtype=np.int64),
        )
    return Loading(free=free, external_force=fext, contacts=contacts)


def _contacts(mesh: TetMesh, problem: Problem, young: float | None):
    """The engine's Contacts of the problem's rigid tools on ``mesh`` (None without any)."""
    if not problem.contacts:
        return None
    if young is None:
        raise InputError("build_loading: the scene has rigid tools; their penalty needs young (Pa)")
    rigid = [
        Rigid(t.shape, t.center, t.radius, t.end, t.normal, t.travel, t.ramp, t.ramp_shape) for t in problem.contacts
    ]
    return contacts(mesh.points, mesh.tets, rigid, young)


def scene_loading(scene) -> Loading:
    """``build_loading`` of a scene on its own mesh, its rigid tools' penalty scaled as the truth's."""
    return build_loading(scene.mesh, scene.densities(), scene.problem, stiffest_young(scene))


def stiffest_young(scene) -> float:
    """The largest Young's modulus (Pa) of the scene's materials: the contact penalty's scale, as the
    reference's (reference.contact)."""
    return float(np.max(Materials.of(scene.body_material(), scene.mesh.n_tets).per_tet("young")))


#: Free components up to which ``check_held`` looks for zero-energy modes (a sparse factorisation of
#: the P1 stiffness): the refined meshes behind it pose the same problem, and are not checked again.
HELD_CHECK_LIMIT = 200_000


def check_held(scene) -> None:
    """SceneError, before any work, for a static scene whose held body has a zero-energy mode with a
    cause in the mesh or the constraints: no static equilibrium exists for either solver, and a run
    would drift until its displacement 'diverged' at any time step. A mode is an eigenvalue of the P1
    linear stiffness on the held components below 1e-10 of the element bound
    (realtime.spectra.zero_energy_modes); a cause is blocks of tetrahedra (joined through faces) that
    meet only at vertices or edges, or fewer than three non-collinear vertices held in all three
    components. Both are asked for: a slender body's soft bending modes also fall below that ratio
    (SOFA's 16 m raptor, finely meshed at its tips: 3e-12), and are physics, not a mechanism."""
    from realtime import build_model
    from realtime.spectra import zero_energy_modes
    from verification.scene import SceneError

    if scene.time.mode != "static" or scene.manufactured:
        return
    base = scene.base or scene
    mesh = base.mesh
    if 3 * mesh.n_vertices > HELD_CHECK_LIMIT:
        return
    loading = scene_loading(base)
    n_blocks, _ = mesh.blocks()
    anchors = mesh.points[np.all(loading.free == 0.0, axis=1)]
    extent = float(np.ptp(mesh.points, axis=0).max())
    spread = np.linalg.svd(anchors - anchors.mean(axis=0), compute_uv=False) if len(anchors) else np.zeros(1)
    too_few = len(anchors) < 3 or (len(spread) < 2 or spread[1] <= 1e-9 * extent)
    if n_blocks == 1 and not too_few:
        return
    model = build_model(linear_tm.NAME, mesh.points, mesh.tets, base.body_material(), loading)
    count, ratio = zero_energy_modes(model)
    if not count:
        return
    causes = []
    if n_blocks > 1:
        causes.append(
            f"its {mesh.n_tets} tetrahedra form {n_blocks} blocks that meet only at vertices or edges, each joint "
            "free to turn"
        )
    if too_few:
        causes.append(f"{len(anchors)} of its vertices are held in all three components, too few or on one line")
    raise SceneError(
        f"{scene.path}: fixed: the held body has {count}{'+' if count == 6 else ''} zero-energy mode(s) (smallest "
        f"stiffness eigenvalue {ratio:.1e} of the largest): {'; '.join(causes)}; a static scene has no "
        "equilibrium, so hold more of the body with [[fixed]] regions"
    )


def scene_inputs(scene) -> SceneInputs:
    """The scene as what every engine builds from (``engines.protocol.SceneInputs``): its mesh's arrays,
    its materials, its loading (``build_loading``) and its time mode; and, for an engine in this process
    that runs on a mesh of its own, the loading on that mesh."""
    mesh, ts = scene.mesh, scene.time
    return SceneInputs(
        name=scene.name,
        source=str(scene.path),
        sha256=scene.sha256(),
        points=mesh.points,
        tets=mesh.tets,
        material=scene.body_material(),
        loading=scene_loading(scene),
        time=TimeMode(ts.mode, ts.end, ts.output_every, ts.damping_mass, ts.damping_stiffness),
        gravity=next((tuple(ld.value) for ld in scene.problem.loads if isinstance(ld, Gravity)), (0.0, 0.0, 0.0)),
        loading_on=_loading_on(scene),
        regions=_region_rules(scene.problem),
    )


def _region_rules(problem: Problem) -> dict:
    """``SceneInputs.regions``: the held and driven regions of ``problem`` by their rule."""

    def entry(c) -> dict:
        return {"rule": c.region.rule(), "components": list(c.components)}

    return {"fixed": [entry(fx) for fx in problem.fixed], "tools": [entry(ld) for ld in problem.tools]}


def _loading_on(scene):
    """For ``SceneInputs.loading_on``: the scene's loading on a mesh whose vertices lie on its own."""

    def on(points, tets, parent):
        mixed = TetMesh(points, tets, source=f"{scene.mesh.source} adaptive")
        return build_loading(mixed, scene.densities()[parent], scene.problem_on(mixed), stiffest_young(scene))

    return on
