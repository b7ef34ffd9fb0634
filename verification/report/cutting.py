"""The report's section on cutting and suturing: a scene with events (``verification.events``), every
tensor-mass model and mass-spring on each of its states against dolfinx on the same body."""

from __future__ import annotations

import html

from realtime.models import corotational_tm, hybrid_tm, linear_tm, mass_spring, stvk_tm
from verification.events import states
from verification.progress import log
from verification.runs.compare import compare
from verification.runs.reference import REFERENCE_DEFAULTS, reference_result
from verification.runs.simulate import SETTLE_MAX_STEPS
from verification.scene_file import load_scene
from verification.studies.frame import with_bar

#: The scene the section cuts and sutures, and the models it runs there.
CUT_SCENE = "cantilever-cut"
CUT_MODELS = (linear_tm.NAME, corotational_tm.NAME, stvk_tm.NAME, hybrid_tm.NAME, mass_spring.NAME)


def cut_cells() -> list[tuple]:
    """The section's settlings, for ``prefetch.settle_ahead``'s cells: each distinct state with each
    model at the default step, as ``compare`` runs them."""
    unique = {s.scene.sha256(): s.scene for s in states(load_scene(CUT_SCENE))}
    return [(scene, m, "symplectic-euler", SETTLE_MAX_STEPS) for scene in unique.values() for m in CUT_MODELS]


def cutting_section(scene=None) -> tuple[str, dict]:
    """The section's HTML and data on ``scene`` (default CUT_SCENE), a static scene with events."""
    log("report: cutting and suturing")
    scene = scene or load_scene(CUT_SCENE)
    ref = reference_result(scene, **REFERENCE_DEFAULTS)
    rows = [compare(scene, m, reference=ref) for m in CUT_MODELS]
    parts = ref.meta["states"]
    head = "<tr><th>model</th>" + "".join(f"<th>t = {s['time']:g} s</th>" for s in parts) + "<th>step (us)</th></tr>"
    body = []
    for r in rows:
        if not r.ok:
            body.append(
                f"<tr><td>{r.model}</td><td colspan='{len(parts) + 1}' class='bad'>{html.escape(r.message or r.status)}</td></tr>"
            )
            continue
        own = (r.error_budget or {}).get("states") or [{}] * len(parts)
        cells = "".join(
            f"<td>{with_bar(s['rel_l2'], s['ref_err_estimate'])}<br><small>model part {own[k].get('model', float('nan')):.2g}</small></td>"
            for k, s in enumerate(r.states)
        )
        body.append(f"<tr><td>{r.model}</td>{cells}<td>{r.step_us:.3g}</td></tr>")
    listed = "".join(
        f"<li>t = {s['time']:g} s: {html.escape(s['label'])} ({s['n_vertices']} vertices; the reference's bar "
        f"{s['ref_err_estimate']:.2g})</li>"
        for s in parts
    )
    text = f"""
<section id="cutting">
<h2>Cutting and suturing: {html.escape(scene.name)}</h2>
<p>{html.escape(scene.description)}. Each state is an equilibrium of its own, solved by dolfinx on the state's
mesh (the cut's faces doubled) and by each model built on it; the sutured body is the uncut one. Each cell is the
model's rel_l2 against the truth in that state, with the interval its bar leaves, and the model's part (against the
P1 solution of the scene's law on the same mesh: what the model's own shortcuts cost). The step time is the slowest
state's.</p>
<ul>{listed}</ul>
<table>{head}{"".join(body)}</table>
</section>"""
    return text, {"scene": scene.name, "states": parts, "rows": [r.to_json() for r in rows]}
