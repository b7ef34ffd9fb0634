"""A scene (docs/data-flow.md): its mesh, materials, constraints, loads and time mode, as
read from its file (``verification.scene_file``), and what it answers: the mesh built and checked
against its regions, each tetrahedron's material, its hash, the same scene refined, warnings for
numbers no soft tissue has.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from meshes import InvalidMeshError, TetMesh, get_mesh, read_mesh
from meshes.regions import FieldRegion, TagRegion
from realtime.errors import InputError
from realtime.material import Material, Materials
from reference.problem import (
    Displacement,
    Force,
    Gravity,
    Problem,
    Traction,
    component_mask,
)

SCENES_DIR = Path(__file__).parent / "scenes"


class SceneError(InputError):
    """A scene file that cannot be used; ``str()`` is the one-line message."""


@dataclass(frozen=True)
class TimeSpec:
    mode: str = "static"
    end: float = 1.0
    output_every: float = 0.01
    damping_mass: float = 0.0  # 1/s
    damping_stiffness: float = 0.0  # s


@dataclass
class Scene:
    """A loaded scene. ``mesh`` is built on first use (``scene.mesh``)."""

    name: str
    description: str
    path: Path
    mesh_spec: dict
    material: Material
    problem: Problem
    time: TimeSpec
    raw: dict = field(repr=False, default_factory=dict)
    _mesh: TetMesh | None = field(default=None, repr=False)
    manufactured: dict | None = None
    #: Uniform refinements of the base scene's mesh this scene is on (``refined``); 0 for a scene file.
    level: int = 0
    #: The scene this one refines (its geometry and regions are the base's); None at level 0.
    base: Scene | None = field(default=None, repr=False)
    #: [[material]] tables: ((region, Material), ...), a tetrahedron taking the last whose region holds
    #: it; None for one [material] everywhere (then ``material`` is it; otherwise the first table's).
    zones: tuple | None = None
    #: [[event]] tables (``verification.events.Event``): cuts and sutures at times; () for none.
    events: tuple = ()

    @property
    def mesh(self) -> TetMesh:
        if self._mesh is None:
            self._mesh = build_mesh(self.mesh_spec, self.path)
            check_regions(self, self._mesh)
            if self.zones:
                zone_index(self, self._mesh)  # every tetrahedron has a material, every table a tetrahedron
        return self._mesh

    def body_material(self) -> Material | Materials:
        """What the solvers take: the Material, or for [[material]] tables the Materials of this scene's
        mesh. A refined scene's tetrahedra take their base tetrahedron's material (``TetMesh.refined``
        numbers child j of parent j mod M), so every level is the base's body."""
        if not self.zones:
            return self.material
        base = self.base or self
        index = zone_index(base, base.mesh)
        for _ in range(self.level - base.level):
            index = np.tile(index, 8)
        return Materials(tuple(m for _, m in self.zones), index)

    def densities(self) -> np.ndarray:
        """Each tetrahedron's density (M,) float64, kg/m^3."""
        return Materials.of(self.body_material(), self.mesh.n_tets).per_tet("density")

    def sha256(self) -> str:
        """Hash of the scene's content: the canonical JSON of its TOML, what was parsed from it (so that
        a variant made with dataclasses.replace, a 90 or a 60 degree twist, has a hash of its own), its
        mesh and the mesh's tags (a region or a material drawn by tag changes with them alone)."""
        text = json.dumps(self.raw, sort_keys=True, default=str)
        parsed = repr((self.material, self.problem, self.time, self.manufactured, self.level, self.zones))
        parsed += repr(self.events) if self.events else ""
        mesh = self.mesh.sha256() + self.mesh.tags_sha256()
        return hashlib.sha256((text + parsed + mesh).encode()).hexdigest()

    def refined(self, levels: int = 1) -> Scene:
        """This scene on its mesh cut uniformly ``levels`` more times (``TetMesh.refined``: h halves at
        each level, the coarser vertices come first), its regions carried by the rule the reference
        applies to its own refined meshes (``meshes.regions.spanned``: a refined vertex belongs to a
        region when the base vertices of its edge or face do), so that every level poses the base
        scene's problem (docs/data-flow.md). The reference of a refined scene is the
        base's, evaluated at the refined vertices."""
        if levels == 0:
            return self
        base = self.base or self
        mesh = self.mesh
        for _ in range(levels):
            mesh = mesh.refined()
        problem = self.problem_on(mesh)
        level = self.level + levels
        raw = json.loads(json.dumps(base.raw, default=str))
        raw.setdefault("mesh", {})["refine"] = level
        return dataclasses.replace(
            base, material=self.material, problem=problem, raw=raw, _mesh=mesh, level=level, base=base
        )

    def problem_on(self, mesh: TetMesh):
        """The base scene's problem on ``mesh``, a mesh whose vertices lie on the base mesh's vertices,
        edges, faces or tetrahedra (a refinement of it, uniform or not): each region becomes the vertices
        that its base selection spans (``meshes.regions.spanned``), the rule the reference applies."""
        from meshes.regions import VertexRegion, spanned

        base = self.base or self

        def carry(region):
            return VertexRegion(tuple(np.flatnonzero(spanned(base.mesh, region.vertices(base.mesh), mesh.points))))

        return dataclasses.replace(
            base.problem,
            fixed=tuple(dataclasses.replace(f, region=carry(f.region)) for f in base.problem.fixed),
            loads=tuple(
                dataclasses.replace(ld, region=carry(ld.region)) if hasattr(ld, "region") else ld
                for ld in base.problem.loads
            ),
        )

    def with_material(self, **changes) -> Scene:
        """A copy with material fields changed (for studies over nu, E); with [[material]] tables, in
        every table."""
        raw = json.loads(json.dumps(self.raw))
        tables = raw.setdefault("material", {})
        for table in tables if isinstance(tables, list) else [tables]:
            table.update(changes)
        zones = self.zones and tuple((region, m.replace(**changes)) for region, m in self.zones)
        return dataclasses.replace(self, material=self.material.replace(**changes), raw=raw, zones=zones)


#: What a body of soft tissue spans, for the warnings of ``implausible``: its largest extent, m (a
#: millimetre patch of vessel wall to a metre-long torso); Young's modulus, Pa (brain about 1 kPa,
#: tendon about 1 GPa); density, kg/m^3 (inflated lung about 300, bone about 2000).
TISSUE_RANGES = {"extent": (1e-3, 1.0), "young": (100.0, 1e9), "density": (200.0, 3000.0)}


def implausible(scene: Scene) -> list[str]:
    """One line per number of the scene that no soft tissue has: a body larger than a metre (a mesh in
    millimetres read as metres: ``scale``), a modulus or a density outside TISSUE_RANGES (a unit
    slip: kPa for Pa, g/cm^3 for kg/m^3). Warnings, not errors: a rubber phantom or a steel probe is
    a valid scene. A manufactured-solution scene is a mathematical problem and is not judged."""
    if scene.manufactured:
        return []
    out = []
    lo, hi = scene.mesh.bounding_box()
    extent = float(np.max(hi - lo))
    low, high = TISSUE_RANGES["extent"]
    if not low <= extent <= high:
        volume = float(scene.mesh.volumes().sum())
        fix = f"; {units_hint(extent, volume)}" if scene.mesh_spec["generator"] == "file" else " (lengths in metres)"
        out.append(f"mesh: the body is {extent:.3g} m across, outside the {low:g} to {high:g} m of tissue{fix}")
    out += point_held(scene)
    out += [line for line in small_tools(scene) if line.split(":")[0] not in {p.split(":")[0] for p in out}]
    tables = [m for _, m in scene.zones] if scene.zones else [scene.material]
    for i, m in enumerate(tables):
        where = f"material[{i}]" if scene.zones else "material"
        for key, unit, hint in (
            ("young", "Pa", "in Pa: 1 kPa = 1e3, 1 MPa = 1e6"),
            ("density", "kg/m^3", "in kg/m^3: 1 g/cm^3 = 1000"),
        ):
            v, (low, high) = getattr(m, key), TISSUE_RANGES[key]
            if not low <= v <= high:
                out.append(f"{where}.{key} = {v:g} {unit}: soft tissue spans {low:g} to {high:g} ({hint})")
    return out


#: What an organ's mesh spans, in m across and m^3 (a 1 cm node of 0.1 mL to a 50 cm liver of 20 L): the
#: range ``units_hint`` reads a file's units by, and the one its hint states.
ORGAN_SIZE = (0.01, 0.5)
ORGAN_VOLUME = (1e-7, 2e-2)
#: The length units a mesh file may be in, with the [mesh] scale that reads each as metres.
FILE_UNITS = (("millimetres", 0.001), ("centimetres", 0.01), ("decimetres", 0.1), ("metres", 1.0))


def _volume(v: float) -> str:
    """A volume in m^3 as a user says it: mL below a litre, L above."""
    return f"{v * 1e6:.3g} mL" if v < 1e-3 else f"{v * 1e3:.3g} L"


def units_hint(extent: float, volume: float) -> str:
    """What a mesh file ``extent`` units across, of ``volume`` cubic units (read as metres), is likely
    in: each unit of FILE_UNITS that makes it an organ by both its size and its volume (ORGAN_SIZE,
    ORGAN_VOLUME), with the scale that reads it so and the size and volume it gives. SOFA's liver2.msh,
    2.1 units across and 1.1 cubic units, is a 2.1 cm organ of 1.1 mL or a 21 cm one of 1.1 L (a human
    liver is about 1.5 L), not a 2.1 mm one."""
    fits = [
        (u, f)
        for u, f in FILE_UNITS
        if f != 1.0
        and ORGAN_SIZE[0] <= extent * f <= ORGAN_SIZE[1]
        and ORGAN_VOLUME[0] <= volume * f**3 <= ORGAN_VOLUME[1]
    ]
    organ = (
        f"{ORGAN_SIZE[0] * 100:g} to {ORGAN_SIZE[1] * 100:g} cm across, "
        f"{_volume(ORGAN_VOLUME[0])} to {_volume(ORGAN_VOLUME[1])}"
    )
    if not fits:
        return f"set [mesh] scale to the metres in one of the file's units (an organ is {organ})"
    said = " or ".join(f"{u} (scale = {f:g}: {extent * f:.3g} m across, {_volume(volume * f**3)})" for u, f in fits)
    return f"if the file is in {said}, set it in [mesh] (the units that make it an organ: {organ})"


#: A tool holding fewer vertices than this is warned of (``small_tools``): a patch of a few triangles.
SMALL_TOOL = 6


def point_held(scene: Scene) -> list[str]:
    """One line per constraint or tool that holds vertices but no triangle (no face of a tetrahedron with
    its three vertices held): a displacement prescribed at points or along edges. A set of dimension
    below two has no capacity in 3D elasticity (no finite-energy field takes a prescribed value there),
    so every refinement of the mesh lets the body move more freely around it: the truth has no limit,
    its bar grows as it is refined (SOFA's liver pressed 4 mm at one vertex: 0.45, then 0.62 adapted
    once), and no model can be judged against it."""
    from itertools import combinations

    from reference.problem import Displacement

    mesh = scene.mesh
    faces = mesh.tets[:, list(combinations(range(4), 3))].reshape(-1, 3)
    held = [(f"fixed[{i}]", fx.region) for i, fx in enumerate(scene.problem.fixed)]
    held += [(f"load[{i}]", ld.region) for i, ld in enumerate(scene.problem.loads) if isinstance(ld, Displacement)]
    out = []
    for table, region in held:
        chosen = np.zeros(mesh.n_vertices, dtype=bool)
        chosen[region.vertices(mesh)] = True
        n = int(chosen.sum())
        if chosen.any() and not chosen[faces].all(axis=1).any():
            out.append(
                f"{table}: {region.describe()} holds {n} vertex{'es' if n > 1 else ''} and no face between them: "
                "a displacement held at points or along edges has no limit under refinement (in 3D a point "
                "has no stiffness), so no truth converges on it; make the region hold at least one face"
            )
    return out


def small_tools(scene: Scene) -> list[str]:
    """One line per tool (a [[load]] of prescribed displacement) holding a face but fewer than SMALL_TOOL
    vertices: a truth exists, but the tool is a few triangles whose rim, where the error lives, is a
    vertex or two wide on the scene's mesh."""
    from reference.problem import Displacement

    out = []
    for i, ld in enumerate(scene.problem.loads):
        if isinstance(ld, Displacement) and 0 < (n := len(ld.region.vertices(scene.mesh))) < SMALL_TOOL:
            out.append(
                f"load[{i}]: {ld.region.describe()} holds {n} vertices: a tool this small is a few triangles of "
                "this mesh, its rim (where the error lives) a vertex or two wide, so the models' errors and tool "
                "forces under it depend on the mesh more than on the model; a finer mesh or a wider tool resolves it"
            )
    return out


#: How many positions along its travel a rigid tool's approach to the body is measured at.
TOOL_PATH_SAMPLES = 65


def check_tools(scene: Scene) -> None:
    """SceneError, before any work, for a rigid tool ([[tool]]) that starts inside the body (a surface
    vertex inside it at t = 0, or its centre inside the body) or that never touches the body's rest
    shape along its travel (sampled at TOOL_PATH_SAMPLES positions): the first has no contact problem
    to start from, the second no contact."""
    from meshes.regions import locate

    if not scene.problem.contacts:
        return
    mesh = scene.mesh
    surface = mesh.points[mesh.surface_vertices]
    tol = 1e-9 * float(np.ptp(mesh.points, axis=0).max())
    for i, tool in enumerate(scene.problem.contacts):
        where = f"{scene.path}: tool[{i}]"
        start = tool.gap(surface, 0.0)
        k = int(np.argmin(start))
        inside = tool.shape != "plane" and locate(mesh, np.asarray([tool.center], dtype=float))[0] >= 0
        if start[k] < -tol or inside:
            at = (
                f"its center {list(tool.center)} lies in the body"
                if inside
                else f"the body's surface point {np.round(surface[k], 6).tolist()} m lies {-start[k]:.3g} m inside it"
            )
            raise SceneError(
                f"{where}: the {tool.shape} starts inside the body ({at}); place it outside at t = 0 and let travel bring it in"
            )
        closest = min(float(tool.gap(surface, s).min()) for s in np.linspace(0.0, 1.0, TOOL_PATH_SAMPLES))
        if closest > tol:
            raise SceneError(
                f"{where}: the {tool.shape} never touches the body: along its travel {list(tool.travel)} m it comes no "
                f"closer than {closest:.3g} m to the body's rest shape; lengthen travel or move the tool"
            )


def zone_index(scene: Scene, mesh: TetMesh) -> np.ndarray:
    """The [[material]] table of each tetrahedron of ``mesh`` (the scene's own, level 0): (M,) int64,
    the last table whose region holds it. A box, sphere or ``all`` holds the tetrahedra whose centroid
    it contains; a tag, the tetrahedra of that volume group of the mesh file (a gmsh physical volume,
    a medit reference); a field, those whose value of that cell field of the file lies in [min, max].
    SceneError for a tetrahedron no table holds, a table that holds none, or a tag or field the mesh
    does not have."""
    index = np.full(mesh.n_tets, -1, dtype=np.int64)
    centroids = mesh.points[mesh.tets].mean(axis=1)
    for k, (region, _) in enumerate(scene.zones):
        if isinstance(region, FieldRegion):
            try:
                held = region.cells(mesh)
            except KeyError as exc:
                raise SceneError(f"{scene.path}: material[{k}].field.name: {exc.args[0]}") from None
        elif isinstance(region, TagRegion):
            if region.name not in mesh.cell_tags:
                known = ", ".join(sorted(mesh.cell_tags)) or "none"
                raise SceneError(
                    f"{scene.path}: material[{k}].tag: {region.name!r} is not a volume group of the mesh "
                    f"(its volume groups: {known}); a material needs tetrahedra"
                )
            held = np.asarray(mesh.cell_tags[region.name], dtype=np.int64)
        else:
            held = np.flatnonzero(region.contains(centroids, mesh))
        if len(held) == 0:
            raise SceneError(
                f"{scene.path}: material[{k}]: the region {region.describe()} holds no tetrahedron's centroid"
            )
        index[held] = k
    orphan = np.flatnonzero(index < 0)
    if len(orphan):
        raise SceneError(
            f"{scene.path}: material: {len(orphan)} tetrahedra have no material, tetrahedron {orphan[0]} with "
            f"centroid {np.round(centroids[orphan[0]], 9).tolist()} among them; add a first [[material]] with "
            "all = true for the host tissue"
        )
    return index


def build_mesh(spec: dict, scene_path: Path) -> TetMesh:
    gen = spec["generator"]
    if gen == "file":
        f = Path(spec["file"])
        if not f.is_absolute():
            f = scene_path.parent / f
        try:
            return read_mesh(f, scale=spec.get("scale", 1.0))
        except (InvalidMeshError, FileNotFoundError) as exc:
            raise SceneError(f"{scene_path}: mesh.file: {exc}") from None
    params = {k: v for k, v in spec.items() if k != "generator"}
    try:
        return get_mesh(gen, params)
    except InputError as exc:  # the generators' checks of their parameters, an invalid mesh
        raise SceneError(f"{scene_path}: mesh: {exc}") from None
    except Exception as exc:
        if type(exc) is not Exception:  # gmsh raises exactly Exception when it cannot mesh; others are bugs
            raise
        raise SceneError(f"{scene_path}: mesh: gmsh cannot mesh {gen} {params} ({exc})") from None


def check_regions(scene: Scene, mesh: TetMesh) -> None:
    """Every region must hold a vertex; no component of a vertex may be both fixed and driven by a
    tool (a roller on y beside a tool pulling x is fine); on a static scene every disconnected part of
    the mesh must be held by a fixed region or a tool (a free part has no equilibrium)."""
    fixed = np.zeros((mesh.n_vertices, 3), dtype=bool)
    held = np.zeros(mesh.n_vertices, dtype=bool)
    for i, fx in enumerate(scene.problem.fixed):
        idx = _vertices(scene, mesh, fx.region, f"fixed[{i}]")
        fixed[idx] |= component_mask(fx.components).astype(bool)
        held[idx] = True
    for i, ld in enumerate(scene.problem.loads):
        if isinstance(ld, Gravity):
            continue
        idx = _vertices(scene, mesh, ld.region, f"load[{i}]")
        if isinstance(ld, (Force, Traction)):
            inside = np.zeros(mesh.n_vertices, dtype=bool)
            inside[idx] = True
            if not np.all(inside[mesh.boundary], axis=1).any():
                raise SceneError(
                    f"{scene.path}: load[{i}]: the region {ld.region.describe()} holds {len(idx)} vertices but "
                    f"no boundary triangle with all three of its vertices inside, so the {ld.__class__.__name__.lower()} "
                    "has no surface to act on; enlarge the region"
                )
        if isinstance(ld, Displacement):
            held[idx] = True
            clash = fixed[idx] & component_mask(ld.components).astype(bool)
            if clash.any():
                k = int(np.argmax(clash.any(axis=1)))
                v, c = int(idx[k]), "xyz"[int(np.argmax(clash[k]))]
                raise SceneError(
                    f"{scene.path}: load[{i}]: the displacement region drives component {c} of vertex {v} "
                    f"{mesh.points[v].tolist()}, which a fixed region holds; make them disjoint"
                )
    n_parts, part = mesh.parts()
    if n_parts > 1 and scene.time.mode == "static" and not scene.manufactured:
        for k in range(n_parts):
            if not held[part == k].any():
                pts = mesh.points[part == k]
                raise SceneError(
                    f"{scene.path}: mesh.file: part {k + 1} of the mesh's {n_parts} disconnected parts "
                    f"({len(pts)} vertices, from {np.round(pts.min(axis=0), 6).tolist()} to "
                    f"{np.round(pts.max(axis=0), 6).tolist()}) touches no fixed region and no tool: "
                    "it has no static equilibrium"
                )


def _vertices(scene, mesh, region, where):
    try:
        idx = region.vertices(mesh)
    except KeyError as exc:
        raise SceneError(f"{scene.path}: {where}.tag: {exc.args[0]}") from None
    if len(idx) == 0:
        lo, hi = mesh.bounding_box()
        raise SceneError(
            f"{scene.path}: {where}.{region.describe().split(' ')[0]}: the region "
            f"{region.describe()} holds no vertex (the mesh spans {lo.tolist()} to {hi.tolist()})"
        )
    return idx
