"""reports.analyses.stacking: which block the stacking episodes get to, from the rollouts (hand-made episodes whose
answers are known), its table and figure; the real rollouts: the RESULTS.md regeneration test."""

from __future__ import annotations

import numpy as np
import pandas as pd

from reports.analyses.stacking import REACH, episode_facts, shares, stacking_figure, stacking_table

SUB = 10  # steps per sub-episode of the hand-made episodes
GRASP = np.array([0.55, -0.20, -0.12])
AWAY = GRASP + [0.0, 0.3, 0.2]


def _episode(*came: bool) -> np.ndarray:
    """A tip path (3 * SUB + 1, 3): in sub-episode k it dips to the grasp point if came[k], else stays away."""
    path = np.repeat(AWAY[None], 3 * SUB + 1, axis=0)
    for k, c in enumerate(came):
        if c:
            path[k * SUB + SUB // 2] = GRASP + [0.0, 0.0, REACH / 2]
    return path


def _arrays() -> dict[str, np.ndarray]:
    tips = np.stack([_episode(True, True, True), _episode(True, False, False), _episode(False, False, False)])
    return {"tip": tips, "success": np.array([1.0, 0.0, 0.0]), "blocks_in_tower": np.array([3.0, 1.0, 0.0])}


def test_facts_and_shares_per_block():
    facts = episode_facts(_arrays(), SUB, GRASP)
    np.testing.assert_allclose(facts["closest_1"], [REACH / 2, REACH / 2, np.linalg.norm(AWAY - GRASP)])
    came, tower = shares(facts)
    np.testing.assert_allclose(came, [2 / 3, 1 / 3, 1 / 3])
    np.testing.assert_allclose(tower, [2 / 3, 1 / 3, 1 / 3])


def test_table_and_figure(tmp_path):
    cells = pd.DataFrame([{"study": "s", "variant": "ac-lstm-mdn", "setting": "retreat_starts=0.3", "seeds": 1,
                           "facts": episode_facts(_arrays(), SUB, GRASP)}])
    (row,) = stacking_table(cells).to_dict("records")
    assert row["success"] == "33%" and row["came for block 1 / 2 / 3 (< 2 cm)"] == "67% / 33% / 33%"
    assert row["tower of at least 1 / 2 / 3"] == "67% / 33% / 33%" and row["episodes"] == "3"
    assert row["median closest approach (cm)"] == "1.0 / 36.1 / 36.1"
    out = stacking_figure(cells, "pick-place", tmp_path)
    assert not out.gap and all(p.stat().st_size > 0 for p in out.paths)
    assert stacking_figure(cells.iloc[:0], "pick-place", tmp_path).gap
