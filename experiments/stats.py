"""Success statistics shared by experiments (study summary, per-run metrics) and reports (tables and comparisons):
the Wilson interval of pooled rollouts, the seed-level interval of a success rate (rate_interval), the success
table, and paired and group comparisons of two variants.

Why two intervals: the rollouts of one training seed share that seed's model, so they are not independent trials
of the variant. The Wilson interval pools every rollout as if they were; the seed-level interval treats each
seed's rate as one draw of the variant's rate (rate_interval says how it keeps its coverage with 3-5 seeds, and at
rates near 0 and 100 %, where a t-interval over the seeds' rates alone collapses)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterable, Mapping, Sequence

import numpy as np
import pandas as pd

CONFIDENCE = 0.95
MIN_SEEDS_FOR_INTERVAL = 2  # one seed says nothing about the spread between seeds

# What the columns of the success table mean, for the notes under it (one wording everywhere).
SEED_COLUMN = "seed-level 95%"
WILSON_COLUMN = "Wilson 95% (rollouts independent)"
SUCCESS_NOTE = ("success: mean over seeds of each seed's success rate; per seed: each training seed's rate; "
                f"{SEED_COLUMN}: the interval to read (needs >= 2 seeds): the wider of a t-interval over the seeds' "
                "rates, a t-interval over their logits (each rate shrunk towards 50 % by two pseudo-successes and "
                "two pseudo-failures) and a Clopper-Pearson interval on the episodes pooled at their effective "
                "number (the spread between seeds counted); it keeps its coverage with 3-5 seeds, widens with the "
                "spread between seeds and never shrinks to a point, at 0 % or 100 % either; Wilson: 95% interval "
                "over all rollouts pooled, which assumes independent rollouts and ignores the spread between seeds; "
                "rollouts: evaluation episodes pooled over seeds; seeds: training seeds with a finished run.")


def wilson_interval(successes: int, n: int, confidence: float = CONFIDENCE) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (nan, nan) when there are no trials."""
    if n <= 0:
        return math.nan, math.nan
    from scipy.stats import binomtest  # here: scipy.stats costs ~0.5 s of import in every process

    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def seed_interval(values, confidence: float = CONFIDENCE, bounds: tuple[float, float] = (0.0, 1.0)):
    """Student-t interval of the mean of `values` (the last axis: one value per seed), clipped to `bounds`;
    NaN where fewer than MIN_SEEDS_FOR_INTERVAL values. Vectorised: values of shape (..., K) give two arrays.

    The plain t-interval over seeds, for values that are not success rates (an entropy, a share of repeats) and as
    a part of rate_interval. A seed is one trained model, so a variant's value varies between seeds, and with 3-5
    seeds that spread is known only roughly: the t quantile with K - 1 degrees of freedom pays for it. It collapses
    when every seed has the same value: for success rates use rate_interval, which does not."""
    from scipy.stats import t as student_t  # here: scipy.stats costs ~0.5 s of import in every process

    x = np.asarray(values, dtype=float)
    k = x.shape[-1]
    if k < MIN_SEEDS_FOR_INTERVAL:
        nan = np.full(x.shape[:-1], np.nan)
        return (math.nan, math.nan) if x.ndim == 1 else (nan, nan)
    half = student_t.ppf(0.5 + confidence / 2, k - 1) * x.std(axis=-1, ddof=1) / math.sqrt(k)
    mean = x.mean(axis=-1)
    low, high = np.clip(mean - half, *bounds), np.clip(mean + half, *bounds)
    return (float(low), float(high)) if x.ndim == 1 else (low, high)


def clopper_pearson(successes, n, confidence: float = CONFIDENCE):
    """Clopper-Pearson (beta quantile) interval of a binomial proportion, vectorised; `successes` and `n` may be
    fractional (an effective number of episodes): the beta quantiles take any positive shapes."""
    from scipy.stats import beta

    x, n = np.broadcast_arrays(np.asarray(successes, dtype=float), np.asarray(n, dtype=float))
    tail = (1 - confidence) / 2
    tiny = np.finfo(float).tiny
    with np.errstate(invalid="ignore"):
        low = np.where(x > 0, beta.ppf(tail, np.maximum(x, tiny), np.maximum(n - x + 1, tiny)), 0.0)
        high = np.where(x < n, beta.ppf(1 - tail, x + 1, np.maximum(n - x, tiny)), 1.0)
    return low, high


def rate_interval(rates, episodes, confidence: float = CONFIDENCE):
    """The seed-level interval of a variant's success rate (the mean over seeds of each seed's rate) from the seeds'
    rates (the last axis: one per seed) and each seed's number of episodes (broadcast against `rates`); NaN with
    fewer than MIN_SEEDS_FOR_INTERVAL seeds. Vectorised as seed_interval.

    It is the union (the wider ends) of three 95 % intervals, each right where the others fail:
    - the t-interval over the seeds' rates (seed_interval): the spread between seeds as the seeds show it;
    - the t-interval over the seeds' logits, each rate shrunk by z^2/2 pseudo-successes and z^2/2 pseudo-failures
      (Agresti-Coull's "add two and two", z = 1.96), mapped back: near 0 and 100 % the seeds' rates are skewed
      towards the middle (a few good seeds pull the mean of a low rate up), and on the logit scale that skew is
      gone, so this interval reaches further towards 50 % than away from it;
    - a Clopper-Pearson interval on the mean rate at the effective number of episodes, the pooled episodes divided
      by the design effect the seeds show (their rates' variance over the binomial variance of one seed's rate,
      at least 1): it never has zero width, so seeds that agree exactly (all at 0 %, all at 100 %) still get an
      interval as wide as their episodes allow.
    Coverage, simulated (tests/test_reports.py: seed rates logit-normal around the true rate, the random-intercept
    model of clustered binary outcomes, their spread named by its standard deviation at a 50 % rate, 0, 10 and 25
    points, shrinking towards the edges as a rate's spread must: 25 points around a 1 % rate cannot exist; 3 and 5
    seeds; 34 episodes each): at least 93 % at true rates of 1, 2, 5, 50, 80, 95, 98 and 99 %, and so on a grid of
    rates every 1-5 points (about 94 % at its worst, 3 seeds 25 points apart around 65 %), where the t-interval over
    the rates alone covers 52-96 % (it collapses when the seeds agree). Limits: seed rates drawn from a beta
    distribution are covered at least 93 % at every rate up to a 15-point spread; at 25 points the beta is J-shaped
    below about 20 % and above 80 % (most seeds at the edge, a rare one far from it), and coverage there falls, to
    about 76 % at 6 % with 3 seeds: seeds that all sit at the edge cannot show a tail they did not draw. Costs: with
    3 seeds the interval is wide (t = 4.3), and the logit part makes it asymmetric near the edges."""
    from scipy.special import expit, logit
    from scipy.stats import norm

    r = np.asarray(rates, dtype=float)
    n = np.broadcast_to(np.asarray(episodes, dtype=float), r.shape)
    k = r.shape[-1]
    if k < MIN_SEEDS_FOR_INTERVAL:
        nan = np.full(r.shape[:-1], np.nan)
        return (math.nan, math.nan) if r.ndim == 1 else (nan, nan)
    t_low, t_high = seed_interval(r, confidence)
    pseudo = norm.ppf(0.5 + confidence / 2) ** 2 / 2
    logit_low, logit_high = seed_interval(logit((r * n + pseudo) / (n + 2 * pseudo)), confidence,
                                          bounds=(-np.inf, np.inf))
    mean = r.mean(axis=-1)
    per_episode = np.mean(1.0 / n, axis=-1)  # one seed's binomial variance is mean (1 - mean) * 1/n
    binomial = mean * (1 - mean) * per_episode
    with np.errstate(divide="ignore", invalid="ignore"):
        design = np.where(binomial > 0, np.maximum(1.0, r.var(axis=-1, ddof=1) / binomial), 1.0)
    n_eff = k / (per_episode * design)
    cp_low, cp_high = clopper_pearson(mean * n_eff, n_eff, confidence)
    low = np.clip(np.minimum.reduce([t_low, expit(logit_low), cp_low]), 0.0, 1.0)
    high = np.clip(np.maximum.reduce([t_high, expit(logit_high), cp_high]), 0.0, 1.0)
    return (float(low), float(high)) if r.ndim == 1 else (low, high)


def difference_interval(a, episodes_a, b, episodes_b, confidence: float = CONFIDENCE, correlation=0.0):
    """An interval of mean(a) - mean(b), two variants' rates over seeds (the last axis; each seed's episodes
    broadcast against its rates), built from the two rate_intervals (Zou and Donner's MOVER, the method behind
    Newcombe's interval for a difference of two proportions): the difference's lower end lies as far below it as
    A's interval reaches down and B's up, combined in quadrature less twice `correlation` (of the two means)
    times their product, and likewise for its upper end. Independent sides (correlation 0): never a point. NaN
    where a side has fewer than MIN_SEEDS_FOR_INTERVAL seeds. Vectorised as seed_interval."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    la, ha = rate_interval(a, episodes_a, confidence)
    lb, hb = rate_interval(b, episodes_b, confidence)
    pa, pb = a.mean(axis=-1), b.mean(axis=-1)
    d = pa - pb

    def reach(x, y):
        return np.sqrt(np.maximum(x ** 2 + y ** 2 - 2 * correlation * x * y, 0.0))

    low = np.maximum(-1.0, d - reach(pa - la, hb - pb))
    high = np.minimum(1.0, d + reach(ha - pa, pb - lb))
    return (float(low), float(high)) if a.ndim == 1 and b.ndim == 1 else (low, high)


def seed_correlation(a, b):
    """The correlation of two variants' rates over their paired seeds (the last axis), as the seeds show it (Pearson,
    taken between 0 and 1: a negative one would widen the interval past independence); 0 where a side's rates do
    not vary or every seed differs by the same, which shows nothing of how the two move together (the t-interval
    over the differences is then a point, and independence keeps the paired interval from being one)."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    da, db = a - a.mean(axis=-1, keepdims=True), b - b.mean(axis=-1, keepdims=True)
    scale = np.sqrt((da ** 2).sum(axis=-1) * (db ** 2).sum(axis=-1))
    same_difference = np.ptp(a - b, axis=-1) <= 1e-12
    with np.errstate(divide="ignore", invalid="ignore"):
        r = np.where((scale > 0) & ~same_difference, (da * db).sum(axis=-1) / scale, 0.0)
    return np.clip(r, 0.0, 1.0)


def paired_interval(a, b, episodes_a, episodes_b, confidence: float = CONFIDENCE):
    """The seed-level interval of A - B for rates measured seed by seed on the same episodes (the last axis: the
    paired seeds): the t-interval over the per-seed differences (seed_interval, clipped to +-1), widened to
    difference_interval at the two rates' seed_correlation where that reaches further. Mid-range the t-interval
    over the differences rules (the pairing's gain kept: seeds whose rates move together give a high correlation);
    near 0 and 100 %, where the differences are few distinct counts and the t-interval under-covers or shrinks to
    a point (every seed differing by the same, e.g. both variants at 0 %), the rate_intervals' reach takes over.
    Simulated (tests/test_reports.py): at least 93 % coverage from 1 % to 99 %, episodes shared or not, 3 and 5
    seeds, spreads 0 and 25 points; never a point. Vectorised."""
    a, b = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    t_low, t_high = seed_interval(a - b, confidence, bounds=(-1.0, 1.0))
    d_low, d_high = difference_interval(a, episodes_a, b, episodes_b, confidence, seed_correlation(a, b))
    low, high = np.fmin(t_low, d_low), np.fmax(t_high, d_high)  # fmin/fmax: a NaN part leaves the other
    return (float(low), float(high)) if np.ndim(low) == 0 else (low, high)


# ------------------------------------------------------------------------------ comparing two variants
TIE = 1e-12  # rates are k/n: a permuted statistic this close to the observed one is as extreme


def sign_flip_p(differences: Sequence[float]) -> float:
    """Exact two-sided p of a paired comparison: the share of the 2**K sign flips of the K differences whose mean
    is at least as far from 0 as the observed one (under "no difference" each seed's difference is as likely
    negated). With 3 seeds it cannot go below 2/8 = 0.25: three paired seeds cannot reject anything."""
    d = np.asarray(differences, dtype=float)
    if d.size == 0:
        return math.nan
    signs = np.array(list(itertools.product((1.0, -1.0), repeat=d.size)))
    flipped = np.abs(signs @ d)
    return float(np.mean(flipped >= abs(d.sum()) - TIE))


EXACT_SPLITS = 200_000  # up to this many splits (10 + 10 models: 184,756) the permutation p is exact
RANDOM_SPLITS = 20_000  # beyond, estimated from this many random splits (a fixed seed: the same p every time)


def permutation_p(a: Sequence[float], b: Sequence[float]) -> float:
    """Two-sided p of two independent groups: the share of the ways to split the pooled values into groups of
    len(a) and len(b) whose difference of means is at least as far from 0 as the observed one; exact up to
    EXACT_SPLITS splits, else from RANDOM_SPLITS random ones (enumerating 15 + 15 models would need 155
    million)."""
    x = np.r_[np.asarray(a, dtype=float), np.asarray(b, dtype=float)]
    if not len(a) or not len(b):
        return math.nan
    observed = abs(np.mean(a) - np.mean(b))
    total, na = x.sum(), len(a)
    if math.comb(x.size, na) <= EXACT_SPLITS:
        sums = x[np.array(list(itertools.combinations(range(x.size), na)))].sum(axis=1)
    else:
        shuffled = np.random.default_rng(0).permuted(np.tile(x, (RANDOM_SPLITS, 1)), axis=1)
        sums = shuffled[:, :na].sum(axis=1)
    diffs = np.abs(sums / na - (total - sums) / len(b))
    return float(np.mean(diffs >= observed - TIE))


def paired_comparison(a: Mapping[int, float], b: Mapping[int, float], episodes_a: Mapping[int, float] | None = None,
                      episodes_b: Mapping[int, float] | None = None) -> dict:
    """A - B over the seeds both have, each seed's two rates measured on the same episodes: the mean of the
    per-seed differences, its seed-level interval and the exact sign-flip p (sign_flip_p); `n` counts the paired
    seeds. The interval: with the seeds' episode counts (success rates) paired_interval, else the t-interval over
    the per-seed differences (seed_interval on the differences, clipped to +-1: for values that are no rates)."""
    seeds = sorted(set(a) & set(b))
    d = np.array([a[s] - b[s] for s in seeds], dtype=float)
    if episodes_a is not None and episodes_b is not None and d.size:
        low, high = paired_interval([a[s] for s in seeds], [b[s] for s in seeds], [episodes_a[s] for s in seeds],
                                    [episodes_b[s] for s in seeds])
    else:
        low, high = seed_interval(d, bounds=(-1.0, 1.0))
    return {"test": "paired", "n": len(seeds), "difference": float(d.mean()) if d.size else math.nan,
            "low": low, "high": high, "p": sign_flip_p(d)}


def group_comparison(a: Sequence[float], b: Sequence[float], confidence: float = CONFIDENCE) -> dict:
    """mean(a) - mean(b) of two independent groups of models' rates (e.g. a.c. models vs plain ones, or two
    studies whose seeds saw different episodes): Welch's t-interval (clipped to +-1) and the exact permutation p
    (permutation_p); `n` counts the models, as "len(a)+len(b)"."""
    from scipy.stats import t as student_t

    x, y = np.asarray(a, dtype=float), np.asarray(b, dtype=float)
    out = {"test": "groups", "n": f"{x.size}+{y.size}", "difference": float(x.mean() - y.mean()),
           "low": math.nan, "high": math.nan, "p": permutation_p(x, y)}
    if min(x.size, y.size) >= MIN_SEEDS_FOR_INTERVAL:
        vx, vy = x.var(ddof=1) / x.size, y.var(ddof=1) / y.size
        se = math.sqrt(vx + vy)
        dof = (vx + vy) ** 2 / (vx ** 2 / (x.size - 1) + vy ** 2 / (y.size - 1)) if se > 0 else x.size + y.size - 2
        half = student_t.ppf(0.5 + confidence / 2, dof) * se
        out["low"], out["high"] = max(-1.0, out["difference"] - half), min(1.0, out["difference"] + half)
    return out


def run_success_metrics(successes: list[float]) -> dict[str, float]:
    """success_rate, success_ci_low, success_ci_high, n_rollouts from one run's per-episode 0/1 values."""
    n = len(successes)
    k = int(round(sum(successes)))
    low, high = wilson_interval(k, n)
    return {"success_rate": k / n if n else math.nan, "success_ci_low": low, "success_ci_high": high,
            "n_rollouts": float(n)}


def success_over_seeds(per_seed: Mapping[int, tuple[float, float]]) -> dict:
    """One (variant, task) over its seeds, from each seed's (success rate, rollouts): the mean over seeds, the seeds'
    rates, the pooled successes/rollouts with their Wilson interval (ci_*) and the seed-level interval
    (seed_*; rate_interval)."""
    logged = {int(s): (float(r), int(n)) for s, (r, n) in sorted(per_seed.items())
              if not (pd.isna(r) or pd.isna(n)) and int(n) > 0}
    counts = {s: (int(round(r * n)), n) for s, (r, n) in logged.items()}
    k = sum(c[0] for c in counts.values())
    n = sum(c[1] for c in counts.values())
    rates = {s: r for s, (r, _) in logged.items()}
    low, high = wilson_interval(k, n)
    vals = np.array(list(rates.values()), dtype=float)
    slow, shigh = rate_interval(vals, [m for _, m in logged.values()])
    return {"mean": float(vals.mean()) if vals.size else math.nan,
            "std": float(vals.std()) if vals.size else math.nan,
            "seeds": len(counts), "seed_rates": rates, "successes": k, "n": n,
            "ci_low": low, "ci_high": high, "seed_low": slow, "seed_high": shigh}


def success_rows(evals: pd.DataFrame, variants: Sequence[str] | None = None,
                  tasks: Sequence[str] | None = None) -> pd.DataFrame:
    """One row per (variant, eval_task) from a long frame of finished runs (columns variant, eval_task, seed,
    success_rate, n_rollouts), in the given orders (else as first seen); see success_over_seeds for the columns."""
    need = {"variant", "eval_task", "seed", "success_rate", "n_rollouts"}
    if evals.empty or not need <= set(evals.columns):
        return pd.DataFrame(columns=["variant", "eval_task", "mean", "std", "seeds", "seed_rates", "successes", "n",
                                     "ci_low", "ci_high", "seed_low", "seed_high"])
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
                rows.append({"variant": variant, "eval_task": task, **success_over_seeds(per_seed)})
    return pd.DataFrame(rows)


def eval_rows(runs: Iterable) -> pd.DataFrame:
    """The long frame success_rows reads, from MLflow runs (FINISHED ones only): metrics <task>/success_rate and
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


def points(x: float) -> str:
    """A difference of rates in percentage points, e.g. '+12' ('0', not '-0', for what rounds to zero)."""
    if math.isnan(x):
        return "–"
    whole = round(100 * x)
    return f"{whole:+d}" if whole else "0"


def p_value(p: float) -> str:
    """A p-value as printed: two decimals, three below 0.01, and '< 0.001' below that (never '0.000')."""
    if math.isnan(p):
        return "–"
    return "< 0.001" if p < 0.001 else f"{p:.3f}" if p < 0.01 else f"{p:.2f}"


def success_table(agg: pd.DataFrame, variant_label=str, task_label=str) -> pd.DataFrame:
    """THE success table, as strings: one row per (task, variant) with the mean success over seeds, each seed's
    rate, the seed-level and the pooled Wilson interval, and what n counts (rollouts, seeds). Rows of `agg`
    with no seed (a gap) keep their row with dashes; a `mark` column (e.g. '†') is appended to the rate."""
    rows = []
    for r in agg.to_dict("records"):
        rates = r.get("seed_rates") or {}
        seeds = int(r.get("seeds") or 0)
        rows.append({
            "task": task_label(r["eval_task"]), "variant": variant_label(r["variant"]),
            "success": (pct(r["mean"]) + str(r.get("mark") or "")) if seeds else "gap",
            "per seed": " / ".join(pct(v) for v in rates.values()) or "–",
            SEED_COLUMN: interval(r["seed_low"], r["seed_high"]) if seeds else "–",
            WILSON_COLUMN: interval(r["ci_low"], r["ci_high"]) if seeds else "–",
            "rollouts": str(int(r["n"])) if seeds else "0",
            "seeds": str(seeds),
        })
    return pd.DataFrame(rows, columns=["task", "variant", "success", "per seed", SEED_COLUMN, WILSON_COLUMN,
                                       "rollouts", "seeds"])
