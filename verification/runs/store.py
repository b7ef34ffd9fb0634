"""Runs through the cache: one JSON file per run under ``$TISSUEBENCH_CACHE/runs``.

A run is keyed by everything that makes its row (docs/data-flow.md): the code, the
machine (a row holds timings), the scene's hash, the model, the integrator, the step (in seconds or as
a fraction of the critical one), the reference's options and whether the row carries an error budget.
A study killed half-way and started again recomputes only the runs it had not finished. The largest
stable step of a model, found by bisection, is cached the same way.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from meshes.io import atomic_write_text
from verification.cache import (
    RUN_CODE,
    code_digest,
    digest,
    entry,
    installed_versions,
    library_versions,
    machine_id,
    read_cached,
)
from verification.engines import engine_for, plug_in, spec_of
from verification.runs.compare import compare
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.row import Row, jsonable
from verification.runs.simulate import SETTLE_MAX_STEPS
from verification.scene import Scene


def run_key(
    scene: Scene,
    model: str,
    integrator: str,
    dt: float | None,
    fraction: float | None,
    ref_opts,
    budget: bool = True,
    options: dict | None = None,
) -> str:
    """The cache key of a run; ``options`` are what else makes it (a model builder's options, how it
    was run), absent for a sweep's rows. The libraries' versions are in it, and for an adapter's model
    the engines' venv's installed versions (``engine_versions``)."""
    fields = {
        "code": code_digest(RUN_CODE),
        "libraries": library_versions(),
        "machine": machine_id(),  # a row holds timings: another machine's are not this one's
        "scene": scene.sha256(),
        "model": model,
        "integrator": integrator,
        "dt": dt,
        "fraction": fraction,
        "reference": ref_opts,
        "budget": budget,
    }
    if options:
        fields["options"] = options
    engines = engine_versions(model)
    if engines:
        fields["engines"] = engines
    return digest(fields)


def engine_versions(model: str) -> dict:
    """What its adapter's venv holds (every installed distribution and its version) when ``model`` runs
    there, an adapter's; {} for the built-in engine's and a plug-in's own models."""
    from verification.engines.adapters import ADAPTERS

    for a in ADAPTERS.values():
        if model in a.models:
            return installed_versions(a.python())
    return {}


def cached_compare(
    scene: Scene,
    model: str,
    integrator: str = "symplectic-euler",
    dt: float | None = None,
    fraction: float | None = None,
    reference=None,
    ref_opts=None,
    use_cache: bool = True,
    max_steps: int = SETTLE_MAX_STEPS,
    budget: bool = True,
    float32: bool = False,
    options: dict | None = None,
    keep_answer: bool = False,
) -> Row:
    """``runs.compare.compare`` through the run cache (``options``: the engine's, as compare's). The row
    says whether it came from the cache. ``keep_answer``: the run's displacements are kept beside the row
    (``cached_answer`` reads them). A plug-in engine's runs are never cached, their code is not in
    the key; an adapter's are (the adapters and their pinned versions are, ``RUN_CODE``)."""
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    use_cache = use_cache and (not plug_in(model) or getattr(engine_for(model), "cacheable", False))
    key = run_key(scene, model, integrator, dt, fraction, ref_opts, budget, _how(float32, options, max_steps))
    path = entry("runs", scene.name, key, ".json")
    answer = answer_path(path) if keep_answer else None
    row = read_cached(path, _read_row) if use_cache else None
    if row is not None and (answer is None or answer.exists() or not row.ok):
        return row.replace(cached=True)
    ref = reference if reference is not None else reference_result(scene, **ref_opts)
    row = compare(
        scene,
        model,
        dt=dt,
        dt_fraction=fraction,
        integrator=integrator,
        reference=ref,
        max_steps=max_steps,
        budget=budget,
        float32=float32,
        options=options,
        answer_to=answer,
    )
    row = row.replace(fraction=fraction)
    if use_cache:
        atomic_write_text(path, json.dumps(row.to_json(), default=jsonable))
    return row


def answer_path(row_path: Path) -> Path:
    """Where the run of the row cached at ``row_path`` keeps its displacements (``cached_compare``'s
    ``keep_answer``): the same entry, as .npz."""
    return row_path.with_name(row_path.stem + "-answer.npz")


def _how(float32: bool, options: dict | None, max_steps: int) -> dict | None:
    """What else makes a run besides its model, step and reference (``run_key``'s options): float32,
    the engine's options, and a static run's step budget where it is not the harness's default (a run
    stopped unsettled at a study's budget is not the answer the default would reach)."""
    extra = {**({"float32": True} if float32 else {}), **({"engine": options} if options else {})}
    if max_steps != SETTLE_MAX_STEPS:
        extra["max_steps"] = int(max_steps)
    return extra or None


def cached_answer(
    scene: Scene, model: str, integrator: str, dt, fraction, ref_opts=None, budget=True, options=None,
    max_steps: int = SETTLE_MAX_STEPS,
):  # fmt: skip
    """The displacements (T, N, 3) m of the run ``cached_compare`` with these arguments kept
    (``keep_answer``), or None where it kept none (a run that gave no answer, or a damaged entry)."""
    ref_opts = dict(REFERENCE_DEFAULTS if ref_opts is None else ref_opts)
    key = run_key(scene, model, integrator, dt, fraction, ref_opts, budget, _how(False, options, max_steps))
    path = answer_path(entry("runs", scene.name, key, ".json"))
    return read_cached(path, lambda p: np.load(p)["displacement"])


def compare_or_unsettled(scene: Scene, model: str, integrator: str, dt, fraction, **options) -> Row:
    """``cached_compare``, where a run that does not settle is a row of status "not settled" with the
    reason (a candidate that failed, not an error that ends a study: hybrid-tm left a newcomer's liver
    advice with no answer), and a model that cannot represent the scene (``ModelRestriction``: a tool
    vertex inside the body for precomputed) one of status "not applicable". Not cached: whether a run
    settles depends on its ``max_steps``, which the run's key leaves out."""
    from realtime import ModelRestriction, NotConvergedError

    try:
        return cached_compare(scene, model, integrator, dt, fraction, **options)
    except NotConvergedError as exc:
        return Row(scene.name, model, integrator, "not settled", dt=dt, fraction=fraction, message=str(exc))
    except ModelRestriction as exc:
        stepper = "quasi-static" if spec_of(model).quasi_static else integrator  # as compare labels its rows
        return Row(scene.name, model, stepper, "not applicable", dt=dt, fraction=fraction, message=str(exc))


def read_json_object(path) -> dict:
    """A cached row: a JSON object (anything else is a damaged entry, read_cached's ValueError)."""
    row = json.loads(path.read_text())
    if not isinstance(row, dict):
        raise ValueError(f"not a JSON object but {type(row).__name__}")
    return row


def _read_row(path) -> Row:
    """A cached row (``Row.from_json`` of a JSON object; anything else is a damaged entry, ValueError)."""
    return Row.from_json(read_json_object(path))
