"""Table I across studies in a RESULTS template: {{ table_one("TASK=STUDY", ...) }} names, per training task, the
study whose finished models on the headline protocol fill that task's cells (so switching a task's source is one
word of the template), and per evaluated task, where it names one, the study of that task's own cells (stacking
judged under another protocol: "stack=STUDY"), and renders Table I with its bar figure
(reports.study_report.table_one). {{ claims }} and {{ headline_train_time }} read the same sources: the paper's
comparisons on those cells (reports.results.paper_claims) and their training time."""

from __future__ import annotations

from typing import TYPE_CHECKING

from reports.data.store import Study
from reports.results.paper_claims import claims_rows, claims_table
from reports.results.selection import headline_study
from reports.results.template import HEADLINE, SOURCE_SEPARATOR, Placeholder, ResultsError
from reports.study_report import table_one

if TYPE_CHECKING:
    from reports.results.writer import Results


def headline_of(placeholders: list[Placeholder]) -> Placeholder | None:
    """The one {{ table_one(...) }} of the template and its notebook pages (None without one)."""
    found = [p for p in placeholders if p.kind == "table_one"]
    if len({p.key for p in found}) > 1:
        raise ResultsError(f"{found[1]}: a second table_one; Table I is one table (the first: {found[0]})")
    return found[0] if found else None


def sources(ph: Placeholder, named: dict[str, Study]) -> dict[str, Study]:
    """training task -> its source study, in the placeholder's order, and an evaluated task of a listed training
    task -> its own study where one is named (reports.study_report.table_one.source_of)."""
    from envs.tasks import evaluation_tasks, training_tasks  # here: it loads torch and pybullet

    out = {}
    for arg in ph.args:
        task, _, name = arg.partition(SOURCE_SEPARATOR)
        out[task] = headline_study(named[name], str(ph))  # never a study of the validation episodes
    evaluated = {t for task in out if task in training_tasks() for t in evaluation_tasks(task)}
    for task in out:
        if task not in training_tasks() and task not in evaluated:
            raise ResultsError(f"{ph}: {task!r} is neither a training task (known: {', '.join(training_tasks())}) "
                               "nor an evaluated task of one listed")
    return out


def check(ph: Placeholder, placeholders: list[Placeholder], named: dict[str, Study]) -> None:
    if ph.kind == "table_one":
        sources(ph, named)
    elif ph.kind in HEADLINE and headline_of(placeholders) is None:
        raise ResultsError(f"{ph} reads the sources of Table I: add {{{{ table_one(\"TASK{SOURCE_SEPARATOR}STUDY\", "
                           "...) }}")


def render(results: Results, ph: Placeholder, placeholders: list[Placeholder]) -> str:
    """{{ table_one(...) }}: Table I, its notes and its figure; {{ claims }}, {{ headline_train_time }}: their
    tables on Table I's sources."""
    head = headline_of(placeholders)
    src = sources(head, results.named)
    if ph.kind == "claims":
        return claims_table(claims_rows(src)).to_markdown(heading=False)
    if ph.kind == "headline_train_time":
        return table_one.train_time_across(src).to_markdown(heading=False)
    rows = table_one.table_one_rows(src)
    text = table_one.table_one_table(rows, src).to_markdown(heading=False)
    studies = list({s.run_id: s for s in src.values()}.values())
    label = f"sources: {', '.join(s.name for s in studies)}"
    return text + "\n" + results.figure(studies[0], table_one.NAME, table_one.NAME,
                                        lambda folder: table_one.table_one_figure(rows, folder), label=label)
