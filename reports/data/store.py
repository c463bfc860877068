"""Load studies from the MLflow tracking store into tidy pandas DataFrames.

Artifact contract (what reports reads; the experiments side writes it)
----------------------------------------------------------------------
Runs: one experiment per study kind (experiments.runtime.tracking.STUDY_KINDS). Parent run = no
`mlflow.parentRunId` tag (experiments.runtime.tracking.PARENT_TAG); tags `kind`, `profile`, `study_name`.
Child run: tag `mlflow.parentRunId`, tags `task` (training task), `variant`, `seed`, `profile`,
`config_hash`; status FAILED/KILLED = a failed cell (a gap).
Child metrics, per evaluated task E: `E/success_rate` (0..1), `E/success_ci_low`, `E/success_ci_high`,
`E/n_rollouts`, `E/final_distance_mean` (m); circle per radius R cm (`f"{R:g}"`):
`circle/r{R}/radial_rmse` (m), `circle/r{R}/max_radial_error_pct` (% of r); `train/loss`
(step = iteration), `val/metric`; `time/train_seconds`, `time/rollout_seconds`, `time/physics_seconds`,
`time/generation_seconds_per_traj`, `time/generation_batched_seconds_per_traj`,
`time/ik_seconds_per_traj`, `time/ik_batched_seconds_per_traj` (seconds per trajectory).
Child artifact `rollouts/<E>.npz` (np.savez_compressed; metres, robot base frame), B episodes, horizon H:
    tip (B, H+1, 3) REQUIRED tool-tip path of the rollout (measured in pybullet, or FK of the executed q);
    optional per episode: success (B,) 0/1 or NaN, final_distance (B,), goal (B, 3), new_goal (B, 3)
    (NaN if none), switch_step (B,) int (-1 if none), radius (B,) m, center (B, 3) m,
    ideal_tip (B, K, 3) ideal path (circle), expert_tip (B, Te+1, 3) the IK expert's direct path
    (changing goal; NaN-padded rows at the end); every other per-episode numeric result of the task's
    evaluate as (B,) float under its own name, NaN where missing (e.g. multimodal tasks: mode_<name> 0/1 one per
    mode, between 0/1, collided 0/1, lateral_offset m, posture_coordinate; pick-and-place: placed, success_strict);
    a per-episode tuple of steps (grip_close_steps: the rows the grip command closed at) as (B, L) int, -1 padded.
Child artifact `rollouts/modes/<E>.json` (eval.mode_repeats R > 0, tasks with modes; experiments.mode_repeats):
    {task, modes, repeats, deterministic, sampling_seeds (R,), mode (B, R) index or -1, success (B, R) 0/1,
    entropy_bits (B,), every_mode (B,)}; with the metrics `E/modes_repeats`, `E/modes_entropy_bits_mean`,
    `E/modes_both_share`, `E/modes_share_<name>`, `E/modes_between_share`.
Child artifact `rollouts/ik_timing.json`: {E: {"n_trajectories", "batch_size", "horizon",
    "stm_seconds_per_traj", "stm_batched_seconds_per_traj", "ik_seconds_per_traj",
    "ik_batched_seconds_per_traj"}}; absent -> the `time/*_seconds_per_traj` metrics of the run.
Sweep children: tags `trial`, `trial_state` (COMPLETE/PRUNED/FAIL), sampled values as params `trial.<name>`,
metric `objective`, intermediate `val/metric` (step = iteration); parent tag/param `direction` (default min).
Anything missing is reported as a gap by the consumer, never a crash.
"""

from __future__ import annotations

import json
import logging
import os
import re
import sqlite3
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pandas as pd

from experiments.runtime.backend_internals import MLFLOW_TABLES, table_names
from experiments.runtime.study_names import check_study_name
from experiments.runtime.tracking import (  # noqa: F401  (file_safe: the reports' name for figure files)
    DEFAULT_TRACKING_URI,
    FAILED_STATUSES,
    PARENT_TAG,
    file_safe,
    sqlite_path,
    tracking_uri,
)

log = logging.getLogger(__name__)

__all__ = ["DEFAULT_TRACKING_URI", "Store", "StoreError", "Study", "order_variants", "tracking_uri"]
EVAL_METRIC = re.compile(r"^metrics\.(?P<task>[^/]+)/(?P<name>success_rate|success_ci_low|success_ci_high|"
                         r"n_rollouts|final_distance_mean|episode_seed)$")
SOURCE_RUN_TAG = "export.run_id"  # an imported run's id in its original store (reports.data.studyimport)
CIRCLE_METRIC = re.compile(r"^metrics\.circle/r(?P<r>\d+(?:\.\d+)?)/(?P<name>radial_rmse|max_radial_error_pct)$")


class StoreError(Exception):
    """A problem with the store or the selection, reported as one line (exit code 2)."""


@dataclass
class Study:
    """One study: its parent run and its children as a tidy frame (one row per child run)."""

    experiment: str
    parent: dict[str, Any]
    children: pd.DataFrame
    client: Any = field(repr=False)
    # downloaded artifacts live as long as the Study (removed when it is garbage-collected)
    _tmp: tempfile.TemporaryDirectory = field(
        default_factory=lambda: tempfile.TemporaryDirectory(prefix="reports-"), repr=False)
    _artifacts: dict[str, set[str]] = field(default_factory=dict, repr=False)
    _frames: dict[str, pd.DataFrame] = field(default_factory=dict, repr=False)

    @property
    def run_id(self) -> str:
        return self.parent["run_id"]

    @property
    def source_run_id(self) -> str:
        """The parent run's id in the store the study ran in (an imported study keeps it in a tag)."""
        return self.parent.get(f"tags.{SOURCE_RUN_TAG}") or self.run_id

    @property
    def kind(self) -> str:
        return self.parent.get("tags.kind") or self.experiment

    @property
    def name(self) -> str:
        return self.parent.get("tags.study_name") or self.run_id

    @property
    def profile(self) -> str:
        return self.parent.get("tags.profile") or "?"

    @property
    def slug(self) -> str:
        """Folder name for this study's outputs: its name, which the study name rule makes one
        (experiments.runtime.study_names; StudyNameError for a name from before the rule, never a cleaned one)."""
        return check_study_name(self.name)

    @property
    def split(self) -> str:
        """The episodes it was evaluated on: "validation" where a run or the parent says so, else "test"."""
        said = [v for c in ("tags.split", "params.eval.split") if c in self.children for v in self.children[c]]
        return "validation" if "validation" in [*said, self.parent.get("tags.split")] else "test"

    @property
    def ok(self) -> pd.DataFrame:
        """Children that finished (not failed, not running)."""
        return self.children[self.children["status"] == "FINISHED"]

    @property
    def variants(self) -> list[str]:
        return order_variants(self.children["variant"].dropna().unique())

    def unseen_radii_cm(self) -> set[float]:
        """Circle radii the runs list as unseen in training (param eval.circle_unseen_radii, metres)."""
        col = "params.eval.circle_unseen_radii"
        out: set[float] = set()
        for listed in self.children[col].dropna() if col in self.children else []:
            for r in str(listed).split(","):
                try:
                    out.add(round(float(r) * 100, 1))
                except ValueError:
                    continue
        return out

    @property
    def seeds(self) -> list[int]:
        return sorted(int(s) for s in self.children["seed"].dropna().unique())

    # ---------------------------------------------------------------- metrics
    def metric_history(self, run_id: str, key: str) -> pd.DataFrame:
        """(step, value) of one metric of one run, sorted by step; empty if never logged."""
        hist = self.client.get_metric_history(run_id, key)
        df = pd.DataFrame({"step": [m.step for m in hist], "value": [m.value for m in hist]})
        return df.sort_values("step").drop_duplicates("step", keep="last").reset_index(drop=True)

    def eval_metrics(self) -> pd.DataFrame:
        """Long frame: one row per (child run, evaluated task) with success_rate, success_ci_low,
        success_ci_high, n_rollouts, final_distance_mean, episode_seed (NaN where not logged)."""
        if "eval" not in self._frames:
            self._frames["eval"] = _melt(self.children, EVAL_METRIC, "task", "eval_task")
        return self._frames["eval"]

    def circle_metrics(self) -> pd.DataFrame:
        """Long frame: one row per (child run, radius) with radius_cm, radial_rmse, max_radial_error_pct."""
        if "per_radius" not in self._frames:
            df = _melt(self.children, CIRCLE_METRIC, "r", "radius_cm")
            if not df.empty:
                df["radius_cm"] = df["radius_cm"].astype(float)
            self._frames["per_radius"] = df
        return self._frames["per_radius"]

    def model_task_of(self, eval_task: str) -> str:
        """The training task whose runs evaluate `eval_task`: from the runs' metrics or `eval_tasks` tags, else
        the envs registry (imported only then: it pulls in torch and pybullet)."""
        em = self.eval_metrics()
        seen = em.loc[em["eval_task"] == eval_task, "task"].dropna().unique() if not em.empty else []
        if len(seen):
            return str(seen[0])
        if "tags.eval_tasks" in self.children:  # a failed run may have logged no metric, but its tag says
            for task, listed in zip(self.children["task"], self.children["tags.eval_tasks"], strict=True):
                if isinstance(listed, str) and eval_task in listed.split(","):
                    return str(task)
        try:  # reports may read envs constants (dependencies point reports -> envs)
            from envs.tasks import get_task
            return get_task(eval_task).model_task
        except Exception:  # noqa: BLE001 - the registry may not know the task
            return eval_task

    # -------------------------------------------------------------- artifacts
    def artifact_paths(self, run_id: str, folder: str = "rollouts") -> set[str]:
        key = f"{run_id}/{folder}"
        if key not in self._artifacts:
            try:
                self._artifacts[key] = {f.path for f in self.client.list_artifacts(run_id, folder)}
            except Exception as exc:  # noqa: BLE001 - an unreachable artifact store is a gap, not a crash
                log.warning("cannot list artifacts of run %s: %s", run_id, exc)
                self._artifacts[key] = set()
        return self._artifacts[key]

    def _download(self, run_id: str, path: str) -> Path | None:
        if path not in self.artifact_paths(run_id, str(Path(path).parent)):
            return None
        dst = Path(self._tmp.name) / run_id
        local = dst / path
        if not local.exists():
            dst.mkdir(parents=True, exist_ok=True)
            try:
                local = Path(self.client.download_artifacts(run_id, path, str(dst)))
            except Exception as exc:  # noqa: BLE001
                log.warning("cannot download %s of run %s: %s", path, run_id, exc)
                return None
        return local

    def rollouts(self, run_id: str, eval_task: str) -> dict[str, np.ndarray] | None:
        """Arrays of `rollouts/<eval_task>.npz`, or None when absent or unreadable (a gap)."""
        local = self._download(run_id, f"rollouts/{eval_task}.npz")
        if local is None:
            return None
        try:
            with np.load(local, allow_pickle=False) as z:
                arrays = {k: z[k] for k in z.files}
        except Exception as exc:  # noqa: BLE001 - a corrupt artifact is a gap
            log.warning("unreadable rollouts/%s.npz in run %s: %s", eval_task, run_id, exc)
            return None
        tip = arrays.get("tip")
        if tip is None or tip.ndim != 3 or tip.shape[-1] != 3:
            log.warning("rollouts/%s.npz of run %s has no tip array of shape (B, H+1, 3)", eval_task, run_id)
            return None
        return arrays

    def ik_timing(self, run_id: str) -> dict[str, dict[str, float]] | None:
        local = self._download(run_id, "rollouts/ik_timing.json")
        if local is None:
            return None
        try:
            return json.loads(local.read_text())
        except (OSError, ValueError) as exc:
            log.warning("unreadable rollouts/ik_timing.json in run %s: %s", run_id, exc)
            return None


def order_variants(names) -> list[str]:
    """The registry's order first (stm.variants: the paper's Table I), then the others alphabetically."""
    from stm.variants import VARIANTS

    names = [str(n) for n in names]
    known = [v for v in VARIANTS if v in names]
    return known + sorted(n for n in set(names) if n not in VARIANTS)


def _melt(children: pd.DataFrame, pattern: re.Pattern, group: str, out_col: str) -> pd.DataFrame:
    """Metric columns matching `pattern` -> one row per (run, group value), one column per metric name."""
    ids = ["run_id", "status", "task", "variant", "seed"]
    cols = {c: pattern.match(c) for c in children.columns}
    cols = {c: m for c, m in cols.items() if m}
    if not cols or children.empty:
        return pd.DataFrame(columns=[*ids, out_col])
    rows = []
    for key in sorted({m.group(group) for m in cols.values()}):
        mine = {m.group("name"): c for c, m in cols.items() if m.group(group) == key}
        part = children[ids].copy()
        part[out_col] = key
        for name, col in mine.items():
            part[name] = children[col].to_numpy()
        part = part[part[list(mine)].notna().any(axis=1)]
        rows.append(part)
    return pd.concat(rows, ignore_index=True)


class Store:
    """Read-only view of a tracking store (never creates one)."""

    def __init__(self, uri: str | None = None):
        from mlflow import MlflowClient

        os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # no bar per small download
        self.uri = uri or tracking_uri()
        path = sqlite_path(self.uri)
        if path is not None:
            _check_sqlite_store(path, self.uri)
        try:
            self.client = MlflowClient(self.uri)
        except Exception as exc:  # noqa: BLE001 - e.g. an unreachable server
            raise StoreError(f"cannot open the MLflow store at {self.uri}: {str(exc).splitlines()[0]}") from None

    def experiments(self) -> dict[str, str]:
        """name -> id of the experiments that hold at least one parent run."""
        try:
            exps = self.client.search_experiments()
        except Exception as exc:  # noqa: BLE001 - e.g. a file that is not an MLflow database
            raise StoreError(f"cannot read the MLflow store at {self.uri}: {str(exc).splitlines()[0]}") from None
        return {e.name: e.experiment_id for e in exps}

    def search(self, experiment_ids: list[str], filter_string: str = "") -> list:
        """Every matching run (mlflow Run objects), all pages."""
        runs, token = [], None
        while True:
            page = self.client.search_runs(experiment_ids, filter_string, max_results=5000, page_token=token)
            runs += page
            token = page.token
            if not token:
                break
        return runs

    def _runs(self, experiment_ids: list[str], filter_string: str = "") -> pd.DataFrame:
        """The runs as one row each, columns named as mlflow.search_runs names them (run_id, status,
        start_time, ..., metrics.X, params.X, tags.X), read through this store's own client."""
        return _runs_frame(self.search(experiment_ids, filter_string))

    def parents(self, experiment: str | None = None) -> pd.DataFrame:
        """Parent runs (newest first) of one experiment or of all."""
        exps = self.experiments()
        if experiment is not None:
            if experiment not in exps:
                known = ", ".join(sorted(exps)) or "none"
                raise StoreError(f"unknown experiment {experiment!r} in {self.uri} (known: {known})")
            exps = {experiment: exps[experiment]}
        if not exps:
            return pd.DataFrame()
        df = self._runs(list(exps.values()))
        if df.empty:
            return df
        if f"tags.{PARENT_TAG}" in df.columns:
            df = df[df[f"tags.{PARENT_TAG}"].isna()]
        names = {v: k for k, v in exps.items()}
        df = df.assign(experiment=df["experiment_id"].map(names))
        return df.sort_values("start_time", ascending=False).reset_index(drop=True)

    def studies(self, experiment: str | None = None, study: str | None = None) -> list[Study]:
        """The selected studies: `study` (a parent run id or study_name), else the latest parent of
        `experiment`, else the latest parent of each experiment."""
        return [self.load(row) for row in pick_study(self.parents(experiment), experiment, study, self.uri)]

    def load(self, parent: dict[str, Any]) -> Study:
        children = self._runs([parent["experiment_id"]], f"tags.`{PARENT_TAG}` = '{parent['run_id']}'")
        return Study(experiment=parent.get("experiment", ""), parent=clean_row(parent),
                     children=tidy_children(children), client=self.client)


def pick_study(parents: pd.DataFrame, experiment: str | None, study: str | None, where: str) -> list[dict]:
    """The parent rows a store's `studies` selects (see Store.studies); `where` names the store in errors."""
    if parents.empty:
        scope = f"experiment {experiment!r}" if experiment else "the store"
        raise StoreError(f"no studies in {scope} at {where}")
    if study is None:
        return parents.groupby("experiment", sort=False).head(1).to_dict("records")
    hit = parents[parents["run_id"] == study]
    if hit.empty and "tags.study_name" in parents.columns:
        hit = parents[parents["tags.study_name"] == study].head(1)
    if hit.empty:
        raise StoreError(f"unknown study {study!r} (not a parent run id or study_name) in {where}")
    return hit.to_dict("records")


def _check_sqlite_store(path: Path, uri: str) -> None:
    """An existing SQLite file with MLflow's tables, checked read-only: opening anything else with MLflow
    would create or migrate tables in it."""
    if not path.exists():
        raise StoreError(f"no MLflow store at {uri} (run a study first, or set MLFLOW_TRACKING_URI)")
    try:
        tables = table_names(path)
    except sqlite3.Error as exc:
        raise StoreError(f"{path} is not an MLflow store ({exc})") from None
    if not MLFLOW_TABLES <= tables:
        raise StoreError(f"{path} is not an MLflow store (no experiments/runs tables)")


def _runs_frame(runs) -> pd.DataFrame:
    rows = []
    for r in runs:
        row = {"run_id": r.info.run_id, "experiment_id": r.info.experiment_id, "status": r.info.status,
               "artifact_uri": r.info.artifact_uri, "start_time": r.info.start_time, "end_time": r.info.end_time}
        row.update({f"metrics.{k}": v for k, v in r.data.metrics.items()})
        row.update({f"params.{k}": v for k, v in r.data.params.items()})
        row.update({f"tags.{k}": v for k, v in r.data.tags.items()})
        rows.append(row)
    if not rows:
        return pd.DataFrame()
    df = pd.DataFrame(rows)
    for col in ("start_time", "end_time"):  # epoch ms -> UTC timestamps, as mlflow.search_runs gives them
        df[col] = pd.to_datetime(df[col], unit="ms", utc=True)
    return df


def clean_row(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and np.isnan(v) else v) for k, v in row.items()}


def tidy_children(df: pd.DataFrame) -> pd.DataFrame:
    """Identity columns (task, variant, seed, profile, config_hash, trial, trial_state) from the tags; metric
    and param columns kept under MLflow's names; `failed` marks FAILED/KILLED cells."""
    if df.empty:
        df = pd.DataFrame(columns=["run_id", "status", "start_time", "end_time"])
    df = df.copy()
    for tag in ("task", "variant", "seed", "profile", "config_hash", "trial", "trial_state"):
        col = f"tags.{tag}"
        df[tag] = df[col] if col in df.columns else pd.Series([None] * len(df), index=df.index, dtype=object)
    df["seed"] = pd.to_numeric(df["seed"], errors="coerce").astype("Int64")
    df["trial"] = pd.to_numeric(df["trial"], errors="coerce").astype("Int64")
    df["failed"] = df["status"].isin(FAILED_STATUSES)
    return df.sort_values(["task", "variant", "seed"], na_position="last").reset_index(drop=True)
