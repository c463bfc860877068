"""reports.analyses.goal_switch: the anatomy of the changing-goal reacher's failures from the rollouts (hand-made
episodes whose answers are known), and its figure."""

from __future__ import annotations

import numpy as np
import pandas as pd

from reports.analyses.goal_switch import MOVING, episode_facts, min_jerk_remaining, switch_figure, switch_table

GOAL, NEW = np.array([0.6, 0.0, 0.1]), np.array([0.6, 0.3, 0.1])
H, K = 20, 10  # horizon and switch step of the hand-made episodes


def _path(*legs: tuple[np.ndarray, np.ndarray, int]) -> np.ndarray:
    """A tip path (H+1, 3) of straight legs (start, end, steps), holding the last point to the horizon."""
    points = [np.linspace(a, b, n + 1)[1:] for a, b, n in legs]
    path = np.concatenate([[legs[0][0]], *points])
    return np.concatenate([path, np.repeat(path[-1:], H + 1 - len(path), axis=0)])


def _arrays() -> dict[str, np.ndarray]:
    start = np.array([0.6, -0.2, 0.1])
    tips = np.stack([
        _path((start, GOAL, K), (GOAL, NEW, 6)),  # adapts: at the new goal 6 steps after the switch
        _path((start, GOAL, K)),  # ignores the switch: holds the first goal
        _path((start, GOAL, K), (GOAL, GOAL + 0.3 * (NEW - GOAL), H - K)),  # too slow: 30 % of the way, moving
        _path((start, GOAL, K)),  # an episode without a switch: left out
    ])
    return {"tip": tips, "goal": np.repeat(GOAL[None], 4, axis=0), "new_goal": np.repeat(NEW[None], 4, axis=0),
            "switch_step": np.array([K, K, K, -1]), "success": np.array([1.0, 0.0, 0.0, 0.0])}


def test_episode_facts_tell_ignored_from_too_slow():
    facts = episode_facts(_arrays())
    assert len(facts) == 3 and facts["success"].tolist() == [1.0, 0.0, 0.0]
    np.testing.assert_allclose(facts["progress"], [1.0, 0.0, 0.3], atol=1e-12)
    assert facts["steps_to_half"][0] == 3 and facts["steps_to_half"][1:].isna().all()
    ignored, slow = facts.iloc[1], facts.iloc[2]
    assert ignored["end_to_first"] < ignored["end_to_new"] and ignored["end_speed"] < MOVING
    assert slow["end_to_first"] < slow["end_to_new"] and slow["end_speed"] > MOVING  # 0.009 m per step
    assert len(facts["remaining"][0]) == H - K + 1 and facts["remaining"][0][0] == 1.0


def test_table_and_figure(tmp_path):
    cells = pd.DataFrame([{"study": "s", "variant": "ac-lstm-mdn", "setting": "goal_switches=0.5", "seeds": 1,
                           "facts": episode_facts(_arrays())}])
    (row,) = switch_table(cells).to_dict("records")
    assert row["success"] == "33%" and row["failures that never set off"] == "50%"  # the one that held
    assert row["failures still moving"] == "50%" and row["median progress at the end"] == "30%"
    assert row["median steps to half-way"] == "–" and row["episodes"] == "3"  # two of three never get half-way
    fig = switch_figure(cells, "reacher", tmp_path)
    assert fig.gap is None and [p.suffix for p in fig.paths] == [".png", ".pdf"]
    assert switch_figure(cells.iloc[:0], "reacher", tmp_path).gap


def test_min_jerk_reference_starts_and_ends_at_rest():
    r = min_jerk_remaining(50, 60)
    assert r[0] == 1.0 and r[50] == 0.0 and r[59] == 0.0 and abs(r[25] - 0.5) < 1e-12
