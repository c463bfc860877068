"""reports.analyses.pick_place_failures: the stage each pick-and-place episode fails at, from the rollouts (hand-made
episodes whose answers are known), its table and figure; the real rollouts: the RESULTS.md regeneration test."""

from __future__ import annotations

import numpy as np
import pandas as pd

from reports.analyses import pick_place_failures as ppf
from reports.analyses.stacking import REACH

GRASP = np.array([0.55, -0.20, -0.12])
AWAY_POINT = GRASP + [0.0, 0.3, 0.2]
NEW_GOAL = np.array([0.6, 0.1, -0.15])
STEPS = 12


def _path(came: bool, end_over: np.ndarray | None = None) -> np.ndarray:
    """A tip path (STEPS, 3) that dips to the grasp point half-way if `came`, ending above `end_over` if given."""
    path = np.repeat(AWAY_POINT[None], STEPS, axis=0)
    if came:
        path[STEPS // 2] = GRASP + [0.0, 0.0, REACH / 2]
    if end_over is not None:
        path[-1] = end_over + [0.005, 0.0, 0.1]
    return path


def _arrays() -> dict[str, np.ndarray]:
    """Four episodes, one per stage: placed; never came; came, block 5 cm off the goal; came, block 1 cm off in xy
    and at the goal's height but failed, its tip still 3 cm from it. The last two end over the new goal; the last
    did not switch goal."""
    tips = np.stack([_path(True), _path(False), _path(True, NEW_GOAL), _path(True, NEW_GOAL)])
    return {"tip": tips, "success": np.array([1.0, 0.0, 0.0, 0.0]), "xy_error": np.array([0.003, 0.3, 0.05, 0.01]),
            "z_error": np.array([0.002, 0.0, 0.0, 0.005]), "tip_to_block": np.array([0.1, 0.3, 0.2, 0.03]),
            "new_goal": np.repeat(NEW_GOAL[None], 4, axis=0),
            "switch_step": np.array([5, 5, 5, -1])}


def test_constants_are_the_tasks_own():
    from envs.tasks.pickplace import AWAY, MAX_TILT, XY_TOL, Z_TOL

    assert (ppf.XY_TOL, ppf.Z_TOL, ppf.MAX_TILT, ppf.AWAY) == (XY_TOL, Z_TOL, MAX_TILT, AWAY)


def test_each_episode_in_the_first_stage_it_did_not_get_through():
    facts = ppf.episode_facts(_arrays(), GRASP)
    assert list(facts["stage"]) == ["placed", "never came for the block", "off the goal", "not released"]
    assert list(facts["release_fault"]) == ["", "", "", "tip at the block"]
    lifted = {**_arrays(), "z_error": np.array([0.0, 0.0, 0.0, 0.1])}  # the height is checked first
    assert list(ppf.episode_facts(lifted, GRASP)["release_fault"]) == ["", "", "", "height off"]
    away = {**_arrays(), "tip_to_block": np.full(4, 0.2)}  # tilt, fingers, grip command: not recorded
    assert list(ppf.episode_facts(away, GRASP)["release_fault"]) == ["", "", "", "not recorded"]
    for key, fault in (("tilt", "tilted"), ("touching", "a finger on it"), ("grip_closed", "grip left closed")):
        recorded = {**away, "tilt": np.zeros(4), "touching": np.zeros(4), "grip_closed": np.zeros(4)}
        recorded[key] = np.array([0.0, 0.0, 0.0, 1.0])
        assert list(ppf.episode_facts(recorded, GRASP)["release_fault"]) == ["", "", "", fault]
    assert facts["closed_again"].isna().all()  # grip_closes not recorded
    closes = {**away, "grip_closed": np.array([0.0, 0.0, 0.0, 1.0]), "grip_closes": np.array([1.0, 0.0, 1.0, 2.0])}
    np.testing.assert_array_equal(ppf.episode_facts(closes, GRASP)["closed_again"], [0.0, 0.0, 0.0, 1.0])
    # the last episode did not switch goal: no answer for it
    np.testing.assert_array_equal(facts["over_new_goal"], [0.0, 0.0, 1.0, np.nan])
    np.testing.assert_allclose(ppf.stage_shares(facts), [0.25, 0.25, 0.25, 0.25])
    plain = {k: v for k, v in _arrays().items() if k not in ("new_goal", "switch_step")}
    assert ppf.episode_facts(plain, GRASP)["over_new_goal"].isna().all()


def test_table_and_figure(tmp_path):
    facts = ppf.episode_facts(_arrays(), GRASP)
    agg = pd.DataFrame([{"study": "s", "variant": v, "setting": "–", "seeds": 1, "facts": facts, "eval_task": task}
                        for task in ppf.EVAL_TASKS for v in ("lstm", "ac-lstm-mdn")])
    table = ppf.failure_table(agg)
    assert list(table["task"]) == ["pick-and-place"] * 2 + ["changing-goal pick-and-place"] * 2
    assert list(table["variant"]) == ["LSTM", "a.c. LSTM-MDN"] * 2
    row = table.iloc[0].to_dict()
    assert [row[s] for s in ppf.STAGES] == ["25%", "25%", "25%", "25%"]
    assert row["not released, by check: " + " / ".join(ppf.RELEASE_FAULTS)] == "0 / 0 / 0 / 1 / 0 / 0"
    assert row["tip ends over the new goal (< 3 cm)"] == "33%" and row["episodes"] == "4"
    assert row["grip left closed: shut again after opening"] == "–"  # no episode failed by the grip command
    shut = {**_arrays(), "tip_to_block": np.full(4, 0.2), "tilt": np.zeros(4), "touching": np.zeros(4),
            "grip_closed": np.array([0.0, 0.0, 0.0, 1.0]), "grip_closes": np.array([1.0, 1.0, 1.0, 3.0])}
    shut_row = ppf.failure_table(agg.assign(facts=[ppf.episode_facts(shut, GRASP)] * len(agg))).iloc[0]
    assert shut_row["grip left closed: shut again after opening"] == "1 of 1"
    out = ppf.failure_figure(agg, "pick-place", tmp_path)
    assert not out.gap and all(p.stat().st_size > 0 for p in out.paths)
    assert ppf.failure_figure(agg.iloc[:0], "pick-place", tmp_path).gap
    assert ppf.failure_table(agg.iloc[:0]).empty
