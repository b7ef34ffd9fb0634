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
