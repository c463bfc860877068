"""reports.analyses.placement: pick-and-place success judged on the block beside the strict criterion, from the
rollouts' per-episode facts (recorded, or derived from older rollouts' facts), per seed with seed-level intervals."""

from __future__ import annotations

import numpy as np
import pandas as pd

from reports.analyses import placement


def _arrays(seed: int, strict: list[float], placed: list[float] | None) -> dict[str, np.ndarray]:
    out = {"seed": np.full(len(strict), seed), "success": np.array(strict), "success_strict": np.array(strict)}
    if placed is not None:
        out["placed"] = np.array(placed)
    return out


def test_placed_is_read_or_derived_from_the_facts_older_rollouts_recorded():
    facts = placement.episode_facts(_arrays(0, [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]))
    assert facts["strict"].tolist() == [1.0, 0.0, 0.0] and facts["placed"].tolist() == [1.0, 1.0, 0.0]
    # rollouts from before `placed`: the task's checks on the facts they kept, in the task's own tolerances
    old = {"seed": np.zeros(4, int), "success": np.array([1.0, 0.0, 0.0, 0.0]),
           "xy_error": np.array([0.005, 0.005, 0.03, 0.005]), "z_error": np.array([0.001, -0.002, 0.0, 0.0]),
           "tilt": np.array([0.01, 0.02, 0.0, 0.0]), "touching": np.array([0.0, 0.0, 0.0, 1.0]),
           "tip_to_block": np.array([0.11, 0.11, 0.11, 0.11])}
    assert placement.episode_facts(old)["placed"].tolist() == [1.0, 1.0, 0.0, 0.0]
    assert placement.episode_facts(old)["strict"].tolist() == [1.0, 0.0, 0.0, 0.0]  # success is the strict one
    del old["tilt"]  # not recorded: no verdict
    assert placement.episode_facts(old)["placed"].isna().all()


def test_table_sets_both_criteria_side_by_side_with_their_intervals():
    seeds = [placement.episode_facts(_arrays(s, [1.0] * k + [0.0] * (10 - k), [1.0] * (k + 6) + [0.0] * (4 - k)))
             for s, k in enumerate((2, 4, 3))]
    facts = pd.concat(seeds, ignore_index=True)
    unrecorded = placement.episode_facts(_arrays(0, [1.0, 0.0], None))
    agg = pd.DataFrame([{"study": "s", "variant": "ac-lstm-mdn", "setting": "–", "seeds": 3, "facts": facts,
                         "eval_task": "pick-place"},
                        {"study": "old", "variant": "ac-lstm-mdn", "setting": "old", "seeds": 1, "facts": unrecorded,
                         "eval_task": "pick-place-changing-goal"}])
    table = placement.placement_table(agg)
    row = table.iloc[0].to_dict()
    assert row["success (strict)"].startswith("30% (") and row["placed (on the block)"].startswith("90% (")
    assert row["placed − strict (points)"].startswith("+60 (") and row["episodes"] == "30" and row["seeds"] == "3"
    low, high = (int(x) for x in row["placed − strict (points)"].split("(")[1].rstrip(")").split(" to "))
    assert 0 < low < 60 < high  # three seeds each 6 episodes apart: clear of zero, yet never a point
    assert table.iloc[1]["placed (on the block)"] == "not recorded" and table.iloc[1]["placed − strict (points)"] == "–"
    assert placement.placement_table(pd.DataFrame()).empty
