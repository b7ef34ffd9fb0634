"""Scene files (docs/architecture.md section 3): TOML -> a validated ``Scene``.

Every unknown key, missing key and bad value is a ``SceneError`` whose one-line message names the
file, the key (dotted, with table indices: ``load[1].kind``) and the allowed values. Nothing in a
scene is evaluated as code.
"""

from __future__ import annotations

import dataclasses
import difflib
import hashlib
import json
import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from meshes import InvalidMeshError, TetMesh, get_mesh, read_mesh
from meshes.regions import AllRegion, BoxRegion, FieldRegion, Region, SphereRegion, TagRegion
from realtime.errors import InputError
from realtime.material import LAWS, Material, MaterialError, Materials
from reference.problem import (
    COMPONENTS,
    RAMP_SHAPES,
    Displacement,
    Fixed,
    Force,
    Gravity,
    Problem,
    Traction,
    component_mask,
)

SCENES_DIR = Path(__file__).parent / "scenes"

MESH_PARAMS = {
    "box": {"size": "vec3", "h": "length"},
    "grid": {"size": "vec3", "h": "length"},
    "cylinder": {"radius": "length", "length": "length", "h": "length"},
    "tube": {"inner_radius": "length", "outer_radius": "length", "length": "length", "h": "length"},
    "liver": {"scale": "positive", "h": "length"},
    "file": {"file": "str", "scale": "positive"},
}
#: Mesh keys that may be left out, with their default.
MESH_OPTIONAL = {("file", "scale"): 1.0}
#: The most tetrahedra a generated mesh may have (estimated before gmsh runs): about 2 GB of P2 reference.
MAX_TETS = 2_000_000
#: The most uniform refinements a scene may ask for (each multiplies the tetrahedra by 8).
MAX_REFINE = 4
LOAD_KINDS = ("gravity", "force", "traction", "displacement")
MODES = ("static", "dynamic")


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
        mesh = self.mesh.sha256() + self.mesh.tags_sha256()
        return hashlib.sha256((text + parsed + mesh).encode()).hexdigest()

    def refined(self, levels: int = 1) -> Scene:
        """This scene on its mesh cut uniformly ``levels`` more times (``TetMesh.refined``: h halves at
        each level, the coarser vertices come first), its regions carried by the rule the reference
        applies to its own refined meshes (``meshes.regions.spanned``: a refined vertex belongs to a
        region when the base vertices of its edge or face do), so that every level poses the base
        scene's problem (docs/architecture.md section 3). The reference of a refined scene is the
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


def builtin_scenes() -> dict[str, Path]:
    """Built-in scene names -> files."""
    return {p.stem: p for p in sorted(SCENES_DIR.glob("*.toml"))}


def resolve(name_or_path: str) -> Path:
    """A built-in scene's file by stem, or a path to a .toml file."""
    p = Path(name_or_path)
    if p.suffix == ".toml":
        if not p.exists():
            raise SceneError(f"{p}: no such scene file")
        return p
    scenes = builtin_scenes()
    if name_or_path not in scenes:
        raise SceneError(f"{name_or_path}: not a built-in scene (known: {', '.join(scenes)}) nor a .toml path")
    return scenes[name_or_path]


def _is_vec3(v) -> bool:
    """A list of three finite numbers (booleans are not numbers here)."""
    return (
        isinstance(v, list)
        and len(v) == 3
        and all(isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in v)
    )


class _Reader:
    """Typed access to a TOML table that records the keys it read, so leftovers are errors."""

    def __init__(self, path: Path, table: dict, where: str):
        self.path, self.table, self.where = path, table, where
        if not isinstance(table, dict):
            self.fail("", f"must be a table, got {type(table).__name__}")
        self.used: set[str] = set()

    def key(self, k: str) -> str:
        return f"{self.where}.{k}" if self.where else k

    def fail(self, k: str, msg: str):
        raise SceneError(f"{self.path}: {self.key(k) if k else self.where}: {msg}")

    def has(self, k):
        return k in self.table

    def get(self, k, default=...):
        self.used.add(k)
        if k not in self.table:
            if default is ...:
                near = difflib.get_close_matches(k, [str(t) for t in self.table if t != k], n=1, cutoff=0.75)
                if near:  # a misspelling: name the key the file has, and the one it meant
                    self.fail(near[0], f"unknown key, did you mean {k!r}? ({k} is required)")
                self.fail(k, "missing key")
            return default
        return self.table[k]

    def number(self, k, default=..., positive=False, nonneg=False):
        v = self.get(k, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v):
            self.fail(k, f"must be a number, got {v!r}")
        if positive and not v > 0:
            self.fail(k, f"must be > 0, got {v!r}")
        if nonneg and v < 0:
            self.fail(k, f"must be >= 0, got {v!r}")
        return float(v)

    def vec3(self, k, default=...):
        v = self.get(k, default)
        if not _is_vec3(v):
            self.fail(k, f"must be a list of 3 finite numbers, got {v!r}")
        return tuple(float(x) for x in v)

    def string(self, k, allowed=None, default=...):
        v = self.get(k, default)
        if not isinstance(v, str):
            self.fail(k, f"must be a string, got {v!r}")
        if allowed is not None and v not in allowed:
            near = difflib.get_close_matches(v, list(allowed), n=1, cutoff=0.6)
            hint = f" (did you mean {near[0]!r}?)" if near else ""
            self.fail(k, f"{v!r} is not one of {', '.join(allowed)}{hint}")
        return v

    def finish(self, allowed: tuple[str, ...] | None = None):
        """Fail naming every key of the table that was not read, each with its closest allowed key."""
        extra = sorted(set(self.table) - self.used)
        if extra:
            valid = sorted(allowed if allowed is not None else self.used)
            names = []
            for k in extra:
                near = difflib.get_close_matches(k, valid, n=1, cutoff=0.6)
                names.append(f"{self.key(k)}: unknown key" + (f", did you mean {near[0]!r}?" if near else ""))
            raise SceneError(f"{self.path}: " + "; ".join(names) + f" (allowed: {', '.join(valid)})")


class _Errors:
    """The errors of one scene file, gathered section by section ([mesh], each [[load]], ...), so that
    one message names them all instead of one per run."""

    def __init__(self, path: Path):
        self.path, self.items = path, []

    def section(self, fn, *args):
        """fn(*args), or None with its SceneError kept."""
        try:
            return fn(*args)
        except SceneError as exc:
            self.items.append(str(exc).removeprefix(f"{self.path}: "))
            return None

    def check(self):
        if len(self.items) == 1:
            raise SceneError(f"{self.path}: {self.items[0]}")
        if self.items:
            raise SceneError(f"{self.path}: {len(self.items)} errors: " + "; ".join(self.items))


REGION_KEYS = ("box", "sphere", "tag", "all")
#: A [[material]] table may also take the tetrahedra by a range of a cell field of the mesh file.
MATERIAL_REGION_KEYS = (*REGION_KEYS, "field")


def _region(r: _Reader, keys: tuple[str, ...] = REGION_KEYS) -> Region:
    given = [k for k in keys if r.has(k)]
    if len(given) != 1:
        r.fail("", f"needs exactly one region key of {', '.join(keys)}, got {given or 'none'}")
    kind = given[0]
    if kind == "field":
        sub = _Reader(r.path, r.get("field"), r.key("field"))
        lo, hi = sub.number("min"), sub.number("max")
        if lo > hi:
            sub.fail("min", f"{lo!r} exceeds max {hi!r}")
        region = FieldRegion(sub.string("name"), lo, hi)
        sub.finish(("name", "min", "max"))
        return region
    if kind == "box":
        v = r.get("box")
        if not (isinstance(v, list) and len(v) == 2 and all(_is_vec3(c) for c in v)):
            r.fail("box", f"must be [[xmin, ymin, zmin], [xmax, ymax, zmax]] of finite numbers, got {v!r}")
        lo, hi = np.asarray(v[0], float), np.asarray(v[1], float)
        if np.any(lo > hi):
            r.fail("box", f"min corner {lo.tolist()} exceeds max corner {hi.tolist()}")
        return BoxRegion(tuple(lo), tuple(hi))
    if kind == "sphere":
        sub = _Reader(r.path, r.get("sphere"), r.key("sphere"))
        region = SphereRegion(sub.vec3("center"), sub.number("radius", positive=True))
        sub.finish(("center", "radius"))
        return region
    if kind == "tag":
        return TagRegion(r.string("tag"))
    if r.get("all") is not True:
        r.fail("all", "must be true")
    return AllRegion()


def _components(r: _Reader) -> tuple[str, ...]:
    v = r.get("components", list(COMPONENTS))
    if not (isinstance(v, list) and v and all(c in COMPONENTS for c in v) and len(set(v)) == len(v)):
        r.fail("components", f"must be a non-empty list of distinct x, y, z, got {v!r}")
    return tuple(c for c in COMPONENTS if c in v)


def _load(r: _Reader):
    kind = r.string("kind", LOAD_KINDS)
    if kind == "gravity":
        load = Gravity(r.vec3("value"))
        r.finish(("kind", "value"))
        return load
    region = _region(r)
    if kind in ("force", "traction"):
        load = (Force if kind == "force" else Traction)(region, r.vec3("value"))
        r.finish(("kind", "value") + REGION_KEYS)
        return load
    comps = _components(r)
    ramp = r.number("ramp", 0.0, nonneg=True)
    shape = r.string("ramp_shape", RAMP_SHAPES, default="linear")
    if r.has("value") == r.has("rotation"):
        r.fail("", "a displacement needs exactly one of value (a translation) or rotation")
    if r.has("value"):
        load = Displacement(region, comps, translation=r.vec3("value"), ramp=ramp, ramp_shape=shape)
    else:
        sub = _Reader(r.path, r.get("rotation"), r.key("rotation"))
        axis = np.asarray(sub.vec3("axis"))
        if not np.linalg.norm(axis) > 0:
            sub.fail("axis", "must be a non-zero vector")
        load = Displacement(
            region,
            comps,
            axis=tuple(axis / np.linalg.norm(axis)),
            center=sub.vec3("center"),
            angle=sub.number("angle"),
            ramp=ramp,
            ramp_shape=shape,
        )
        sub.finish(("axis", "center", "angle"))
    r.finish(("kind", "value", "rotation", "ramp", "ramp_shape", "components") + REGION_KEYS)
    return load


def _tables(r: _Reader, key: str) -> list[_Reader]:
    v = r.get(key, [])
    if not isinstance(v, list):
        r.fail(key, f"must be an array of tables ([[{key}]]), got {type(v).__name__}")
    return [_Reader(r.path, t, f"{key}[{i}]") for i, t in enumerate(v)]


def parse(path: Path, data: dict) -> Scene:
    """Validate parsed TOML ``data`` read from ``path``; every section's errors in one SceneError."""
    errors = _Errors(path)
    top = _Reader(path, data, "")
    name = errors.section(top.string, "name", None, path.stem)
    description = errors.section(top.string, "description", None, "")
    spec = errors.section(_mesh_spec, top)
    material, zones = errors.section(_materials, top) or (None, None)
    fixed = [f for f in (errors.section(_fixed, fr) for fr in errors.section(_tables, top, "fixed") or []) if f]
    loads = [ld for ld in (errors.section(_load, lr) for lr in errors.section(_tables, top, "load") or []) if ld]
    tspec = errors.section(_time, top)
    manufactured = errors.section(_manufactured, top) if top.has("manufactured") else None
    errors.section(top.finish, ("name", "description", "mesh", "material", "fixed", "load", "time", "manufactured"))
    errors.check()
    if zones and manufactured:
        top.fail("manufactured", "a manufactured solution is for one [material]; this scene has [[material]] tables")
    if (
        not fixed
        and not any(isinstance(ld, Displacement) for ld in loads)
        and tspec.mode == "static"
        and not manufactured
    ):
        raise SceneError(
            f"{path}: fixed: a static scene needs a [[fixed]] region or a displacement load "
            "(otherwise rigid motions are free and there is no equilibrium)"
        )
    return Scene(
        name,
        description,
        path,
        spec,
        material,
        Problem(tuple(fixed), tuple(loads)),
        tspec,
        raw=data,
        manufactured=manufactured,
        zones=zones,
    )


def _mesh_spec(top: _Reader) -> dict:
    """The [mesh] table: a generator and its parameters."""
    mr = _Reader(top.path, top.get("mesh"), "mesh")
    gen = mr.string("generator", tuple(MESH_PARAMS))
    spec = {"generator": gen}
    for k, kind in MESH_PARAMS[gen].items():
        if kind == "vec3":
            spec[k] = list(mr.vec3(k))
            if min(spec[k]) <= 0:
                mr.fail(k, f"every side must be > 0, got {spec[k]}")
        elif kind == "str":
            spec[k] = mr.string(k)
        else:
            spec[k] = mr.number(k, MESH_OPTIONAL.get((gen, k), ...), positive=True)
    refine = mr.get("refine", 0)
    if not (isinstance(refine, int) and not isinstance(refine, bool) and 0 <= refine <= MAX_REFINE):
        mr.fail("refine", f"must be a whole number from 0 to {MAX_REFINE} (uniform refinements), got {refine!r}")
    mr.finish(("generator", "refine") + tuple(MESH_PARAMS[gen]))
    if gen == "tube" and not spec["inner_radius"] < spec["outer_radius"]:
        mr.fail("inner_radius", f"{spec['inner_radius']!r} must be below outer_radius = {spec['outer_radius']!r}")
    if gen != "file":
        n_tets = _volume(spec) / (spec["h"] ** 3 / (6.0 * math.sqrt(2.0)))
        if n_tets > MAX_TETS:
            mr.fail("h", f"{spec['h']!r} m would make about {n_tets:.1e} tetrahedra (the limit is {MAX_TETS:.0e})")
    return spec


def _materials(top: _Reader) -> tuple[Material, tuple | None]:
    """The [material] table, or the [[material]] tables as (region, Material) zones, one law for all."""
    if not isinstance(top.table.get("material"), list):
        return _material(_Reader(top.path, top.get("material"), "material"), ()), None
    zones = [(_region(t, MATERIAL_REGION_KEYS), _material(t, MATERIAL_REGION_KEYS)) for t in _tables(top, "material")]
    if not zones:
        top.fail("material", "an empty array of tables: give [material] or at least one [[material]]")
    for i, (_, m) in enumerate(zones[1:], start=1):
        if m.law != zones[0][1].law:
            top.fail(
                f"material[{i}].law",
                f"{m.law!r} differs from material[0].law = {zones[0][1].law!r}: one law for the whole body",
            )
    return zones[0][1], tuple(zones)


def _fixed(fr: _Reader) -> Fixed:
    fixed = Fixed(_region(fr), _components(fr))
    fr.finish(("components",) + REGION_KEYS)
    return fixed


def _time(top: _Reader) -> TimeSpec:
    """The [time] table (static when absent)."""
    tr = _Reader(top.path, top.get("time", {}), "time")
    mode = tr.string("mode", MODES, default="static")
    damping = _Reader(top.path, tr.get("damping", {}), "time.damping")
    tspec = TimeSpec(
        mode=mode,
        end=tr.number("end", 1.0, positive=True),
        output_every=tr.number("output_every", 0.01, positive=True),
        damping_mass=damping.number("mass", 0.0, nonneg=True),
        damping_stiffness=damping.number("stiffness", 0.0, nonneg=True),
    )
    damping.finish(("mass", "stiffness"))
    tr.finish(("mode", "end", "output_every", "damping"))
    if mode == "dynamic":
        n_out = tspec.end / tspec.output_every
        if abs(n_out - round(n_out)) > 1e-9 * max(n_out, 1.0) or round(n_out) < 1:
            tr.fail(
                "end",
                f"{tspec.end!r} s is not a whole multiple of output_every = {tspec.output_every!r} s "
                f"({n_out:.6g} outputs): both sides are compared at the output times 0, output_every, ..., end",
            )
    return tspec


def _manufactured(top: _Reader) -> dict:
    """The [manufactured] table: the degrees and mesh sizes of a manufactured-solution study."""
    mr2 = _Reader(top.path, top.get("manufactured"), "manufactured")
    degrees = mr2.get("degrees", [1, 2])
    if not (isinstance(degrees, list) and degrees and all(d in (1, 2) for d in degrees)):
        mr2.fail("degrees", f"must be a list of 1 and/or 2, got {degrees!r}")
    sizes = _Reader(top.path, mr2.get("sizes"), "manufactured.sizes")
    per = {}
    for d in degrees:
        v = sizes.get(str(d))
        if not (isinstance(v, list) and len(v) >= 2 and all(isinstance(n, int) and n >= 1 for n in v)):
            sizes.fail(str(d), f"must be a list of at least two mesh sizes (cubes per side), got {v!r}")
        per[str(d)] = v
    sizes.finish(tuple(str(d) for d in degrees))
    mr2.finish(("degrees", "sizes"))
    return {"degrees": degrees, "sizes": per}


def _material(mat: _Reader, region_keys: tuple) -> Material:
    """One [material] table (or [[material]] entry, which also holds ``region_keys``) as a Material."""
    path = mat.path
    fields = dict(
        law=mat.string("law", LAWS),
        young=mat.number("young"),
        poisson=mat.number("poisson"),
        density=mat.number("density"),
        volume_penalty=mat.number("volume_penalty", 0.0),
    )
    if mat.has("fiber") and mat.has("fiber_around"):
        mat.fail("fiber_around", "give fibres one direction (fiber) or an axis to run around (fiber_around), not both")
    if mat.has("fiber_around"):
        around = _Reader(path, mat.get("fiber_around"), mat.key("fiber_around"))
        fields["fiber_axis"] = around.vec3("axis")
        fields["fiber_point"] = around.vec3("point", [0.0, 0.0, 0.0])
        around.finish(("axis", "point"))
        fields["young_fiber"] = mat.number("young_fiber")
        fields["fiber_shear"] = mat.number("fiber_shear", 0.0)
    elif mat.has("fiber") or mat.has("young_fiber"):
        fields["fiber"] = mat.vec3("fiber")
        fields["young_fiber"] = mat.number("young_fiber")
        fields["fiber_shear"] = mat.number("fiber_shear", 0.0)
    mat.finish(
        ("law", "young", "poisson", "density", "volume_penalty", "fiber", "fiber_around", "young_fiber", "fiber_shear")
        + region_keys
    )
    try:
        return Material(**fields)
    except MaterialError as exc:
        key = (
            str(exc)
            .split(" ", 1)[0]
            .replace("fiber_axis", "fiber_around.axis")
            .replace("fiber_point", "fiber_around.point")
        )
        raise SceneError(f"{path}: {mat.key(key)} {str(exc).split(' ', 1)[1]}") from None


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
        unit = "millimetres: scale = 0.001" if extent > high else "other units: scale = the metres in one of them"
        fix = (
            f"; if the file is in {unit} in [mesh]"
            if scene.mesh_spec["generator"] == "file"
            else " (lengths in metres)"
        )
        out.append(f"mesh: the body is {extent:.3g} m across, outside the {low:g} to {high:g} m of an organ{fix}")
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


def _volume(spec: dict) -> float:
    """The volume, m^3, of a generator's body (the liver: 1.28 litres at scale 1)."""
    gen = spec["generator"]
    if gen in ("box", "grid"):
        return float(np.prod(spec["size"]))
    if gen == "cylinder":
        return math.pi * spec["radius"] ** 2 * spec["length"]
    if gen == "tube":
        return math.pi * (spec["outer_radius"] ** 2 - spec["inner_radius"] ** 2) * spec["length"]
    return 1.28e-3 * spec["scale"] ** 3


def load_scene(name_or_path: str | Path, refine: int = 0) -> Scene:
    """Read and validate a scene by built-in name or path; raises SceneError. ``refine`` cuts its mesh
    uniformly that many more times than its ``[mesh] refine`` says (``Scene.refined``)."""
    if not (isinstance(refine, int) and 0 <= refine <= MAX_REFINE):
        raise SceneError(f"refine = {refine!r}: must be a whole number from 0 to {MAX_REFINE}")
    path = resolve(str(name_or_path))
    try:
        data = tomllib.loads(path.read_text(encoding="utf-8-sig"))  # -sig: an editor's byte-order mark
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as exc:
        raise SceneError(f"{path}: not valid TOML ({exc})") from None
    except OSError as exc:
        raise SceneError(f"{path}: cannot read it ({exc.strerror})") from None
    scene = parse(path, data)
    levels = scene.raw["mesh"].get("refine", 0) + refine
    if levels > MAX_REFINE:
        raise SceneError(
            f"{path}: mesh.refine: {levels} levels in all, at most {MAX_REFINE} (8^levels times the tetrahedra)"
        )
    return scene.refined(levels)


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
