"""Reacher's start_joint_range constructor argument: cache key, validation, effect on starts."""

from __future__ import annotations

import numpy as np
import pytest

from envs.datasets import config_hash
from envs.kinematics import tip_position_np
from envs.robot import NEUTRAL_Q
from envs.tasks import get_task
from envs.tasks.reacher import START_JOINT_RANGE, Reacher


def test_default_config_and_another_range_changes_the_cache_key():
    default = Reacher()
    assert default.start_joint_range == START_JOINT_RANGE
    assert default.config()["start_joint_range"] == START_JOINT_RANGE
    assert config_hash(get_task("reacher").config()) == config_hash(default.config())
    narrow = Reacher(start_joint_range=0.05)
    assert narrow.config()["start_joint_range"] == 0.05
    assert config_hash(narrow.config()) != config_hash(default.config())


@pytest.mark.parametrize("bad", [-0.1, 4.0])
def test_out_of_range_value_is_a_clear_error(bad):
    with pytest.raises(ValueError, match="start_joint_range"):
        Reacher(start_joint_range=bad)


def test_narrow_range_gives_starts_closer_to_the_neutral_tip():
    rng_a, rng_b = np.random.default_rng(0), np.random.default_rng(0)
    neutral_tip = tip_position_np(NEUTRAL_Q[None])[0]
    wide = tip_position_np(Reacher(start_joint_range=0.3).sample_starts(rng_a, 16))
    narrow = tip_position_np(Reacher(start_joint_range=0.02).sample_starts(rng_b, 16))
    spread = lambda tips: np.linalg.norm(tips - neutral_tip, axis=-1).max()  # noqa: E731
    assert spread(narrow) < 0.05 < spread(wide)
