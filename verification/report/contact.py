"""A contact scene's force against the tool's travel: the truth's curve with its bars (the reference's
stations, ``runs.reference.contact_summary``) and each time-stepping model's, settled with the tool at
each station (the scene's variant with the travel cut to that fraction), as a haptic device pressing
slowly would feel them."""

from __future__ import annotations

import dataclasses
import html

import numpy as np

from verification.figures import img
from verification.progress import log
from verification.report.plots import plot_contact_curve
from verification.runs.reference import contact_summary
from verification.runs.row import Row
from verification.runs.simulate import run_model


def at_fraction(scene, fraction: float):
    """The scene with each rigid tool's travel (and ramp) cut to ``fraction`` of its own: a variant with a
    hash of its own (Scene.sha256 reads the problem)."""
    tools = tuple(
        dataclasses.replace(t, travel=tuple(fraction * np.asarray(t.travel)), ramp=fraction * t.ramp)
        for t in scene.problem.contacts
    )
    return dataclasses.replace(scene, problem=dataclasses.replace(scene.problem, contacts=tools))


def contact_html(scene, ref, rows: list[Row]) -> tuple[str, dict]:
    """On a static scene with one rigid tool and the truth's stations: the plot and its data (the travel m,
    the truth's force along the travel N with bars, each model's at the same stations). Each model runs at
    the step of its row of the largest step that settled (every station's own settling); "" elsewhere.
    The forces are the tool's push on the body, projected on its travel."""
    summary = contact_summary(ref.meta)
    if scene.time.mode != "static" or len(scene.problem.contacts) != 1 or not summary or not summary[0]["curve"]:
        return "", {}
    travel = np.asarray(scene.problem.contacts[0].travel, dtype=float)
    along = travel / np.linalg.norm(travel)
    curve = summary[0]["curve"]
    fractions = [c["fraction"] for c in curve]
    truth = [float(np.dot(c["force"], along)) for c in curve]  # the tool's push on the body
    bars = [c["force_bar"] for c in curve]
    models, missing = {}, {}
    for model in sorted({r.model for r in rows if r.status == "ok" and r.dt is not None}):
        r = max((r for r in rows if r.model == model and r.status == "ok" and r.dt is not None), key=lambda r: r.dt)
        log(f"report: {scene.name}: {model} at {len(fractions)} stations of the tool's travel")
        forces = _stations(scene, model, r, fractions, along)
        if isinstance(forces, str):
            missing[model] = forces
        else:
            models[model] = forces
    for model in sorted({r.model for r in rows} - set(models) - set(missing)):
        missing[model] = ", ".join(sorted({r.status for r in rows if r.model == model}))
    areas = _areas_html(summary[0], rows)
    distance = np.linalg.norm(travel) * np.asarray(fractions)
    plot = plot_contact_curve(distance, truth, bars, models, f"{scene.name}: the tool's force along its travel")
    text = (
        "<h3>The tool's force along its travel</h3><p>The force the rigid tool pushes the body with along its "
        "travel, what a haptic device pressing slowly renders (with the opposite sign): the reference at its stations with its bar (two "
        "levels and the penalty; none drawn where one level was solved), and each time-stepping model settled "
        "with the tool at each station.</p>"
        + img(plot, f"tool force along the travel for {html.escape(scene.name)}")
        + (
            "<p>Not drawn: "
            + "; ".join(f"{html.escape(m)} ({html.escape(why)})" for m, why in sorted(missing.items()))
            + ".</p>"
            if missing
            else ""
        )
        + areas
    )
    data = {"travel_m": distance.tolist(), "reference": truth, "reference_bar": bars, "models": models}
    return text, data | {"not_drawn": missing}


def _stations(scene, model: str, row: Row, fractions: list, along: np.ndarray) -> list | str:
    """``model`` settled with the tool at each of ``fractions`` of its travel, at its row's step: the tool's
    push on the body along the travel (N) at each; or why it has no curve (a station that diverged or did
    not settle, an engine that states no tool force)."""
    from realtime import DivergenceError, NotConvergedError
    from realtime.errors import InputError

    step = {"dt_fraction": row.fraction} if row.fraction is not None else {"dt": row.dt}  # an engine's: its own
    forces = []
    for f in fractions:
        try:
            res = run_model(at_fraction(scene, f), model, integrator=row.integrator, **step)
        except (DivergenceError, NotConvergedError, InputError) as exc:
            return f"at {f:.3g} of the travel: {' '.join(str(exc).split())}"
        forces.append(float(np.dot(res.reaction[-1], along)))
    if not np.all(np.isfinite(forces)):
        return "its engine states no tool force"
    return forces


def _areas_html(truth: dict, rows: list[Row]) -> str:
    """The contact area at the end of the travel: the truth's with its bar, each model's run at its largest
    settled step with its distance from the truth's (Row.contact)."""
    bar = "unknown" if truth["area_bar"] is None else f"{truth['area_bar']:.3g}"
    cells = []
    for model in sorted({r.model for r in rows if r.status == "ok" and r.contact}):
        r = max((r for r in rows if r.model == model and r.status == "ok" and r.contact), key=lambda r: r.dt or 0.0)
        c = r.contact[0]
        area = "unknown" if c["area"] is None else f"{c['area']:.3g}"
        err = "-" if c["area_rel_err"] is None else f"{c['area_rel_err']:.3g}"
        cells.append(f"<tr><td>{html.escape(model)}</td><td>{area}</td><td>{err}</td></tr>")
    return (
        f"<p>Contact area at the end of the travel: the reference's {truth['area']:.3g} m&sup2; (bar {bar}); "
        "a model's is the part of its boundary triangles, in the rest shape, where the interpolated gap to the tool "
        "is negative. An engine whose contact acts on its elements (MuJoCo's flex) keeps its vertices out of the "
        "tool, and its area is unknown.</p><table><tr><th>model</th>"
        "<th>area (m&sup2;)</th><th>relative to the reference's</th></tr>" + "".join(cells) + "</table>"
    )
