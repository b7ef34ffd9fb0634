"""What every seeds experiment shares: the two sizes, the scenes of the source documents, the settled runs
(cached on disk like every other run), the reference and its bar, and the shape of a finding."""

from __future__ import annotations

import copy
import json
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from meshes.io import atomic_savez
from realtime import NotConvergedError
from realtime.geometry import signed_volumes
from realtime.models import corotational_tm, linear_tm, stvk_tm
from verification.cache import entry, read_cached
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.simulate import run_model
from verification.runs.store import run_key
from verification.scene import SCENES_DIR, Scene
from verification.scene_file import parse, resolve

SEEDS_SCENES = SCENES_DIR / "seeds"

#: An error this many times the reference's estimate is a measured difference, not reference noise.
MEASURABLE = 10.0

#: Two models' answers this far apart (relative L2) deform visibly differently.
DIFFER = 0.01

#: A hybrid threshold keeps the non-linear answer when its departure from StVK tensor-mass is at most
#: this share of the all-linear departure.
KEEPS_NONLINEAR = 0.25


@dataclass(frozen=True)
class Size:
    """How big each experiment's runs are (``FULL`` for ``tissuebench seeds``, ``SMALL`` for tests)."""

    name: str
    reference: dict  # reference_result options
    rotation_h: float  # m, the cube of experiment 1
    rotation_angles: tuple  # degrees
    twist_h: float  # m, the cylinder of experiment 2
    twist_angles: tuple  # degrees
    tube_h: float  # m
    tube_force: float  # N, sideways on the tube's top
    livers: tuple  # scene names or seed files of experiment 4
    liver_force: float  # N, scale of the force on each liver (1: the scene's)
    hybrid_scene: str
    hybrid_fractions: tuple  # thresholds as fractions of the reference's largest displacement
    remesh_h: tuple  # m, the beam of experiment 6 meshed at each h (first one also refined once)
    spring_youngs: tuple  # Pa
    spring_levels: tuple  # uniform refinements of the spring block
    rate_levels: tuple  # uniform refinements of the rates beam
    speedup_scene: str
    speedup_h: float  # m, its mesh size


FULL = Size(
    name="full",
    reference=dict(REFERENCE_DEFAULTS),
    rotation_h=0.01,
    rotation_angles=tuple(range(0, 181, 15)),
    twist_h=0.004,
    twist_angles=(45, 90, 135, 180),
    tube_h=0.004,
    tube_force=0.03,
    livers=("liver", "sofa-liver-force"),
    liver_force=1.0,
    hybrid_scene="liver",
    hybrid_fractions=(0.0, 0.1, 0.25, 0.5, 1.01),
    remesh_h=(0.005, 0.0045),
    spring_youngs=(1e4, 1e5, 1e6),
    spring_levels=(0, 1),
    rate_levels=(0, 1, 2),
    speedup_scene="cantilever-pull",
    speedup_h=0.005,
)

SMALL = Size(
    name="small",
    reference={"degree": 2, "refine": 0, "estimate": False},
    rotation_h=0.02,
    rotation_angles=(0, 30, 60, 90),
    twist_h=0.006,
    twist_angles=(4, 8),
    tube_h=0.005,
    tube_force=0.002,
    livers=("sofa-liver-force",),
    liver_force=0.02,
    hybrid_scene="sofa-liver-force",
    hybrid_fractions=(0.0, 0.5, 1.01),
    remesh_h=(0.01, 0.009),
    spring_youngs=(1e4, 1e6),
    spring_levels=(0,),
    rate_levels=(0,),
    speedup_scene="cantilever-pull",
    speedup_h=0.01,
)

TENSOR_MASS = (linear_tm.NAME, corotational_tm.NAME, stvk_tm.NAME)


def seed_scene(stem: str, suffix: str = "", edit=None, refine: int = 0) -> Scene:
    """A seeds scene (``verification/scenes/seeds/STEM.toml``, else a built-in scene or a path), its
    TOML data passed through ``edit(data)`` (which changes it in place) and its name given ``suffix``."""
    path = SEEDS_SCENES / f"{stem}.toml"
    if not path.exists():
        path = resolve(stem)
    data = copy.deepcopy(tomllib.loads(path.read_text()))
    if edit is not None:
        edit(data)
    data["name"] = data.get("name", stem) + suffix
    return parse(path, data).refined(refine + data["mesh"].get("refine", 0))


#: Steps a model may take to settle in these experiments; runs that need more are reported as such.
SETTLE_STEPS = 300_000


def _settled(
    scene: Scene, model: str, ref_opts: dict, options: dict | None = None, allow_unsettled: bool = False
) -> tuple[np.ndarray | None, dict]:
    """A model's settled answer on a static scene, (N, 3) m, and its run's metadata (step_us, settle
    steps, dt ...), cached like every run (``runs.run_key``). A run that does not settle within
    SETTLE_STEPS is cached too: with ``allow_unsettled`` it gives (None, {"unsettled": why}), else
    NotConvergedError."""
    opts = {"settled": True, "max_steps": SETTLE_STEPS, **(options or {})}
    key = run_key(scene, model, "symplectic-euler", None, None, ref_opts, False, opts)
    path = entry("runs", f"{scene.name}-{model}-settled", key, ".npz")
    kept = read_cached(path, _read_settled)
    if kept is None:
        try:
            res = run_model(scene, model, options=options, max_steps=SETTLE_STEPS)
            u, meta = res.displacement[0], json.loads(json.dumps(res.meta, default=str))
        except NotConvergedError as exc:
            u, meta = np.zeros((0, 3)), {"unsettled": " ".join(str(exc).split()), **_step_time(scene, model, options)}
        atomic_savez(path, u=u, meta=json.dumps(meta))
    else:
        u, meta = kept
    if "unsettled" in meta:
        if not allow_unsettled:
            raise NotConvergedError(f"{scene.name}: {meta['unsettled']}")
        return None, meta
    return u, meta


def _read_settled(path: Path) -> tuple[np.ndarray, dict]:
    """(u, meta) of a settled run as _settled keeps it."""
    with np.load(path) as z:
        return z["u"], json.loads(str(z["meta"]))


def _step_time(scene: Scene, model: str, options: dict | None) -> dict:
    """The step time of a run that did not settle: symplectic Euler at 0.9 of the rest critical step,
    timed from rest like every run (``runs.simulate.time_steps``), with the integrator named as a run's
    meta names it (the rates study read it, and failed with a KeyError on an unsettled hybrid-tm)."""
    from verification.engines import engine_for
    from verification.inputs import scene_inputs
    from verification.runs.simulate import EXPLICIT_FRACTION, time_steps

    sim = engine_for(model).build(scene_inputs(scene), model, "symplectic-euler", dict(options or {}))
    dt = EXPLICIT_FRACTION * sim.critical_dt()
    sim.start(dt)
    return {"dt": dt, "integrator": "symplectic-euler", **time_steps(sim)}


def _ref(scene: Scene, size: Size):
    ref = reference_result(scene, **size.reference)
    return ref.displacement[0], ref.meta.get("ref_err_estimate")


def _reference_info(estimates: list, kind: str = "dolfinx") -> dict:
    known = [e for e in estimates if e is not None]
    return {
        "kind": kind,
        "ref_err_estimate": max(known) if known and len(known) == len(estimates) else None,
        "verified": bool(known) and len(known) == len(estimates),
    }


def _volume_change(points: np.ndarray, tets: np.ndarray, u: np.ndarray) -> float:
    """(V(x + u) - V(x)) / V(x), the body's relative change of volume."""
    v0 = signed_volumes(points, tets).sum()
    return float(signed_volumes(points + u, tets).sum() / v0 - 1.0)


def _finding(number: int, key: str, title: str, source: str, claim: str, rule: str) -> dict:
    return {
        "number": number,
        "key": key,
        "title": title,
        "source": source,
        "claim": claim,
        "rule": rule,
        "plots": [],
        "table": [],
    }


def _slope(x, y) -> float:
    return float(np.polyfit(np.log(x), np.log(y), 1)[0])
