"""The largest stable step of a built-in model, by bisection (the stability study's, the sweep's limit,
and the seeds experiment on the critical stiffness read it): the span searched, the steps each trial
runs, and the bisection itself, cached by the run cache's rule (the code, the libraries, the scene)."""

from __future__ import annotations

import json

import numpy as np

from meshes.io import atomic_write_text
from realtime import DivergenceError, State, make_integrator
from verification.cache import RUN_CODE, code_digest, digest, entry, library_versions, read_cached
from verification.engines.builtin import model_for
from verification.engines.protocol import SceneInputs
from verification.engines.settling import omega2_rest
from verification.runs.store import read_json_object
from verification.scene import Scene

#: Bisection of the largest stable step: the span searched and the steps each trial runs.
STABLE_SEARCH = (0.5, 3.0)
STABLE_STEPS = 2000


def stable_fraction(inputs: SceneInputs, model_name: str, integrator: str, steps: int, iterations: int) -> dict:
    """Bisection on dt / dt_crit in STABLE_SEARCH for the largest step that runs ``steps`` steps from a
    small perturbation of rest (1e-6 of the mesh size) without blowing up, with the scene's loading and
    damping. Returns the stable and unstable fractions bracketing the limit, dt_crit and the ratio
    observed / predicted (1 when the prediction is exact)."""
    model = model_for(inputs, model_name)
    integ = make_integrator(integrator, inputs.time.damping_mass, inputs.time.damping_stiffness)
    dt_crit = integ.critical_dt(model, omega2_rest(inputs, model))
    size = float(np.ptp(model.points, axis=0).max())
    rng = np.random.default_rng(0)
    u0 = 1e-6 * size * rng.standard_normal(model.points.shape) * model.loading.free

    def stable(frac):
        st = State(u=u0.copy(), v=np.zeros_like(u0))
        try:
            integ.step(model, st, frac * dt_crit, steps, dt_crit=dt_crit)
            return True
        except DivergenceError:
            return False

    lo, hi = STABLE_SEARCH
    if not stable(lo):
        out = {"stable": None, "unstable": lo, "dt_crit": dt_crit, "ratio": None}
    elif stable(hi):
        out = {"stable": hi, "unstable": None, "dt_crit": dt_crit, "ratio": hi}
    else:
        for _ in range(iterations):
            mid = 0.5 * (lo + hi)
            lo, hi = (mid, hi) if stable(mid) else (lo, mid)
        out = {"stable": lo, "unstable": hi, "dt_crit": dt_crit, "ratio": lo, "steps": steps}
    return out


def stable_key(scene: Scene, model_name: str, integrator: str, steps: int, iterations: int) -> str:
    """The cache key of a largest-stable-step bisection (``largest_stable_fraction``)."""
    return digest(
        {
            "code": code_digest(RUN_CODE),
            "libraries": library_versions(),  # where a run blows up depends on the arithmetic
            "scene": scene.sha256(),
            "model": model_name,
            "integrator": integrator,
            "steps": steps,
            "iterations": iterations,
        }
    )


def largest_stable_fraction(
    scene: Scene,
    model_name: str,
    integrator: str = "symplectic-euler",
    steps: int = STABLE_STEPS,
    iterations: int = 7,
    use_cache: bool = True,
) -> dict:
    """Bisection on dt / dt_crit in STABLE_SEARCH for the largest step that runs ``steps`` steps from a
    small perturbation of rest (1e-6 of the mesh size) without blowing up, with the scene's loading and
    damping. Returns the stable and unstable fractions bracketing the limit, dt_crit and the ratio
    observed / predicted (1 when the prediction is exact)."""
    from verification.inputs import scene_inputs

    key = stable_key(scene, model_name, integrator, steps, iterations)
    path = entry("runs", f"{scene.name}-stable", key, ".json")
    kept = read_cached(path, read_json_object) if use_cache else None
    if kept is not None:
        return kept
    out = stable_fraction(scene_inputs(scene), model_name, integrator, steps, iterations)
    if use_cache:
        atomic_write_text(path, json.dumps(out))
    return out
