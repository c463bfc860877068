"""Success rates with Wilson 95% score intervals (scipy's binomtest)."""

from __future__ import annotations

import math

from scipy.stats import binomtest


def wilson_interval(successes: int, n: int, confidence: float = 0.95) -> tuple[float, float]:
    """Wilson score interval of a binomial proportion; (nan, nan) when n == 0."""
    if n == 0:
        return math.nan, math.nan
    ci = binomtest(int(successes), int(n)).proportion_ci(confidence_level=confidence, method="wilson")
    return float(ci.low), float(ci.high)


def success_summary(successes: list[float]) -> dict[str, float]:
    """success_rate, success_ci_low, success_ci_high, n_rollouts from per-episode 0/1 values."""
    n = len(successes)
    k = int(round(sum(successes)))
    low, high = wilson_interval(k, n)
    return {"success_rate": k / n if n else math.nan, "success_ci_low": low, "success_ci_high": high,
            "n_rollouts": float(n)}
