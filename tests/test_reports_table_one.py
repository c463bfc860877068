"""Table I (reports.study_report.table_one): the strict pick-and-place criterion gets a column only where a study's
rollouts record both criteria per episode (`placed` and `success_strict`), so the column appears with such rollouts
and no template changes; before them the rollouts' success is the strict criterion and there is no column."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pytest

from reports.study_report import table_one


@dataclass
class _Study:
    """What table_one reads of a study: its name, profile, seeds and each run's rollouts arrays."""

    name: str = "pp"
    profile: str = "paper"
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    arrays: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)

    def rollouts(self, run_id: str, eval_task: str) -> dict[str, np.ndarray] | None:
        return self.arrays.get(run_id)


RUNS = pd.DataFrame({"run_id": ["r0", "r1", "r2"], "seed": [0, 1, 2]})


def _arrays(strict: list[float], with_placed: bool = True) -> dict[str, np.ndarray]:
    out = {"success": np.array(strict), "success_strict": np.array(strict)}
    if with_placed:
        out["placed"] = np.ones(len(strict))
    return out


def test_the_strict_rate_is_read_where_the_rollouts_record_both_criteria():
    study = _Study(arrays={"r0": _arrays([1, 0, 0, 0]), "r1": _arrays([1, 1, 0, 0]), "r2": _arrays([1, 1, 1, 0])})
    got = table_one._strict(study, RUNS, "pick-place")
    assert got["strict_mean"] == pytest.approx(0.5) and got["strict_seeds"] == 3
    assert got["strict_seed_low"] < 0.5 < got["strict_seed_high"]


@pytest.mark.parametrize("arrays", [
    {"r0": {"success": np.ones(4)}, "r1": {"success": np.ones(4)}, "r2": {"success": np.ones(4)}},  # today's
    {"r0": _arrays([1, 0]), "r1": _arrays([1, 0], with_placed=False), "r2": _arrays([1, 1])},  # one seed lacks it
    {"r0": _arrays([1, 0]), "r1": _arrays([1, 0])},  # one seed without rollouts
])
def test_no_strict_rate_unless_every_seed_records_both_criteria(arrays):
    assert table_one._strict(_Study(arrays=arrays), RUNS, "pick-place") == {}


def _row(eval_task: str, variant: str, strict: float | None = None) -> dict:
    row = {"eval_task": eval_task, "variant": variant, "mean": 0.6, "std": 0.1, "seeds": 3,
           "seed_rates": {0: 0.5, 1: 0.6, 2: 0.7}, "successes": 60, "n": 102, "ci_low": 0.5, "ci_high": 0.7,
           "seed_low": 0.35, "seed_high": 0.85, "expected_seeds": 3, "status": "ok", "note": "", "study": "pp",
           "paper": 1.0 if eval_task == "pick-place" else None}
    if strict is not None:
        row.update(strict_mean=strict, strict_seed_low=strict - 0.1, strict_seed_high=strict + 0.1)
    return row


def test_the_strict_column_appears_only_when_some_cell_has_it():
    sources = {"pick-place": _Study()}
    without = table_one.table_one_table(pd.DataFrame([_row("pick-place", "ac-lstm-mdn")]), sources)
    assert table_one.STRICT_COLUMN not in without.columns
    assert without.rows[0][:3] == ["pick-and-place", "a.c. LSTM-MDN", "60%"]
    rows = pd.DataFrame([_row("pick-place", "ac-lstm-mdn", strict=0.4), _row("stack", "ac-lstm-mdn")])
    table = table_one.table_one_table(rows, sources)
    col = table.columns.index(table_one.STRICT_COLUMN)
    assert [r[col] for r in table.rows] == ["40% (30–50%)", "–"]
    assert table.columns[-2:] == ["paper", "study"] and [r[-2] for r in table.rows] == ["100%", "–"]
    assert any("success_strict" in n for n in table.notes)


def test_a_cell_without_a_finished_seed_is_a_gap():
    row = {**_row("pick-place", "lstm"), "mean": math.nan, "seeds": 0, "seed_rates": {}, "n": 0, "status": "gap",
           "seed_low": math.nan, "seed_high": math.nan, "note": "seed 0: RUNNING"}
    table = table_one.table_one_table(pd.DataFrame([row]), {"pick-place": _Study()})
    assert table.rows[0][2:5] == ["gap", "–", "–"]
    assert "LSTM / pick-and-place: seed 0: RUNNING" in table.notes
