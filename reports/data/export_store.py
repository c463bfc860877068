"""The study exports of a folder (reports.data.export), read as a store: what `--results --exports DIR` renders from,
with no MLflow store in between.

ExportStore answers what reports.data.store.Store answers (parents, studies, load), from each export's runs.json, in
the same frames; each Study's client (ExportClient) serves the metric histories and artifacts the reports read
(rollouts) straight from the export's files. Runs keep their original ids (tag export.run_id too, as after an
import), but for a copy of an export under another study name, whose ids are taken: there `<id>@<study>`. To
browse an export in the MLflow UI instead, `python -m reports import` reads it into a store
(reports.data.studyimport)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pandas as pd

from experiments.runtime.tracking import PARENT_TAG
from reports.data.export import ARTIFACTS, RUN_NAME_TAG
from reports.data.store import SOURCE_RUN_TAG, StoreError, Study, clean_row, pick_study, tidy_children
from reports.data.studyimport import export_folders, read_export


@dataclass(frozen=True)
class _Point:
    """One metric point, shaped as MLflow's Metric (what Study.metric_history reads)."""

    key: str
    value: float
    timestamp: int
    step: int


@dataclass(frozen=True)
class _File:
    """One artifact listing entry, shaped as MLflow's FileInfo."""

    path: str
    is_dir: bool


class ExportClient:
    """The three reads a Study makes of its client, answered from the exports' files."""

    def __init__(self, runs: dict[str, dict], files: dict[str, Path]):
        self.runs, self.files = runs, files  # run id -> exported run, run id -> the folder of its artifacts

    def get_metric_history(self, run_id: str, key: str) -> list[_Point]:
        run = self.runs[run_id]
        if key in run["histories"]:
            return [_Point(key, float(v), int(ts), int(step)) for step, ts, v in run["histories"][key]["points"]]
        if key in run["metrics"]:  # a latest value without a history: one point, as an import writes it
            return [_Point(key, float(run["metrics"][key]), int(run["end_time"] or run["start_time"]), 0)]
        return []

    def list_artifacts(self, run_id: str, path: str) -> list[_File]:
        prefix = path.rstrip("/") + "/"
        entries = {prefix + rest.split("/", 1)[0]: "/" in rest
                   for p in self.runs[run_id]["artifacts"] if p.startswith(prefix) and (rest := p[len(prefix):])}
        return [_File(p, is_dir) for p, is_dir in sorted(entries.items())]

    def download_artifacts(self, run_id: str, path: str, dst_path: str) -> str:
        if path not in self.runs[run_id]["artifacts"]:
            raise FileNotFoundError(f"run {run_id} exported no artifact {path}")
        return str(self.files[run_id] / path)  # read in place: an export is not written to


def _own_ids(doc: dict, taken: set[str]) -> tuple[dict, dict[str, str]]:
    """The export with run ids of its own in this store (`<id>@<study>` where an earlier export holds the id),
    and each one's id in the export (its artifacts' folder, and what an import tags it with)."""
    if not taken & {r["run_id"] for r in doc["runs"]}:
        return doc, {r["run_id"]: r["run_id"] for r in doc["runs"]}
    own = {r["run_id"]: f"{r['run_id']}@{doc['study_name']}" for r in doc["runs"]}
    runs = [{**r, "run_id": own[r["run_id"]], "parent_run_id": own.get(r["parent_run_id"])} for r in doc["runs"]]
    return {**doc, "runs": runs}, {new: old for old, new in own.items()}


def _row(run: dict, experiment: str, exported_id: str) -> dict[str, Any]:
    """The run as one row of Store's frames (mlflow.search_runs' columns), with the tags an import would add."""
    tags = {**run["tags"], SOURCE_RUN_TAG: exported_id}
    if run["run_name"] is not None:
        tags[RUN_NAME_TAG] = run["run_name"]
    if run["parent_run_id"] is not None:
        tags[PARENT_TAG] = run["parent_run_id"]
    return {"run_id": run["run_id"], "experiment_id": experiment, "experiment": experiment, "status": run["status"],
            "artifact_uri": None, "start_time": run["start_time"], "end_time": run["end_time"],
            **{f"metrics.{k}": float(v) for k, v in run["metrics"].items()},
            **{f"params.{k}": v for k, v in run["params"].items()},
            **{f"tags.{k}": v for k, v in tags.items()}}


def _frame(rows: list[dict]) -> pd.DataFrame:
    if not rows:
        return pd.DataFrame()
    df = pd.DataFrame(rows)
    for col in ("start_time", "end_time"):  # epoch ms -> UTC timestamps, as Store gives them
        df[col] = pd.to_datetime(df[col], unit="ms", utc=True)
    return df


class ExportStore:
    """Read-only view of every study export in a folder (or of one export folder), validated whole on opening."""

    def __init__(self, root: Path):
        from reports.data.export import ExportError

        self.uri = Path(root).as_posix()
        self._studies: dict[str, tuple[dict, Path]] = {}  # parent run id -> (runs.json, its folder)
        self._exported: dict[str, str] = {}  # run id here -> its id in the export
        names: dict[str, Path] = {}
        taken: set[str] = set()
        try:
            for folder in export_folders(Path(root)):
                doc, _ = read_export(folder)
                if doc["study_name"] in names:
                    raise StoreError(f"two exports of study {doc['study_name']!r}: {names[doc['study_name']]} and "
                                     f"{folder}")
                names[doc["study_name"]] = folder
                doc, exported = _own_ids(doc, taken)
                taken |= set(exported)
                self._exported |= exported
                self._studies[doc["runs"][0]["run_id"]] = (doc, folder)
        except ExportError as exc:
            raise StoreError(str(exc)) from None

    def parents(self, experiment: str | None = None) -> pd.DataFrame:
        """Parent runs (newest first), of one study kind or of all."""
        rows = [self._row(doc["runs"][0], doc["experiment"]) for doc, _ in self._studies.values()
                if experiment is None or doc["experiment"] == experiment]
        df = _frame(rows)
        return df if df.empty else df.sort_values("start_time", ascending=False).reset_index(drop=True)

    def studies(self, experiment: str | None = None, study: str | None = None) -> list[Study]:
        """As Store.studies: `study` (a parent run id or study_name), else the latest of `experiment`, else the
        latest of each kind."""
        return [self.load(row) for row in pick_study(self.parents(experiment), experiment, study, self.uri)]

    def load(self, parent: dict[str, Any]) -> Study:
        doc, folder = self._studies[parent["run_id"]]
        children = [r for r in doc["runs"][1:] if r["parent_run_id"] == parent["run_id"]]
        client = ExportClient({r["run_id"]: r for r in doc["runs"]},
                              {r["run_id"]: folder / ARTIFACTS / self._exported[r["run_id"]] for r in doc["runs"]})
        return Study(experiment=doc["experiment"], parent=clean_row(parent),
                     children=tidy_children(_frame([self._row(r, doc["experiment"]) for r in children])), client=client)

    def _row(self, run: dict, experiment: str) -> dict[str, Any]:
        return _row(run, experiment, self._exported[run["run_id"]])
