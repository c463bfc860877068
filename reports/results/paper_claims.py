"""The comparisons the paper's claims rest on, on the cells of Table I: auto-conditioned against plain (both heads
pooled), mixture against deterministic (both trainings pooled), and the paper's method, a.c. LSTM-MDN, against
each other variant (reports.results.comparisons.PAPER_PAIRS). One row per comparison, one column per evaluated
task, each cell from the study Table I takes the task from ({{ claims }} in a RESULTS template reads the sources of
its {{ table_one(...) }}; a study's own report compares within the study): A − B in points, its 95 % interval and
p, with the paper's own difference where its Table I has both sides."""

from __future__ import annotations

import math

import pandas as pd

from experiments.stats import p_value, points
from reports import paper
from reports.data.store import Study
from reports.results.comparisons import NOTE, PAPER_PAIRS, ComparisonError, compare, side
from reports.study_report.table_one import eval_tasks, source_of
from reports.study_report.tables import Table

NAME, TITLE = "claims_table", "The paper's comparisons on Table I's cells: A − B in points (95 % interval), p"
GROUPS_MARK = "ᵍ"  # a single-variant comparison whose seeds did not see the same episodes: compared as groups


def _label(variants: tuple[str, ...]) -> str:
    return " + ".join(paper.variant_label(v) for v in variants)


def _claim(a: tuple[str, ...], b: tuple[str, ...]) -> str:
    if len(a) > 1:
        what = "auto-conditioning" if all(v.startswith("ac-") for v in a) else "mixture head"
        return f"{what}: {_label(a)} − {_label(b)}"
    return f"{_label(a)} − {_label(b)}"


def _paper_difference(a: tuple[str, ...], b: tuple[str, ...], eval_task: str) -> float | None:
    """The same difference of the paper's Table I values (pooled variants: their mean), None where it has none."""
    va, vb = ([paper.paper_success(v, eval_task) for v in vs] for vs in (a, b))
    if None in va or None in vb:
        return None
    return sum(va) / len(va) - sum(vb) / len(vb)


def claims_rows(sources: dict[str, Study]) -> pd.DataFrame:
    """One row per (comparison, evaluated task): the comparison's numbers (experiments.stats), the paper's
    difference, and NaN where a side has no finished run."""
    rows = []
    for a, b in PAPER_PAIRS:
        for eval_task in eval_tasks(sources):
            study = source_of(sources, eval_task)
            try:
                c = compare(side({v: study for v in a}, eval_task, False), side({v: study for v in b}, eval_task,
                                                                                  False))
            except ComparisonError:
                c = {"difference": math.nan, "low": math.nan, "high": math.nan, "p": math.nan, "test": "", "n": 0}
            rows.append({"claim": _claim(a, b), "single": len(a) == 1, "eval_task": eval_task,
                         "study": study.name, **{k: c[k] for k in ("difference", "low", "high", "p", "test", "n")},
                         "paper": _paper_difference(a, b, eval_task)})
    return pd.DataFrame(rows)


def _cell(r: dict) -> str:
    if math.isnan(r["difference"]):
        return "–"
    text = points(r["difference"])
    if not math.isnan(r["low"]):
        text += f" ({points(r['low'])} to {points(r['high'])})"
    text += f", p {p_value(r['p'])}" + (GROUPS_MARK if r["single"] and r["test"] == "groups" else "")
    return text + (f"; paper {points(r['paper'])}" if not pd.isna(r["paper"]) else "")


def _clear(group: pd.DataFrame) -> str:
    """The tasks where the interval lies clear of zero, with the sign of the difference."""
    out = [f"{paper.task_label(r.eval_task)} {'+' if r.low > 0 else '−'}" for r in group.itertuples()
           if not math.isnan(r.low) and (r.low > 0 or r.high < 0)]
    return ", ".join(out) or "none"


def claims_table(rows: pd.DataFrame) -> Table:
    """rows pivoted: one line per comparison, one column per evaluated task, and where its interval is clear of
    zero."""
    tasks = list(dict.fromkeys(rows["eval_task"])) if not rows.empty else []
    lines = [[claim, *(_cell(r) for r in group.to_dict("records")), _clear(group)]
             for claim, group in rows.groupby("claim", sort=False)] if not rows.empty else []
    notes = [f"Each task's cells from the study Table I takes it from. {NOTE}",
             f"{GROUPS_MARK}: a single-variant comparison whose seeds did not see the same episodes, compared as "
             "groups; paper: the same difference of the paper's Table I values (pooled variants: their mean), where "
             "it has both; clear of zero: the tasks whose 95 % interval excludes zero, with the sign of A − B."]
    return Table(NAME, TITLE, ["comparison", *(paper.task_label(t) for t in tasks), "clear of zero"], lines, notes,
                 rows)
