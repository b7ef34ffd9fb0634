"""A model's run against the scene's reference: the metrics, the error budget and the float32 twin
(docs/metrics.md)."""

from __future__ import annotations

import time

import numpy as np

from meshes.io import atomic_savez
from realtime import DivergenceError
from verification.engines import spec_of
from verification.engines.builtin import BUILTIN
from verification.engines.settling import UnboundedAnswerError
from verification.inputs import scene_inputs
from verification.metrics import compute, rel_l2
from verification.runs.reference import P1_OWN_MESH, REFERENCE_DEFAULTS, reference_result
from verification.runs.results import Result
from verification.runs.row import Row
from verification.runs.simulate import _run_dynamic, run_model, time_steps
from verification.scene import Scene


def error_budget(scene: Scene, model_name: str, res: Result, ref: Result, integrator: str, max_steps: int) -> dict:
    """Which part of a model's error is whose (docs/metrics.md), each an L2 distance over
    the scene's vertices and output times relative to the converged reference's norm, like ``rel_l2``:

    - ``mesh``: the P1 finite-element solution of the scene's law on the scene's mesh against the
      converged reference: what any P1 model on this mesh pays (locking, a coarse mesh), whatever it is;
    - ``model``: the model against that P1 solution: what the model's own shortcuts cost (linearity,
      lumping, springs, condensation, an unsettled run);
    - ``time`` (dynamic scenes, time-stepping models): the model at its step against the same model at
      an eighth of it; the model part is then taken at the eighth, so the parts do not overlap.

    ``dominant`` names the largest; a scene with events also has each state's mesh and model parts
    (``states``, relative to that state's reference). The parts are distances between solutions over one norm, so by the
    triangle inequality |mesh - model| - time <= total <= mesh + model + time; a total far below the sum
    is errors cancelling (mass-spring's missing Poisson effect against P1's locking). A P1 reference that
    cannot solve leaves ``mesh`` None with the reason.
    """
    from reference.errors import ReferenceSolveError

    out = {"mesh": None, "model": None, "time": None}
    try:
        p1 = reference_result(scene, **P1_OWN_MESH)
    except ReferenceSolveError as exc:
        out["why"] = f"no P1 solution on this mesh: {exc}"
        return out
    scale = max(float(np.linalg.norm(ref.displacement)), 1e-300)

    def distance(a, b):
        return float(np.linalg.norm(a - b)) / scale

    out["mesh"] = distance(p1.displacement, ref.displacement)
    model_u = res.displacement
    dt = res.meta.get("dt")
    if scene.time.mode == "dynamic" and dt is not None and not spec_of(model_name).quasi_static:
        record = res.meta.get("adaptation")
        if record:  # a re-adapting run's step follows its mesh: an eighth of its fraction of each one's
            fraction = record[0]["dt"] / res.meta["dt_crit"] / 8.0
            fine = run_model(scene, model_name, dt_fraction=fraction, integrator=integrator, max_steps=max_steps)
        else:
            fine = run_model(scene, model_name, dt=dt / 8.0, integrator=integrator, max_steps=max_steps)
        out["time"] = distance(res.displacement, fine.displacement)
        model_u = fine.displacement
    out["model"] = distance(model_u, p1.displacement)
    if scene.events:  # each state's parts, relative to that state's reference
        out["states"] = [
            {"mesh": rel_l2(p1.displacement[k], ref.displacement[k]), "model": rel_l2(model_u[k], p1.displacement[k])}
            for k in range(len(ref.times))
        ]
    out["dominant"] = max((k for k in ("mesh", "model", "time") if out[k] is not None), key=lambda k: out[k])
    return out


def cancelling(total: float | None, mesh: float | None, model: float | None) -> bool:
    """Whether a model's total error is errors cancelling: below the mesh's part (P1 on the same mesh)
    while its own part is over half of it. The model is then right for a wrong reason, its error offsetting
    P1's (mass-spring's missing Poisson effect against P1's locking), and a finer mesh, which shrinks the
    mesh's part and not its own, does not make it better."""
    if total is None or mesh is None or model is None:
        return False
    return total < mesh and model > mesh / 2.0


def float32_twin(scene: Scene, res: Result) -> dict:
    """The run of ``res`` (a float64 explicit run of a model whose spec says float32) again with its model
    built in float32, at the same dt: on a dynamic scene the same trajectory, on a static one the same
    number of settling steps (``BuiltinSimulation.settle_steps``: a float32 residual cannot say when to
    stop). Returns the float32 run's displacement (T, N, 3) m and its meta: dt, settle_steps and the
    step timing (``time_steps``)."""
    m = res.meta
    t0 = time.perf_counter()
    sim = BUILTIN.build(scene_inputs(scene), m["model"], m["integrator"], {"precision": "float32"})
    build_s = time.perf_counter() - t0
    if scene.time.mode == "dynamic":
        twin = _run_dynamic(scene, sim, m["dt"], None, build_s, BUILTIN.name)
        return {"displacement": twin.displacement, "dt": m["dt"], "settle_steps": None, **_timing(twin.meta)}
    sim.settle_steps(m["dt"], m["static"]["steps"])
    u = sim.displacement().astype(np.float64)[None]
    timing = time_steps(sim)
    return {"displacement": u, "dt": m["dt"], "settle_steps": m["static"]["steps"], **_timing(timing)}


def _timing(meta: dict) -> dict:
    return {k: meta[k] for k in ("step_us", "step_us_min", "step_us_max")}


def compare(
    scene: Scene,
    model_name: str,
    dt: float | None = None,
    dt_fraction: float | None = None,
    integrator: str = "symplectic-euler",
    reference: Result | None = None,
    max_steps: int = 2_000_000,
    vtk: str | None = None,
    budget: bool = True,
    float32: bool = False,
    options: dict | None = None,
    answer_to: str | None = None,
    **ref_options,
) -> Row:
    """Metrics of one model run against the scene's reference, as a Row (docs/metrics.md).

    A diverging run gives a row of status "diverged" with the step, dt and dt_crit instead of errors.
    ``unrepresented`` lists what the material asks that the model does not represent (fibres, the
    volume penalty: ModelSpec.unrepresented): it ran without it, and its errors measure the cost.
    ``vtk`` (a directory or a .pvd path) also writes both displacements and the pointwise error at every
    output time as one ParaView series. ``budget`` adds ``error_budget`` (see ``error_budget``).
    ``float32``: for a model whose spec says float32 under an explicit integrator, the row's ``float32`` holds
    its float32 twin (``float32_twin``): rel_l2_vs_float64, its distance from this run by the row's own
    metric, beside its rel_l2 against the reference, and its step times; None for the other models.
    ``options`` go to the engine's build (an adapter's knobs: iterations, substeps). ``answer_to``: an .npz
    path that also keeps the run's ``displacement`` (T, N, 3) m, for a study comparing two runs' answers.
    """
    # a quasi-static model has its own update whatever integrator was asked for
    spec = spec_of(model_name)
    stepper = "quasi-static" if spec.quasi_static else integrator
    base = {"scene": scene.name, "model": model_name, "integrator": stepper}
    base["unrepresented"] = tuple(spec.unrepresented(scene.body_material()))
    ref = reference if reference is not None else reference_result(scene, **{**REFERENCE_DEFAULTS, **ref_options})
    try:
        res = run_model(
            scene,
            model_name,
            dt=dt,
            dt_fraction=dt_fraction,
            integrator=integrator,
            max_steps=max_steps,
            options=options,
        )
    except DivergenceError as exc:  # named by what stepped it: another engine's own solver
        return Row(**{**base, "integrator": getattr(exc, "solver", None) or base["integrator"]}, **_diverged(exc))
    metrics = run_metrics(scene, res, ref)
    mesh = scene.mesh
    if vtk is not None:
        _write_vtk(vtk, scene, model_name, res, ref)
    if answer_to is not None:
        atomic_savez(answer_to, displacement=res.displacement)
    m = res.meta
    parts = error_budget(scene, model_name, res, ref, integrator, max_steps) if budget else None
    single = _float32_row(scene, res, ref) if float32 and spec.float32 and integrator != "implicit-euler" else None
    return Row(
        **{**base, "integrator": m["integrator"]},  # what stepped it: a plug-in's own solver
        status="ok",
        error_budget=parts,
        float32=single,
        own_law=own_law(scene, spec, res) if spec.build is None else None,
        dt=m["dt"],
        dt_crit=m["dt_crit"],
        dt_crit_element=m.get("dt_crit_element"),
        **metrics,
        step_us=m["step_us"],
        step_us_min=m["step_us_min"],
        step_us_max=m["step_us_max"],
        realtime_factor=m["realtime_factor"],
        rate_hz=m["rate_hz"],
        settle_steps=m["static"]["steps"],
        settle_ms=m["settle_ms"],
        build_s=m.get("build_s"),
        reference=_reference_summary(ref),
        engine=m.get("engine"),
        n_vertices=mesh.n_vertices,
        n_tets=mesh.n_tets,
        adaptation=_adaptation(m.get("adaptation")),
        contact=contact_areas(scene, res, ref),
    )


def contact_areas(scene: Scene, res: Result, ref: Result) -> tuple:
    """Each rigid tool's contact area, the run's (its meta's ``contact_area``) against the truth's
    (runs.reference.contact_summary): ``Row.contact``; () on a scene without rigid tools."""
    from verification.runs.reference import contact_summary

    if not scene.problem.contacts:
        return ()
    truth = {t["tool"]: t for t in contact_summary(ref.meta)}
    mine = res.meta.get("contact_area")
    out = []
    for k in range(len(scene.problem.contacts)):
        t = truth.get(k, {})
        area, ref_area, bar = None if mine is None else mine[k], t.get("area"), t.get("area_bar")
        known = area is not None and ref_area
        out.append(
            {
                "tool": k,
                "area": area,
                "ref_area": ref_area,
                "area_rel_err": abs(area - ref_area) / ref_area if known else None,
                "ref_area_bar": bar / ref_area if bar is not None and ref_area else None,
            }
        )
    return tuple(out)


def own_law(scene: Scene, spec, res: Result) -> dict | None:
    """Another engine's model against the P1 truth of its own law (its spec's ``own_law``: newton's
    stable neo-Hookean, MuJoCo's StVK) on the scene's mesh, with the scene's Lame constants: {"law",
    "rel_l2"}, an L2 distance over the vertices and output times relative to that solution's norm. What
    remains is the engine's numerics alone (its settling, its solver's iterations), apart from its law.
    None where the spec declares no law; {"law", "rel_l2": None, "why"} where that P1 truth has no answer."""
    from reference.errors import ReferenceSolveError

    if spec.own_law is None:
        return None
    try:
        p1 = reference_result(scene.with_material(law=spec.own_law), **P1_OWN_MESH)
    except ReferenceSolveError as exc:
        return {"law": spec.own_law, "rel_l2": None, "why": " ".join(str(exc).split())}
    return {"law": spec.own_law, "rel_l2": rel_l2(res.displacement, p1.displacement)}


def _adaptation(record: list | None) -> dict | None:
    """A re-adapting run's record (``engines.readapting``) as the row keeps it."""
    if not record:
        return None
    tets = [r["tets"] for r in record]
    return {
        "tets_first": tets[0],
        "tets_max": max(tets),
        "tets_last": tets[-1],
        "checks": len(record) - 1,
        "changes": sum(a != b for a, b in zip(tets, tets[1:], strict=False)),
        "record": [(r["t"], r["tets"]) for r in record],
    }


def _write_vtk(vtk: str, scene: Scene, model_name: str, res: Result, ref: Result) -> None:
    """Both displacements and the pointwise error at every output time as one ParaView series."""
    from verification.vtk import write_series

    write_series(
        vtk,
        f"{scene.name}-{model_name}",
        res.points,  # the scene's mesh, or with events the union of its states' (runs.staged)
        res.tets,
        ref.times,
        {
            "reference_displacement": ref.displacement,
            "model_displacement": res.displacement,
            "error": res.displacement - ref.displacement,
            "error_magnitude": np.linalg.norm(res.displacement - ref.displacement, axis=2),
        },
    )


def _reference_summary(ref: Result) -> dict:
    """What a row says of its reference: how it was solved and what its own error is known to be (its
    bar, or "unverified" without the estimate)."""
    return {
        "degree": ref.meta["degree"],
        "refine": ref.meta["refine"],
        "law": ref.meta["law"],
        "cache_key": ref.meta.get("cache_key"),
        # what the reference's own error is known to be: its bar, or "unverified" without the estimate
        "ref_err_estimate": ref.meta.get("ref_err_estimate"),
        "ref_reaction_err_estimate": ref.meta.get("ref_reaction_err_estimate"),
        "verified": ref.meta.get("ref_err_estimate") is not None,
        "min_det_F": ref.meta.get("min_det_F"),
        "returned_level": ref.meta.get("returned_level"),
        "petsc_options": ref.meta.get("petsc_options"),
    }


def _float32_row(scene: Scene, res: Result, ref: Result) -> dict:
    """The row's float32 twin: its distance from the float64 run, its error and its step times."""
    twin = float32_twin(scene, res)
    u32 = twin.pop("displacement")
    return {**twin, "rel_l2_vs_float64": rel_l2(u32, res.displacement), "rel_l2": rel_l2(u32, ref.displacement)}


def _diverged(exc: DivergenceError) -> dict:
    """A diverged run's fields: where it blew up, and whether the scene's own answer is what is unbounded."""
    return {
        "status": "diverged",
        "dt": exc.dt,
        "dt_crit": exc.dt_crit,
        "step": exc.step,
        "message": str(exc),
        "unbounded": isinstance(exc, UnboundedAnswerError),
    }


def run_metrics(scene: Scene, res: Result, ref: Result) -> dict:
    """The run's metrics against its reference (``metrics.compute``), the tool force where there are tools.
    A scene with events is measured on the union of its states' vertices (``runs.staged``), its surface
    every state's (a cut's lips included), and each state's rel_l2 and bar are listed in ``states``."""
    mesh = scene.mesh
    has_tools = scene.problem.held_by_tools and bool(np.all(np.isfinite(res.reaction)))  # NaN: an engine gave none
    surface = mesh.surface_vertices
    per_state = {}
    if scene.events:
        from verification.events import states

        parts = states(scene)
        surface = np.unique(np.concatenate([s.union[s.scene.mesh.surface_vertices] for s in parts]))
        per_state["states"] = tuple(
            {
                "time": s.time,
                "label": s.label,
                "rel_l2": rel_l2(res.displacement[k], ref.displacement[k]),
                "ref_err_estimate": ref.meta["states"][k].get("ref_err_estimate"),
            }
            for k, s in enumerate(parts)
        )
    return per_state | compute(
        res.points,
        res.tets,
        surface,
        res.displacement,
        ref.displacement,
        res.reaction if has_tools else None,
        ref.reaction if has_tools else None,
        ref.meta.get("ref_err_estimate"),
    )
