"""Which studies RESULTS.md is built from: the ablation study (named, else the latest), the sweep studies
(named, else the latest one per task) and the studies the template names (study="NAME")."""

from __future__ import annotations

import pandas as pd

from reports.data.store import SOURCE_RUN_TAG, Store, StoreError, Study
from reports.study_report.sweep_summary import sweep_task


def _kind_of(parents: pd.DataFrame) -> pd.Series:
    kind = parents["tags.kind"] if "tags.kind" in parents else pd.Series(None, index=parents.index, dtype=object)
    return kind.fillna(parents["experiment"])


def load(store: Store, parent: dict) -> Study:
    """A study with its children's columns in sorted order: MLflow returns them in an order that changes from
    one process to the next, and figures that iterate over columns (e.g. sweep panels) would follow it."""
    study = store.load(parent)
    study.children = study.children[sorted(study.children.columns)]
    return study


class Selection:
    """The store's parent runs, and the studies picked from them by id or name (each loaded once)."""

    def __init__(self, store: Store):
        self.store = store
        self.parents = store.parents()
        if self.parents.empty:
            raise StoreError(f"no studies in the store at {store.uri}")
        self.kinds = _kind_of(self.parents)
        self._loaded: dict[str, Study] = {}

    def load(self, row: dict) -> Study:
        if row["run_id"] not in self._loaded:
            self._loaded[row["run_id"]] = load(self.store, row)
        return self._loaded[row["run_id"]]

    def pick(self, ident: str, kind: str | tuple[str, ...]) -> Study:
        """The study of this parent run id (its own, or its original one when imported) or study_name, of
        `kind` (or one of several kinds)."""
        p = self.parents
        hit = p[p["run_id"] == ident]
        for col in (f"tags.{SOURCE_RUN_TAG}", "tags.study_name"):
            if hit.empty and col in p:
                hit = p[p[col] == ident].head(1)
        if hit.empty:
            raise StoreError(f"unknown study {ident!r} (not a parent run id or study_name) in {self.store.uri}")
        kinds = (kind,) if isinstance(kind, str) else kind
        if self.kinds[hit.index[0]] not in kinds:
            raise StoreError(f"study {ident!r} is of kind {self.kinds[hit.index[0]]!r}, not {' or '.join(kinds)!r}")
        return self.load(hit.iloc[0].to_dict())

    def latest(self, kind: str) -> Study | None:
        rows = self.parents[self.kinds == kind]
        return self.load(rows.iloc[0].to_dict()) if len(rows) else None


def select_studies(selection: Selection, ablation: str | None,
                   sweep_ids: list[str] | None) -> tuple[Study | None, list[Study]]:
    """The ablation study (given, else the latest; None when the store has none) and the sweep studies
    (given, else the latest one per task), sorted by task."""
    abl = selection.pick(ablation, "ablation") if ablation else selection.latest("ablation")
    by_task: dict[str, Study] = {}
    if sweep_ids:
        for s in (selection.pick(i, "sweep") for i in dict.fromkeys(sweep_ids)):
            task = sweep_task(s)
            if task in by_task:
                raise StoreError(f"two sweep studies of task {task!r} selected ({by_task[task].name!r}, "
                                 f"{s.name!r}); pass one --sweep per task")
            by_task[task] = s
    else:
        parents = selection.parents
        for row in parents[selection.kinds == "sweep"].to_dict("records"):  # newest first: the first of each task wins
            task = row.get("params.sweep.task") or row.get("tags.task") or "?"
            if isinstance(task, str) and task not in by_task:
                by_task[task] = selection.load(row)
    return abl, [by_task[t] for t in sorted(by_task)]


def headline_study(study: Study, what: str) -> Study:
    """`study` for a headline table (`what`: the placeholder), unless its runs were evaluated on the validation
    episodes (Study.split): those are where protocol choices are made, so a headline number never comes from them
    (StoreError naming the study; a comparison or lever table may still quote it, labelled)."""
    if study.split == "validation":
        raise StoreError(f"{what}: study {study.name!r} was evaluated on the validation episodes (eval.split = "
                         "validation); a headline table reads test episodes only")
    return study
