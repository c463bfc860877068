"""Table I (reports.study_report.table_one): the strict pick-and-place criterion gets a column only where a study
judged success on the block (eval.success = placed) and its rollouts record both criteria per episode (`placed` and
`success_strict`), so the column appears with such rollouts and no template changes; where success is the strict
criterion there is no column, and a note says so."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
import pandas as pd
import pytest

from reports.study_report import criteria, table_one


@dataclass
class _Study:
    """What table_one reads of a study: its name, profile, seeds and each run's rollouts arrays."""

    name: str = "pp"
    profile: str = "paper"
    seeds: list[int] = field(default_factory=lambda: [0, 1, 2])
    arrays: dict[str, dict[str, np.ndarray]] = field(default_factory=dict)
    success: str | None = "placed"  # the runs' param eval.success (None: absent, the strict default)

    @property
    def ok(self) -> pd.DataFrame:
        return RUNS.assign(task="pick-place", **{"params.eval.success": self.success})

    def rollouts(self, run_id: str, eval_task: str) -> dict[str, np.ndarray] | None:
        return self.arrays.get(run_id)


RUNS = pd.DataFrame({"run_id": ["r0", "r1", "r2"], "seed": [0, 1, 2], "params.eval.success": "placed"})


def _arrays(strict: list[float], with_placed: bool = True) -> dict[str, np.ndarray]:
    out = {"success": np.array(strict), "success_strict": np.array(strict)}
    if with_placed:
        out["placed"] = np.ones(len(strict))
    return out


def test_the_strict_rate_is_read_where_the_rollouts_record_both_criteria():
    study = _Study(arrays={"r0": _arrays([1, 0, 0, 0]), "r1": _arrays([1, 1, 0, 0]), "r2": _arrays([1, 1, 1, 0])})
    got = criteria.strict_rate(study, RUNS, "pick-place")
    assert got["strict_mean"] == pytest.approx(0.5) and got["strict_seeds"] == 3
    assert got["strict_seed_low"] < 0.5 < got["strict_seed_high"]


@pytest.mark.parametrize("arrays", [
    {"r0": {"success": np.ones(4)}, "r1": {"success": np.ones(4)}, "r2": {"success": np.ones(4)}},  # today's
    {"r0": _arrays([1, 0]), "r1": _arrays([1, 0], with_placed=False), "r2": _arrays([1, 1])},  # one seed lacks it
    {"r0": _arrays([1, 0]), "r1": _arrays([1, 0])},  # one seed without rollouts
])
def test_no_strict_rate_unless_every_seed_records_both_criteria(arrays):
    assert criteria.strict_rate(_Study(arrays=arrays), RUNS, "pick-place") == {}


def test_no_strict_rate_where_success_is_the_strict_criterion_already():
    """Rollouts record both criteria whatever eval.success is: a study judged strictly would get a column equal to
    ours, so it gets none."""
    study = _Study(arrays={"r0": _arrays([1, 0]), "r1": _arrays([1, 1]), "r2": _arrays([0, 0])}, success=None)
    assert criteria.strict_rate(study, study.ok, "pick-place") == {}
    strict = RUNS.assign(**{"params.eval.success": "strict"})
    assert criteria.strict_rate(study, strict, "pick-place") == {}


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
    assert criteria.STRICT_COLUMN not in without.columns
    assert without.rows[0][:3] == ["pick-and-place", "a.c. LSTM-MDN", "60%"]
    assert not any("ours is the strict criterion" in n for n in without.notes)  # judged on placed, rollouts older
    rows = pd.DataFrame([_row("pick-place", "ac-lstm-mdn", strict=0.4), _row("stack", "ac-lstm-mdn")])
    table = table_one.table_one_table(rows, sources)
    col = table.columns.index(criteria.STRICT_COLUMN)
    assert [r[col] for r in table.rows] == ["40% (30–50%)", "–"]
    assert table.columns[-2:] == ["paper", "study"] and [r[-2] for r in table.rows] == ["100%", "–"]
    assert any("success_strict" in n for n in table.notes)


def test_a_study_judged_strictly_says_so_under_the_table():
    strict = table_one.table_one_table(pd.DataFrame([_row("pick-place", "lstm"), _row("stack", "lstm")]),
                                       {"pick-place": _Study(name="campaign", success=None)})
    (note,) = [n for n in strict.notes if "ours is the strict criterion" in n]
    assert note.startswith("pick-and-place, stacking in `campaign`: ours is the strict criterion")


def test_a_cell_without_a_finished_seed_is_a_gap():
    row = {**_row("pick-place", "lstm"), "mean": math.nan, "seeds": 0, "seed_rates": {}, "n": 0, "status": "gap",
           "seed_low": math.nan, "seed_high": math.nan, "note": "seed 0: RUNNING"}
    table = table_one.table_one_table(pd.DataFrame([row]), {"pick-place": _Study()})
    assert table.rows[0][2:5] == ["gap", "–", "–"]
    assert "LSTM / pick-and-place: seed 0: RUNNING" in table.notes


def test_a_study_judged_on_the_block_shows_the_strict_criterion_in_its_success_table():
    """The headline v2's 5,000-iteration milestones (judged on the block): its success table carries the strict
    rate beside each pick-and-place cell, read from the same exported rollouts."""
    from pathlib import Path

    from reports.data.export_store import ExportStore
    from reports.results.across import at_iteration
    from reports.study_report import tables

    (study,) = ExportStore(Path(__file__).resolve().parents[1] / "reports" / "studies").studies(
        study="pickplace-v2-milestones")
    at_5000 = at_iteration(study, 5000)
    table = tables.paper_success_table(tables.success_summary(at_5000), at_5000)
    col = table.columns.index(criteria.STRICT_COLUMN)
    by_cell = {(r[0], r[1]): r for r in table.rows}
    assert by_cell[("pick-and-place", "a.c. LSTM-MDN")][col].startswith("57% (")  # placed: 78 %
    assert by_cell[("stacking", "a.c. LSTM-MDN")][col] == "–"
    assert criteria.STRICT_NOTE in table.notes


def test_stacking_names_its_own_study_with_the_place_pose_restart_beside():
    """Table I's stacking row from a study that judged it after a scripted return to a start configuration (the
    headline v2's stack-start milestones at 30,000), the same models' rate restarting from the place pose (the
    study's own cells' evaluation) beside it; the paper's comparisons read the same cells."""
    from pathlib import Path

    from reports.data.export_store import ExportStore
    from reports.results.across import at_iteration
    from reports.results.paper_claims import claims_rows

    exports = ExportStore(Path(__file__).resolve().parents[1] / "reports" / "studies")
    (v2,) = exports.studies(study="pickplace-v2")
    (start,) = exports.studies(study="pickplace-v2-milestones-stack-start")
    sources = {"pick-place": v2, "stack": at_iteration(start, 30000)}
    flat = table_one.table_one_rows(sources)
    rows = flat.set_index(["eval_task", "variant"])
    stack = rows.loc[("stack", "ac-lstm-mdn")]
    assert stack["study"] == "pickplace-v2-milestones-stack-start@30000"
    own = table_one.table_one_rows({"pick-place": v2}).set_index(["eval_task", "variant"])
    assert stack["place_pose_mean"] == own.loc[("stack", "ac-lstm-mdn"), "mean"] != stack["mean"]
    assert pd.isna(rows.loc[("pick-place", "ac-lstm-mdn"), "place_pose_mean"])  # pick-and-place has no restart
    table = table_one.table_one_table(flat, sources)
    assert table_one.PLACE_POSE_COLUMN in table.columns and table_one.PLACE_POSE_NOTE in table.notes
    assert table_one.PLACE_POSE_COLUMN not in table_one.table_one_table(own.reset_index(), {"pick-place": v2}).columns
    claims = claims_rows(sources)
    assert set(claims.loc[claims["eval_task"] == "stack", "study"]) == {"pickplace-v2-milestones-stack-start@30000"}
