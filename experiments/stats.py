"""Success statistics shared by experiments (study summary, per-run metrics) and reports (tables): the Wilson
interval of pooled rollouts, a seed-aware cluster-bootstrap interval, and the success table itself.

Why two intervals: the rollouts of one training seed share that seed's model, so they are not independent
trials of the variant. The Wilson interval pools every rollout as if they were; the cluster bootstrap
resamples seeds first, then episodes within each drawn seed, so the spread between seeds widens it."""

from __future__ import annotations

import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

CONFIDENCE = 0.95
BOOTSTRAP_REPLICATES = 4000
BOOTSTRAP_SEED = 0  # fixed: the same store gives the same table, byte for byte
MIN_SEEDS_FOR_BOOTSTRAP = 2

# What the columns of the success table mean, for the notes under it (one wording everywhere).
SUCCESS_NOTE = ("success: mean over seeds of each seed's success rate; per seed: each training seed's rate; "
                "Wilson: 95% interval over all rollouts pooled as independent trials; seed-aware: 95% cluster "
                "bootstrap (seeds resampled, then episodes within each seed; needs >= 2 seeds), which widens with "
                "the spread between seeds and collapses at 0% and 100% (read Wilson there); rollouts: evaluation "
                "episodes pooled over seeds; seeds: training seeds with a finished run.")


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (nan, nan) when there are no trials."""
    if n <= 0:
        return math.nan, math.nan
    from scipy.stats import binomtest  # here: scipy.stats costs ~0.5 s of import in every process

    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def cluster_bootstrap_interval(groups: Sequence[Sequence[float]], confidence: float = CONFIDENCE,
                               replicates: int = BOOTSTRAP_REPLICATES,
                               seed: int = BOOTSTRAP_SEED) -> tuple[float, float]:
    """Percentile interval of the pooled mean under a two-stage bootstrap: draw len(groups) groups (seeds) with
    replacement, then within each drawn group its episodes with replacement. (nan, nan) without data."""
    groups = [np.asarray(g, dtype=float) for g in groups]
    groups = [g[~np.isnan(g)] for g in groups]
    groups = [g for g in groups if g.size]
    if not groups:
        return math.nan, math.nan
    rng = np.random.default_rng(seed)
    picks = rng.integers(len(groups), size=(replicates, len(groups)))  # stage 1: seeds
    sums = np.zeros(replicates)
    counts = np.zeros(replicates)
    for j, g in enumerate(groups):  # stage 2: episodes of seed j, for every slot that drew it
        rep, _ = np.nonzero(picks == j)
        if rep.size:
            draws = g[rng.integers(g.size, size=(rep.size, g.size))].sum(axis=1)
            np.add.at(sums, rep, draws)
            np.add.at(counts, rep, g.size)
    means = sums / counts
    alpha = (1 - confidence) / 2
    low, high = np.quantile(means, [alpha, 1 - alpha])
    return float(low), float(high)


def success_summary(successes: list[float]) -> dict[str, float]:
    """success_rate, success_ci_low, success_ci_high, n_rollouts from one run's per-episode 0/1 values."""
    n = len(successes)
    k = int(round(sum(successes)))
    low, high = wilson_interval(k, n)
    return {"success_rate": k / n if n else math.nan, "success_ci_low": low, "success_ci_high": high,
            "n_rollouts": float(n)}


def success_cell(per_seed: Mapping[int, tuple[float, float]]) -> dict:
    """One (variant, task) cell from each seed's (success rate, rollouts): the mean over seeds, the seeds'
    rates, the pooled successes/rollouts with their Wilson interval and the cluster-bootstrap interval.
    A seed's rollouts are 0/1 outcomes, so its rate and count are all the bootstrap needs of them."""
    logged = {int(s): (float(r), int(n)) for s, (r, n) in sorted(per_seed.items())
              if not (pd.isna(r) or pd.isna(n)) and int(n) > 0}
    counts = {s: (int(round(r * n)), n) for s, (r, n) in logged.items()}
    k = sum(c[0] for c in counts.values())
    n = sum(c[1] for c in counts.values())
    rates = {s: r for s, (r, _) in logged.items()}
    low, high = wilson_interval(k, n)
    # one seed says nothing about the spread between seeds: no seed-aware interval then
    blow, bhigh = cluster_bootstrap_interval([np.r_[np.ones(ks), np.zeros(ns - ks)] for ks, ns in counts.values()]) \
        if len(counts) >= MIN_SEEDS_FOR_BOOTSTRAP else (math.nan, math.nan)
    vals = np.array(list(rates.values()), dtype=float)
    return {"mean": float(vals.mean()) if vals.size else math.nan,
            "std": float(vals.std()) if vals.size else math.nan,
            "seeds": len(counts), "seed_rates": rates, "successes": k, "n": n,
            "ci_low": low, "ci_high": high, "boot_low": blow, "boot_high": bhigh}


def success_cells(evals: pd.DataFrame, variants: Sequence[str] | None = None,
                  tasks: Sequence[str] | None = None) -> pd.DataFrame:
    """One row per (variant, eval_task) from a long frame of finished runs (columns variant, eval_task, seed,
    success_rate, n_rollouts), in the given orders (else as first seen); see success_cell for the columns."""
    need = {"variant", "eval_task", "seed", "success_rate", "n_rollouts"}
    if evals.empty or not need <= set(evals.columns):
        return pd.DataFrame(columns=["variant", "eval_task", "mean", "std", "seeds", "seed_rates", "successes", "n",
                                     "ci_low", "ci_high", "boot_low", "boot_high"])
    evals = evals[evals["success_rate"].notna()]
    variants = list(variants or dict.fromkeys(evals["variant"]))
    tasks = list(tasks or dict.fromkeys(evals["eval_task"]))
    rows = []
    for task in tasks:
        for variant in variants:
            got = evals[(evals["variant"] == variant) & (evals["eval_task"] == task)]
            if len(got):
                per_seed = {int(s): (r, n) for s, r, n in zip(got["seed"], got["success_rate"], got["n_rollouts"],
                                                              strict=True)}
                rows.append({"variant": variant, "eval_task": task, **success_cell(per_seed)})
    return pd.DataFrame(rows)


def eval_rows(runs: Iterable) -> pd.DataFrame:
    """The long frame success_cells reads, from MLflow runs (FINISHED ones only): metrics <task>/success_rate and
    <task>/n_rollouts, tags variant and seed."""
    rows = []
    for run in runs:
        if run.info.status != "FINISHED":
            continue
        metrics, tags = run.data.metrics, run.data.tags
        for key, rate in metrics.items():
            task, _, name = key.partition("/")
            if name == "success_rate" and f"{task}/n_rollouts" in metrics:
                rows.append({"variant": tags.get("variant", "?"), "eval_task": task,
                             "seed": int(tags.get("seed", -1)), "success_rate": rate,
                             "n_rollouts": metrics[f"{task}/n_rollouts"]})
    return pd.DataFrame(rows)


def pct(x: float | None) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{100 * x:.0f}%"


def interval(low: float, high: float) -> str:
    return "–" if math.isnan(low) else f"{100 * low:.0f}–{100 * high:.0f}%"


def success_table(cells: pd.DataFrame, variant_label=str, task_label=str) -> pd.DataFrame:
    """THE success table, as strings: one row per (task, variant) with the mean success over seeds, each seed's
    rate, the pooled Wilson and the seed-aware interval, and what n counts (rollouts, seeds). Rows of `cells`
    with no seed (a gap) keep their row with dashes; a `mark` column (e.g. '†') is appended to the rate."""
    rows = []
    for r in cells.to_dict("records"):
        rates = r.get("seed_rates") or {}
        seeds = int(r.get("seeds") or 0)
        rows.append({
            "task": task_label(r["eval_task"]), "variant": variant_label(r["variant"]),
            "success": (pct(r["mean"]) + str(r.get("mark") or "")) if seeds else "gap",
            "per seed": " / ".join(pct(v) for v in rates.values()) or "–",
            "Wilson 95%": interval(r["ci_low"], r["ci_high"]) if seeds else "–",
            "seed-aware 95%": interval(r["boot_low"], r["boot_high"]) if seeds else "–",
            "rollouts": str(int(r["n"])) if seeds else "0",
            "seeds": str(seeds),
        })
    return pd.DataFrame(rows, columns=["task", "variant", "success", "per seed", "Wilson 95%", "seed-aware 95%",
                                       "rollouts", "seeds"])
