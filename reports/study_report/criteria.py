"""The strict pick-and-place criterion beside the lenient one: where a study judged success on the block
(eval.success = placed) and its rollouts record both criteria per episode (`placed`, `success_strict`), the strict
rate of a cell over its seeds, for a column beside ours in every success table (Table I and the study's own)."""

from __future__ import annotations

import math

import numpy as np
import pandas as pd

from experiments import stats

# the per-episode records of rollouts judged by both pick-and-place criteria: `placed` (the block at the goal) and
# `success_strict` (every check of the task); rollouts without both were judged by the strict one alone
STRICT_KEYS = ("placed", "success_strict")
STRICT_COLUMN = "strict criterion"
STRICT_NOTE = (f"{STRICT_COLUMN}: the rate under every check of the task, the last grip command open as well (the "
               "rollouts' success_strict), mean over seeds (seed-level 95 %), on the same rollouts as ours, which "
               "judges the block alone (`placed`).")
PLACE_TASK = "pick-place"  # the training task whose evaluated tasks are judged by either criterion (eval.success)


def judged_on_placed(runs: pd.DataFrame) -> bool:
    """Whether every run's success is the lenient `placed` (param eval.success; absent: the strict default)."""
    col = "params.eval.success"
    return not runs.empty and col in runs and bool((runs[col] == "placed").all())


def strict_rate(study, runs: pd.DataFrame, eval_task: str) -> dict:
    """The strict criterion over the seeds whose rollouts record both criteria (every finished seed must), as
    success_over_seeds' columns prefixed strict_; empty when the rollouts do not record them or when success is the
    strict criterion already (a column equal to ours would say nothing)."""
    if not judged_on_placed(runs):
        return {}
    per_seed = {}
    for run in runs.itertuples():
        arrays = study.rollouts(run.run_id, eval_task)
        if arrays is None or not set(STRICT_KEYS) <= set(arrays):
            return {}
        strict = np.asarray(arrays["success_strict"], float)
        per_seed[int(run.seed)] = (float(strict.mean()), len(strict))
    agg = stats.success_over_seeds(per_seed) if per_seed else {}
    return {f"strict_{k}": v for k, v in agg.items()}


def cell_strict_rate(study, row: dict) -> dict:
    """strict_rate of one row of reports.data.seed_aggregates.aggregate_success (a cell: eval task, variant, the
    seeds it holds), over that cell's runs in the study."""
    if not row["seeds"]:
        return {}
    ok = study.ok
    runs = ok[(ok["task"] == study.model_task_of(row["eval_task"])) & (ok["variant"] == row["variant"])]
    return strict_rate(study, runs[runs["seed"].isin(list(row["seed_rates"]))].sort_values("seed"), row["eval_task"])


def beside_cell(row: dict, prefix: str = "strict_") -> str:
    """A row's rate beside ours (strict_*, or another prefix's) with its seed-level interval; – where the cell has
    none."""
    mean = row.get(f"{prefix}mean")
    if mean is None or pd.isna(mean):
        return "–"
    low, high = row[f"{prefix}seed_low"], row[f"{prefix}seed_high"]
    return f"{stats.pct(mean)} ({stats.interval(low, high)})" if not math.isnan(low) else stats.pct(mean)
