"""The report's aggregates over seeds: success rows with gaps marked (the intervals and comparisons themselves
live in experiments.stats, shared with the study summary), means over seeds, curve bands."""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np
import pandas as pd

from experiments.stats import CONFIDENCE, seed_interval, success_over_seeds, wilson_interval

__all__ = ["CONFIDENCE", "aggregate_success", "curve_band", "mean_over_seeds", "seed_interval", "wilson_interval"]


def aggregate_success(evals: pd.DataFrame, children: pd.DataFrame, variants: Sequence[str],
                      tasks: Sequence[str], model_task_of, all_seeds: Sequence[int]) -> pd.DataFrame:
    """One row per (variant, eval_task): experiments.stats.success_over_seeds over the seeds that finished (mean/std
    over seeds, each seed's rate, pooled successes and n with the Wilson interval, the seed-level
    interval) and `status` ok | partial | gap with a `note` naming what is missing.

    evals: Study.eval_metrics(); children: Study.children; model_task_of(eval_task) -> training task.
    A seed counts when its run FINISHED and logged the rate; expected seeds are those of the cell group's runs
    (whatever their status) or, with no run at all, every seed of the study."""
    rows = []
    usable = not evals.empty and {"success_rate", "n_rollouts"} <= set(evals.columns)
    finished = evals[(evals["status"] == "FINISHED") & evals["success_rate"].notna()] if usable else None
    for task in tasks:  # grouped by task, as the paper's Table I compares the variants on each task
        for variant in variants:
            group_runs = children[(children["variant"] == variant) & (children["task"] == model_task_of(task))]
            expected = sorted({int(s) for s in group_runs["seed"].dropna()} or set(all_seeds))
            got = finished[(finished["variant"] == variant) & (finished["eval_task"] == task)] \
                if finished is not None else pd.DataFrame(columns=["seed", "success_rate", "n_rollouts"])
            agg = success_over_seeds({int(s): (r, n) for s, r, n in zip(got["seed"], got["success_rate"],
                                                                        got["n_rollouts"], strict=True)
                                      if not pd.isna(s)})
            have = sorted(agg["seed_rates"])
            missing = [s for s in expected if s not in have]
            notes = []
            if group_runs.empty:  # the study never trained this cell group: one note, not one per seed
                missing, notes = [], [f"no {model_task_of(task)} run of this variant in the study"]
            for s in missing:
                status = group_runs.loc[group_runs["seed"] == s, "status"]
                notes.append(f"seed {s}: {status.iloc[0] if len(status) else 'no run'}")
            rows.append({"variant": variant, "eval_task": task, **agg, "expected_seeds": len(expected),
                         "status": "gap" if not have else ("partial" if missing else "ok"),
                         "note": "; ".join(notes)})
    return pd.DataFrame(rows)


def mean_over_seeds(df: pd.DataFrame, by: Sequence[str], value: str) -> pd.DataFrame:
    """mean, std (population) and count of `value` per group, NaNs left out."""
    if df.empty or value not in df.columns:
        return pd.DataFrame(columns=[*by, "mean", "std", "count"])
    g = df.dropna(subset=[value]).groupby(list(by), sort=False)[value]
    out = g.agg(mean="mean", count="count").reset_index()
    out["std"] = g.std(ddof=0).to_numpy()
    return out


def curve_band(histories: Sequence[pd.DataFrame]) -> pd.DataFrame:
    """Mean, std, min and max over seeds of (step, value) histories, step by step (seeds missing a
    step are left out of that step)."""
    frames = [h.set_index("step")["value"].rename(i) for i, h in enumerate(histories) if len(h)]
    if not frames:
        return pd.DataFrame(columns=["step", "mean", "std", "min", "max", "n"])
    wide = pd.concat(frames, axis=1).sort_index()
    vals = wide.to_numpy(dtype=float)
    with np.errstate(invalid="ignore"):
        return pd.DataFrame({
            "step": wide.index.to_numpy(),
            "mean": np.nanmean(vals, axis=1), "std": np.nanstd(vals, axis=1),
            "min": np.nanmin(vals, axis=1), "max": np.nanmax(vals, axis=1),
            "n": np.sum(~np.isnan(vals), axis=1),
        })
