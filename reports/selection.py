"""Which studies RESULTS.md is built from: the ablation study (named, else the latest) and the sweep studies
(named, else the latest one per task)."""

from __future__ import annotations

import pandas as pd

from reports.store import Store, StoreError, Study
from reports.sweeps import sweep_task


def _kind_of(parents: pd.DataFrame) -> pd.Series:
    kind = parents["tags.kind"] if "tags.kind" in parents else pd.Series(None, index=parents.index, dtype=object)
    return kind.fillna(parents["experiment"])


def load(store: Store, parent: dict) -> Study:
    """A study with its children's columns in sorted order: MLflow returns them in an order that changes from
    one process to the next, and figures that iterate over columns (e.g. sweep panels) would follow it."""
    study = store.load(parent)
    study.children = study.children[sorted(study.children.columns)]
    return study


def select_studies(store: Store, ablation: str | None, sweep_ids: list[str] | None) -> tuple[Study | None, list[Study]]:
    """The ablation study (given, else the latest; None when the store has none) and the sweep studies
    (given, else the latest one per task), sorted by task."""
    parents = store.parents()
    if parents.empty:
        raise StoreError(f"no studies in the store at {store.uri}")
    kinds = _kind_of(parents)

    def pick(ident: str, kind: str) -> Study:
        hit = parents[parents["run_id"] == ident]
        if hit.empty and "tags.study_name" in parents:
            hit = parents[parents["tags.study_name"] == ident].head(1)
        if hit.empty:
            raise StoreError(f"unknown study {ident!r} (not a parent run id or study_name) in {store.uri}")
        if kinds[hit.index[0]] != kind:
            raise StoreError(f"study {ident!r} is of kind {kinds[hit.index[0]]!r}, not {kind!r}")
        return load(store, hit.iloc[0].to_dict())

    if ablation:
        abl = pick(ablation, "ablation")
    else:
        rows = parents[kinds == "ablation"]
        abl = load(store, rows.iloc[0].to_dict()) if len(rows) else None
    by_task: dict[str, Study] = {}
    if sweep_ids:
        for s in (pick(i, "sweep") for i in dict.fromkeys(sweep_ids)):
            task = sweep_task(s)
            if task in by_task:
                raise StoreError(f"two sweep studies of task {task!r} selected ({by_task[task].name!r}, "
                                 f"{s.name!r}); pass one --sweep per task")
            by_task[task] = s
    else:
        for row in parents[kinds == "sweep"].to_dict("records"):  # newest first: the first of each task wins
            task = row.get("params.sweep.task") or row.get("tags.task") or "?"
            if isinstance(task, str) and task not in by_task:
                by_task[task] = load(store, row)
    return abl, [by_task[t] for t in sorted(by_task)]
