"""A run's row: one model run on one scene against its reference, as every study reads it
(docs/metrics.md). A frozen dataclass, so that a study reads a field by its name and a
misspelt one fails where it is written; ``to_json`` is the row as ``compare --json`` prints it and the
run cache keeps it, ``from_json`` reads it back.

Which fields hold a value depends on ``status``:

- "ok": the metrics (``rel_l2`` ... ``rel_l2_interval``), the step timing (``step_us`` ...
  ``build_s``), the error budget, the float32 twin, the reference's summary and the mesh size;
- "diverged": the ``step`` it blew up at, the ``message``, and whether the scene's own answer is what is
  unbounded (``unbounded``);
- "not settled": the ``message`` (a static run that did not reach equilibrium in its steps);
- "not applicable": the ``message`` (a model that cannot represent the scene, ``ModelRestriction``:
  precomputed's responses exist for surface vertices only);
- "over budget": a run the advisor did not make, its steps timed ahead (``step_us``, ``dt``) and too
  slow for the frame rate asked (``frame``, ``message``): its error was not needed for the verdict.

The last group says how a study obtained and placed the run: asked as a ``fraction`` of the critical
step, read from the run ``cached``, the sweep's ``largest_stable`` step, its index in the sweep's plan
and whether it is on the ``pareto`` front, the advisor's ``frame`` budget, mesh ``level`` and the steps
merged into the row (``merged_dt``).
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

#: The statuses a row can have.
STATUSES = ("ok", "diverged", "not settled", "not applicable", "over budget")


@dataclass(frozen=True)
class Row:
    # what was run
    scene: str
    model: str
    integrator: str
    status: str
    #: Material terms the model does not represent (fibres, the volume penalty): it ran without them.
    unrepresented: tuple[str, ...] = ()
    #: The step and the explicit critical step it was chosen from, s (None: quasi-static).
    dt: float | None = None
    dt_crit: float | None = None
    dt_crit_element: float | None = None
    # the metrics against the reference (verification.metrics.compute): relative L2 over all vertices and
    # times, over the surface, the largest pointwise error (m), the volume change's error, the tool
    # force's relative error, the reference's own estimate and whether the error is within 10x of it
    rel_l2: float | None = None
    surface_rel_l2: float | None = None
    max_err: float | None = None
    volume_err: float | None = None
    reaction_rel_err: float | None = None
    ref_err_estimate: float | None = None
    rel_l2_interval: tuple[float, float] | None = None
    # what it cost: a step's median and spread (us), dt over a step's wall time, steps per second, the
    # steps and milliseconds to settle a static scene, the model's build (s)
    step_us: float | None = None
    step_us_min: float | None = None
    step_us_max: float | None = None
    realtime_factor: float | None = None
    rate_hz: float | None = None
    settle_steps: int | None = None
    settle_ms: float | None = None
    build_s: float | None = None
    #: Whose error is it (runs.compare.error_budget): the mesh's, the model's and the time step's parts.
    error_budget: dict | None = None
    #: Another engine's model against the P1 truth of its own law on the same mesh (runs.compare.own_law):
    #: {"law": its law, "rel_l2": the distance, its numerics alone}; None where it declares no law, or
    #: for a built-in model (its own law's P1 solution by construction, which the tests hold).
    own_law: dict | None = None
    #: The float32 twin of a float32-capable model's run (runs.compare.float32_twin).
    float32: dict | None = None
    #: The reference's summary: degree, refinement, law, cache key, its estimate and how it was solved.
    reference: dict | None = None
    #: Another engine's run (an adapter's): the engine and its version, the law the scene's was mapped
    #: to, its knobs (iterations, substeps); None for the built-in models.
    engine: dict | None = None
    n_vertices: int | None = None
    n_tets: int | None = None
    #: A scene with events (verification.events): each state's time, label, rel_l2 and reference bar;
    #: the row's own metrics are over every state at once.
    states: tuple = ()
    #: A re-adapting run (adaptive-tm on a dynamic scene): its tetrahedra first, largest and last, its
    #: checks and the changes among them, and (t, tetrahedra) at each check.
    adaptation: dict | None = None
    #: A scene with rigid tools: each tool's contact area against the truth's (runs.compare.contact_areas):
    #: {"tool", "area" m^2, "ref_area" m^2, "area_rel_err", "ref_area_bar" (relative)}; the area a model
    #: gives none of is None, never zero.
    contact: tuple = ()
    # a run that did not finish
    step: int | None = None
    message: str | None = None
    unbounded: bool = False
    # how a study obtained and placed it
    fraction: float | None = None
    cached: bool = False
    largest_stable: bool = False
    plan_index: int | None = None
    pareto: bool = False
    frame: dict | None = field(default=None, compare=False)
    level: int = 0
    #: The steps (s) whose runs gave this row's answer to SAME_ANSWER (studies.frame.merge_same_answers).
    merged_dt: tuple[float, ...] = ()

    def __post_init__(self):
        if self.status not in STATUSES:
            raise ValueError(f"row status {self.status!r}: must be one of {', '.join(STATUSES)}")

    @property
    def ok(self) -> bool:
        return self.status == "ok"

    def replace(self, **changes) -> Row:
        """A copy with ``changes``."""
        return dataclasses.replace(self, **changes)

    def to_json(self) -> dict:
        """The row as JSON-ready data: every field, tuples as lists."""
        out = dataclasses.asdict(self)
        out["unrepresented"] = list(self.unrepresented)
        out["merged_dt"] = list(self.merged_dt)
        out["states"] = list(self.states)
        return out

    @classmethod
    def from_json(cls, data: dict) -> Row:
        """A row from ``to_json``'s data; ValueError for data that is not one (an unknown or missing
        field: a damaged cache entry, which read_cached treats as absent)."""
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = set(data) - names
        if unknown:
            raise ValueError(f"not a row's field: {sorted(unknown)[0]}")
        try:
            tuples = {k: tuple(data.get(k) or ()) for k in ("unrepresented", "merged_dt", "states", "contact")}
            return cls(**{**data, **tuples})
        except TypeError as exc:
            raise ValueError(f"not a row: {exc}") from None


def jsonable(x):
    """For ``json.dumps(default=...)``: a Row (or anything with ``to_json``) as its data, numpy scalars as
    numbers, the rest as text."""
    if hasattr(x, "to_json"):
        return x.to_json()
    if hasattr(x, "item"):
        return x.item()
    if hasattr(x, "tolist"):
        return x.tolist()
    return str(x)
