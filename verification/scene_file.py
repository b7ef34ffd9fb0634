"""Scene files (docs/data-flow.md): TOML -> a validated ``Scene``.

Every unknown key, missing key and bad value is a ``SceneError`` whose one-line message names the
file, the key (dotted, with table indices: ``load[1].kind``) and the allowed values; a file's errors
come in one message, each unknown key with its closest valid one. Nothing in a scene is evaluated as
code.
"""

from __future__ import annotations

import difflib
import math
import tomllib
from pathlib import Path

import numpy as np

from meshes.regions import AllRegion, BoxRegion, FieldRegion, Region, SphereRegion, TagRegion
from realtime.material import LAWS, Material, MaterialError
from reference.problem import (
    COMPONENTS,
    RAMP_SHAPES,
    TOOL_SHAPES,
    Displacement,
    Fixed,
    Force,
    Gravity,
    Problem,
    RigidTool,
    Traction,
)
from verification.scene import SCENES_DIR, Scene, SceneError, TimeSpec

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


def _rigid_tool(r: _Reader) -> RigidTool:
    """A [[tool]] table: a rigid shape pressed on the body (reference.problem.RigidTool)."""
    shape = r.string("shape", TOOL_SHAPES)
    keys = {"sphere": ("radius",), "capsule": ("radius", "end"), "plane": ("normal",)}[shape]
    fields = {"center": r.vec3("center"), "travel": r.vec3("travel", [0.0, 0.0, 0.0])}
    fields["ramp"] = r.number("ramp", 0.0, nonneg=True)
    fields["ramp_shape"] = r.string("ramp_shape", RAMP_SHAPES, default="linear")
    if "radius" in keys:
        fields["radius"] = r.number("radius", positive=True)
    if "end" in keys:
        fields["end"] = r.vec3("end")
        length = float(np.linalg.norm(np.subtract(fields["end"], fields["center"])))
        if not length > 1e-9 * fields["radius"]:
            r.fail("end", f"= {list(fields['end'])} is the center: a capsule of length {length:g} m is a sphere")
    if "normal" in keys:
        normal = np.asarray(r.vec3("normal"))
        if not np.linalg.norm(normal) > 0:
            r.fail("normal", "must be a non-zero vector")
        fields["normal"] = tuple(normal / np.linalg.norm(normal))
    stations = r.get("stations", 0)
    if not (isinstance(stations, int) and not isinstance(stations, bool) and 0 <= stations <= 50):
        r.fail(
            "stations", f"must be a whole number from 0 to 50 (points of the force-indentation curve), got {stations!r}"
        )
    fields["stations"] = stations
    r.finish(("shape", "center", "travel", "ramp", "ramp_shape", "stations") + keys)
    return RigidTool(shape, **fields)


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
    contacts = [t for t in (errors.section(_rigid_tool, tr) for tr in errors.section(_tables, top, "tool") or []) if t]
    tspec = errors.section(_time, top)
    manufactured = errors.section(_manufactured, top) if top.has("manufactured") else None
    events = errors.section(_events, top, tspec and tspec.mode) or ()
    errors.section(
        top.finish,
        ("name", "description", "mesh", "material", "fixed", "load", "tool", "time", "manufactured", "event"),
    )
    errors.check()
    if contacts and (tspec.mode != "static" or events):
        what = "a dynamic scene" if tspec.mode != "static" else "a scene with events"
        top.fail("tool", f"a rigid tool is solved in a static scene without events; this is {what}")
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
        Problem(tuple(fixed), tuple(loads), tuple(contacts)),
        tspec,
        raw=data,
        manufactured=manufactured,
        zones=zones,
        events=events,
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
    if gen == "box" and mr.has("fine"):
        fine = _Reader(top.path, mr.get("fine"), mr.key("fine"))
        spec["fine"] = {"point": list(fine.vec3("point")), "h": fine.number("h", positive=True)}
        spec["fine"]["radius"] = fine.number("radius", 0.0, nonneg=True)
        fine.finish(("point", "h", "radius"))
        if not spec["fine"]["h"] < spec["h"]:
            fine.fail("h", f"= {spec['fine']['h']!r} must be below the mesh's h = {spec['h']!r}")
    mr.finish(("generator", "refine") + (("fine",) if gen == "box" else ()) + tuple(MESH_PARAMS[gen]))
    if gen == "tube" and not spec["inner_radius"] < spec["outer_radius"]:
        mr.fail("inner_radius", f"{spec['inner_radius']!r} must be below outer_radius = {spec['outer_radius']!r}")
    if gen != "file":
        n_tets = _volume(spec) / (spec["h"] ** 3 / (6.0 * math.sqrt(2.0))) + _graded_tets(spec)
        if n_tets > MAX_TETS:
            key = "fine" if "fine" in spec else "h"
            mr.fail(key, f"{spec[key]!r} would make about {n_tets:.1e} tetrahedra (the limit is {MAX_TETS:.0e})")
    return spec


def _graded_tets(spec: dict) -> float:
    """An upper estimate of the tetrahedra a box's fine region adds (``meshes.generators.box``): the
    regular tetrahedra of the local edge length over the whole ball where it is below the mesh's h."""
    from meshes.generators import GRADE

    if "fine" not in spec:
        return 0.0
    h, fine = spec["h"], spec["fine"]
    r = np.linspace(0.0, fine["radius"] + (h - fine["h"]) / GRADE, 4001)
    size = np.minimum(h, fine["h"] + GRADE * np.maximum(r - fine["radius"], 0.0))
    density = 4.0 * math.pi * r**2 / (size**3 / (6.0 * math.sqrt(2.0)))
    return float(np.sum(0.5 * (density[1:] + density[:-1]) * np.diff(r)))


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


def _event(r: _Reader):
    """One [[event]] table: a cut (a plane, a box bounding the part cut) or a suture (a box bounding the
    lips joined) at a time > 0 s (``verification.events``)."""
    from verification.events import EVENT_KINDS, Event

    time = r.number("time", positive=True)
    kind = r.string("kind", EVENT_KINDS)
    box = None
    if r.has("box"):
        region = _region(r, ("box",))
        box = (region.lo, region.hi)
    if kind == "suture":
        r.finish(("time", "kind", "box"))
        return Event(time, kind, box=box)
    plane = _Reader(r.path, r.get("plane"), r.key("plane"))
    point, normal = plane.vec3("point"), np.asarray(plane.vec3("normal"))
    if not np.linalg.norm(normal) > 0:
        plane.fail("normal", "must be a non-zero vector")
    plane.finish(("point", "normal"))
    r.finish(("time", "kind", "plane", "box"))
    return Event(time, kind, point, tuple((normal / np.linalg.norm(normal)).tolist()), box)


def _events(top: _Reader, mode: str | None) -> tuple:
    """The [[event]] tables in time order: a static scene's states (a dynamic scene takes none yet)."""
    tables = _tables(top, "event")
    if tables and mode == "dynamic":
        top.fail("event", "cuts and sutures are events of a static scene (mode = 'static'); a dynamic one takes none")
    events = sorted((_event(t) for t in tables), key=lambda e: e.time)
    if events and events[0].kind == "suture":
        top.fail("event", f"the first event (t = {events[0].time:g} s) is a suture: there is no cut to join yet")
    return tuple(events)


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
