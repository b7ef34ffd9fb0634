"""A run's row (verification.runs.row.Row): what the run cache keeps is what it reads back, and what is
not a row is refused, not half-read."""

import json

import pytest

from verification.runs.row import Row, jsonable


def _ok() -> Row:
    return Row(
        "cantilever", "stvk-tm", "symplectic-euler", "ok", unrepresented=("fibres",), dt=1e-5, dt_crit=2e-5,
        rel_l2=0.0123, step_us=41.5, error_budget={"mesh": 0.01, "model": 0.002, "time": None, "dominant": "mesh"},
        reference={"degree": 2, "verified": True}, merged_dt=(1e-5, 2e-5),
    )  # fmt: skip


def test_a_row_survives_the_run_cache():
    row = _ok()
    text = json.dumps(row.to_json(), default=jsonable)
    back = Row.from_json(json.loads(text))
    assert back == row and back.unrepresented == ("fibres",) and back.merged_dt == (1e-5, 2e-5)
    assert json.loads(json.dumps({"rows": [row]}, default=jsonable))["rows"][0]["rel_l2"] == 0.0123


def test_a_row_is_changed_by_copy_only():
    row = _ok()
    with pytest.raises(AttributeError):
        row.pareto = True  # frozen: a study marks its rows by copies
    marked = row.replace(pareto=True, plan_index=3)
    assert marked.pareto and marked.plan_index == 3 and not row.pareto


@pytest.mark.parametrize(
    "data, why",
    [
        ({"scene": "s", "model": "m", "integrator": "i", "status": "ok", "rel_2": 0.1}, "not a row's field: rel_2"),
        ({"scene": "s", "model": "m", "status": "ok"}, "not a row"),  # integrator missing
        ({"scene": "s", "model": "m", "integrator": "i", "status": "fine"}, "must be one of ok, diverged"),
    ],
)
def test_what_is_not_a_row_is_refused(data, why):
    """A damaged or foreign cache entry raises ValueError (read_cached then computes the run again)."""
    with pytest.raises(ValueError, match=why):
        Row.from_json(data)


def test_a_run_stopped_at_a_studys_step_budget_is_not_read_as_the_default_runs(monkeypatch):
    """The engines study settles with a budget of its own (200 000 steps): its "not settled" row must not be
    what compare, with the harness's budget, reads back from the cache for the same run, nor the reverse."""
    from verification.runs import store
    from verification.scene_file import load_scene

    scene, made = load_scene("cantilever"), []

    def compare(scene, model, max_steps, **kwargs):
        made.append(max_steps)
        return Row(scene.name, model, "symplectic-euler", "not settled" if max_steps < 10**6 else "ok", dt=1e-5)

    monkeypatch.setattr(store, "compare", compare)
    monkeypatch.setattr(store, "reference_result", lambda *a, **k: None)
    for _ in range(2):  # the second round is read from the cache
        study = store.cached_compare(scene, "linear-tm", dt=1e-5, max_steps=200_000)
        default = store.cached_compare(scene, "linear-tm", dt=1e-5)
    assert made == [200_000, store.SETTLE_MAX_STEPS]
    assert (study.status, study.cached, default.status, default.cached) == ("not settled", True, "ok", True)
