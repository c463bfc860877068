"""reports.mode_use on hand-made per-seed rows: the variant rows (mean over seeds with the seed-level t-interval)
and the paired MDN - deterministic comparisons (per-seed differences, exact sign-flip p)."""

from __future__ import annotations

import pandas as pd
import pytest

from experiments.stats import seed_interval, sign_flip_p
from reports.analyses.mode_use import comparisons, even_coin_bits, variant_summary


def _rows() -> pd.DataFrame:
    rows = []
    for variant, both, entropy in (("ac-lstm", (0.0, 0.0, 0.0), (0.0, 0.0, 0.0)),
                                   ("ac-lstm-mdn", (0.5, 0.7, 0.6), (0.4, 0.6, 0.5))):
        for seed in range(3):
            rows.append({"eval_task": "t", "variant": variant, "seed": seed, "run_id": f"{variant}{seed}",
                         "repeats": 10, "success": 0.8, "entropy": entropy[seed], "both": both[seed],
                         "between": 0.1})
    return pd.DataFrame(rows)


def test_variant_rows_are_seed_means_with_the_t_interval():
    s = variant_summary(_rows()).set_index("variant")
    assert s.loc["ac-lstm-mdn", "both"] == pytest.approx(0.6)
    assert (s.loc["ac-lstm-mdn", "both_low"], s.loc["ac-lstm-mdn", "both_high"]) == pytest.approx(
        seed_interval([0.5, 0.7, 0.6]))
    assert s.loc["ac-lstm", "entropy"] == 0 and s.loc["ac-lstm", "seeds"] == 3


def test_paired_comparisons_of_the_mixture_head_with_its_deterministic_twin():
    c = comparisons(_rows())
    both = c[c["measure"] == "episodes with both modes"].iloc[0]
    assert (both["A"], both["B"], both["n"]) == ("ac-lstm-mdn", "ac-lstm", 3)
    assert both["difference"] == pytest.approx(0.6) and both["p"] == sign_flip_p([0.5, 0.7, 0.6]) == 0.25
    assert len(c) == 2  # lstm-mdn / lstm absent from the rows: no comparison


def test_an_even_coin_averages_below_one_bit_over_r_draws():
    assert even_coin_bits(1) == 0 and even_coin_bits(2) == pytest.approx(0.5)  # 2 draws: half the time 1/1
    assert even_coin_bits(10) == pytest.approx(0.9235, abs=1e-4)
