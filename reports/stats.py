"""Statistics of the report: Wilson intervals (scipy), aggregation over seeds with gaps marked."""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import pandas as pd
from scipy.stats import binomtest

CONFIDENCE = 0.95


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (nan, nan) when there are no trials."""
    if n <= 0:
        return math.nan, math.nan
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def pooled_successes(rates: Iterable[float], ns: Iterable[float]) -> tuple[int, int]:
    """Successes and trials pooled over seeds, from each seed's logged rate and rollout count."""
    k = n = 0
    for rate, count in zip(rates, ns, strict=True):
        if pd.isna(rate) or pd.isna(count):
            continue
        k += int(round(float(rate) * float(count)))
        n += int(count)
    return k, n


def aggregate_success(evals: pd.DataFrame, children: pd.DataFrame, variants: Sequence[str],
                      tasks: Sequence[str], model_task_of, all_seeds: Sequence[int]) -> pd.DataFrame:
    """One row per (variant, eval_task): mean/std of the success rate over seeds, the Wilson interval over
    the pooled rollouts (successes, n), and `status` ok | partial | gap with a `note` naming what is missing.

    evals: Study.eval_metrics(); children: Study.children; model_task_of(eval_task) -> training task.
    A seed counts when its run FINISHED and logged the rate; expected seeds are those of the cell's runs
    (whatever their status) or, with no run at all, every seed of the study."""
    rows = []
    finished = evals[evals["status"] == "FINISHED"] if not evals.empty else evals
    for variant in variants:
        for task in tasks:
            cell_runs = children[(children["variant"] == variant) & (children["task"] == model_task_of(task))]
            expected = sorted({int(s) for s in cell_runs["seed"].dropna()} or set(all_seeds))
            got = finished[(finished["variant"] == variant) & (finished["eval_task"] == task)] \
                if not finished.empty else finished
            got = got[got["success_rate"].notna()] if "success_rate" in got.columns else got.iloc[0:0]
            have = sorted({int(s) for s in got["seed"].dropna()})
            k, n = pooled_successes(got["success_rate"], got["n_rollouts"]) if len(got) and \
                "n_rollouts" in got.columns else (0, 0)
            low, high = wilson_interval(k, n)
            missing = [s for s in expected if s not in have]
            notes = []
            if cell_runs.empty:  # the study never trained this cell: one note, not one per seed
                missing, notes = [], [f"no {model_task_of(task)} run of this variant in the study"]
            for s in missing:
                status = cell_runs.loc[cell_runs["seed"] == s, "status"]
                notes.append(f"seed {s}: {status.iloc[0] if len(status) else 'no run'}")
            rates = got["success_rate"].astype(float)
            rows.append({
                "variant": variant, "eval_task": task,
                "mean": float(rates.mean()) if len(rates) else math.nan,
                "std": float(rates.std(ddof=0)) if len(rates) else math.nan,
                "seeds": len(have), "expected_seeds": len(expected),
                "successes": k, "n": n, "ci_low": low, "ci_high": high,
                "status": "gap" if not have else ("partial" if missing else "ok"),
                "note": "; ".join(notes),
            })
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
