"""The source documents' experiments: every claim of ``../shared/seeds`` measured against the ground truth.

The two documents the project started from (Xu's slides on Picinbono, Delingette and Ayache's
tensor-mass models, and Liu's survey of deformable models) make claims with pictures and tables. Each
module ``e1_...`` to ``e9_...`` reproduces one of them (docs/verification.md): it builds the scene the claim
is about, runs the real-time models and the dolfinx reference (or a closed form, where the truth has
one), and returns a finding:

- ``claim``: the claim in our words, ``source``: the document and slide;
- ``figure``: what we measured, in one line; ``data`` and ``table``: the numbers behind it;
- ``verdict``: confirmed, refuted or nuanced (undecided where a number the rule needs is missing), computed from the numbers by the rule in ``rule``, and
  ``decides``: the number that decided it;
- ``reference``: where the truth came from and its own error estimate;
- ``plots``: PNG figures (base64) where a reader would rather look than read.

Every experiment has two sizes: ``FULL`` (what ``tissuebench seeds`` runs) and ``SMALL`` (the tests':
coarse meshes, a P1 reference). Model runs are settled static solves cached on disk like every other
run (``_settled``); the reference is the cached ``reference_result``.
"""

from __future__ import annotations

import copy
import json
import time
from pathlib import Path

from meshes.io import atomic_write_text
from verification.progress import log
from verification.runs.reference import P1_OWN_MESH
from verification.scene import Scene
from verification.studies.seeds.common import FULL, Size
from verification.studies.seeds.e1_global_rotation import global_rotation
from verification.studies.seeds.e2_partial_rotation import partial_rotation, twist_scenes
from verification.studies.seeds.e3_tubes import tube_scenes, tubes
from verification.studies.seeds.e4_liver import liver, liver_scene
from verification.studies.seeds.e5_hybrid_threshold import hybrid_rates
from verification.studies.seeds.e6_remeshing import remesh_scenes, remeshing
from verification.studies.seeds.e7_critical_stiffness import critical_stiffness
from verification.studies.seeds.e8_rates import rates, rates_cells, rates_scenes
from verification.studies.seeds.e9_speedups import speedup_scene, speedups

EXPERIMENTS = {
    "global-rotation": global_rotation,
    "partial-rotation": partial_rotation,
    "tubes": tubes,
    "liver": liver,
    "hybrid-threshold": hybrid_rates,
    "tensor-mass-vs-mass-spring": remeshing,
    "critical-stiffness": critical_stiffness,
    "rates": rates,
    "speed-ups": speedups,
}

#: The scenes whose reference (``Size.reference``) each experiment asks for; the liver's also asks for
#: the P1 solution on each liver's own mesh.
REFERENCE_SCENES = {
    "partial-rotation": twist_scenes,
    "tubes": tube_scenes,
    "liver": lambda size: [liver_scene(name, size) for name in size.livers],
    "hybrid-threshold": lambda size: [liver_scene(size.hybrid_scene, size)],
    "tensor-mass-vs-mass-spring": remesh_scenes,
    "rates": rates_scenes,
    "speed-ups": lambda size: [speedup_scene(size)],
}


#: The settlings each experiment makes that are known before it runs (``prefetch.settle_ahead``'s cells).
SETTLE_CELLS = {"rates": rates_cells}


def reference_jobs(keys, size: Size) -> list[tuple[Scene, dict]]:
    """The references the experiments ``keys`` ask for, as ``prefetch.solve_references`` takes them."""
    jobs = []
    for key in keys:
        scenes = REFERENCE_SCENES.get(key, lambda size: [])(size)
        jobs += [(scene, size.reference) for scene in scenes]
        if key == "liver":
            jobs += [(scene, P1_OWN_MESH) for scene in scenes]
    return jobs


def run_seeds(only=None, size: Size = FULL) -> dict:
    """Run the experiments (all, or the keys in ``only``) and return {"experiments": [...], "meta"}.
    Their references are solved first, then the settlings known ahead (SETTLE_CELLS), one process per
    core (``prefetch``); the experiments then find them in the cache, and nothing runs beside the model
    runs they time."""
    from verification.studies.prefetch import settle_ahead, solve_references

    keys = list(EXPERIMENTS) if not only else list(only)
    t0 = time.perf_counter()
    solve_references(reference_jobs(keys, size))
    settle_ahead([], cells=[cell for k in keys for cell in SETTLE_CELLS.get(k, lambda size: [])(size)])
    found = []
    for k in keys:
        t1 = time.perf_counter()
        log(f"seeds: {k} ...")
        f = EXPERIMENTS[k](size)
        f["wall_s"] = time.perf_counter() - t1
        log(f"seeds: {k}: {f['verdict']} ({f['wall_s']:.0f} s)")
        found.append(f)
    return {"experiments": found, "meta": {"size": size.name, "wall_s": time.perf_counter() - t0}}


def without_pictures(res: dict) -> dict:
    """The study as JSON-ready data: each plot by its description only."""
    out = copy.deepcopy(res)
    for f in out["experiments"]:
        f["plots"] = [p["alt"] for p in f["plots"]]
    return out


def format_seeds(res: dict) -> str:
    lines = []
    for f in res["experiments"]:
        ref = f["reference"]
        est = ref.get("ref_err_estimate")
        bar = ref["kind"] if est is None else f"{ref['kind']}, estimate {est:.1e}"
        lines.append(f"{f['number']}. {f['title']} ({f['source']}): {f['verdict'].upper()}")
        lines.append(f"   claim:    {f['claim']}")
        lines.append(f"   measured: {f['figure']}")
        lines.append(f"   decides:  {f['decides']}")
        lines.append(f"   truth:    {bar}")
        if f.get("left_out"):
            lines.append(f"   left out: {f['left_out']}")
    lines.append(f"({res['meta']['wall_s']:.0f} s)")
    return "\n".join(lines)


def write_json(res: dict, path: Path) -> Path:
    return atomic_write_text(path, json.dumps(without_pictures(res), indent=1, default=str))
