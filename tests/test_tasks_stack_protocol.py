"""Stacking's protocol between the blocks (eval.stack_restart: "place_pose" or "start", envs/tasks/stack_protocol.py)
and the check a failed tower is put down to (failed_block, failed_<check>)."""

from __future__ import annotations

import numpy as np
import pytest

from envs.blocks import BlockState, level_z
from envs.tasks import get_task, task_class
from envs.tasks.pickplace import MAX_TILT, START_BOX, XY_TOL, Z_TOL, tip_poses
from envs.tasks.stack import SUB_HORIZON
from envs.tasks.stack_protocol import (
    FAILED_CHECKS,
    LIFT_STEPS,
    RETURN_STEPS,
    BlockAtEnd,
    failed_check,
    physics_path,
)

TOL = (XY_TOL, Z_TOL, MAX_TILT)
GOAL = np.array([0.6, 0.1, level_z(1)])


def _block(dx: float = 0.0, dz: float = 0.0, tilt: float = 0.0) -> BlockState:
    """A block whose bottom sits dx (x) and dz (z) off GOAL, tilted `tilt` rad."""
    return BlockState(centre=GOAL + [dx, 0.0, 0.02 + dz], tilt=tilt)


def test_a_failed_level_is_put_down_to_the_first_check_its_block_fails():
    at_goal = BlockAtEnd(_block(), touched=False, grip=0.0)
    assert failed_check(1, False, at_goal, GOAL, False, 0.0, TOL) == "never_came"
    assert failed_check(1, True, None, GOAL, False, 0.0, TOL) == "no_block"
    assert failed_check(1, True, at_goal, GOAL, False, 0.0, TOL) == "knocked_down"  # placed, gone at the end
    moved = BlockAtEnd(_block(), touched=False, grip=0.0, after_move=_block(dx=0.05))
    assert failed_check(1, True, moved, GOAL, False, 0.0, TOL) == "knocked_by_move"
    held = BlockAtEnd(_block(dz=0.03), touched=True, grip=1.0)
    assert failed_check(1, True, held, GOAL, False, 0.0, TOL) == "not_released"
    dropped_elsewhere = BlockAtEnd(_block(dx=0.05, dz=0.03), touched=False, grip=1.0)  # closed on nothing
    assert failed_check(1, True, dropped_elsewhere, GOAL, False, 0.0, TOL) == "off_target"
    assert failed_check(1, True, BlockAtEnd(_block(dz=0.02), False, 0.0), GOAL, False, 0.0, TOL) == "height_off"
    assert failed_check(1, True, BlockAtEnd(_block(tilt=0.5), False, 0.0), GOAL, False, 0.0, TOL) == "tilted"
    # every level stands: the release at the end failed
    assert failed_check(None, True, at_goal, GOAL, True, 0.0, TOL) == "touched"
    assert failed_check(None, True, at_goal, GOAL, False, 1.0, TOL) == "grip_closed"
    assert set(FAILED_CHECKS) >= {"never_came", "off_target", "tilted", "knocked_down", "not_released"}


def test_start_restarts_are_drawn_per_episode_from_the_start_distribution():
    place, start = get_task("stack"), get_task("stack", restart="start")
    a, b = place.episodes(3, seed=5), start.episodes(3, seed=5)
    for x, y in zip(a, b, strict=True):  # the episodes themselves are those of the place-pose protocol
        assert np.array_equal(x.q0, y.q0) and np.array_equal(x.psi, y.psi) and "restart_q" not in x.info
        assert {k: v for k, v in y.info.items() if k != "restart_q"} == x.info
    configs = np.array([ep.info["restart_q"] for ep in b])
    assert configs.shape == (3, 2, 7) and len({c.tobytes() for c in configs.reshape(6, 7)}) == 6
    again = start.episodes(3, seed=5)
    assert all(ep.info["restart_q"] == y.info["restart_q"] for ep, y in zip(again, b, strict=True))
    assert start.episodes(2, seed=5)[1].info["restart_q"] == b[1].info["restart_q"]  # seeded by (seed, episode)
    tip, _ = tip_poses(configs.reshape(-1, 7))
    assert all(np.all((tip[:, i] >= lo) & (tip[:, i] <= hi)) for i, (lo, hi) in enumerate(START_BOX))
    # an eval option: the dataset (config) and the default protocol stay as they were
    assert start.config() == place.config() and place.restart == "place_pose"
    assert task_class("stack").for_evaluation({}, {"stack_restart": "start"}).restart == "start"
    with pytest.raises(ValueError, match="eval.stack_restart: 'home' is not allowed"):
        task_class("stack").for_evaluation({}, {"stack_restart": "home"})
    with pytest.raises(ValueError, match="restart must be one of"):
        get_task("stack", restart="home")


def test_the_physics_plays_a_straight_lift_and_a_joint_move_between_the_model_rows():
    ep = get_task("stack", restart="start").episodes(1, seed=2)[0]
    rng = np.random.default_rng(0)
    q = ep.q0 + np.cumsum(rng.normal(0, 0.002, (ep.horizon + 1, 7)), axis=0)
    grip = (np.arange(ep.horizon + 1) % 2).astype(float)
    path = physics_path(q, grip, SUB_HORIZON, ep.info["restart_q"])
    move = LIFT_STEPS + RETURN_STEPS
    assert len(path.q) == len(q) + 2 * move and path.moved == [SUB_HORIZON + move, 2 * SUB_HORIZON + 2 * move]
    assert path.spans == [(0, SUB_HORIZON), (SUB_HORIZON + move, 2 * SUB_HORIZON + move),
                          (2 * (SUB_HORIZON + move), len(path.q) - 1)]
    for k, t in enumerate((SUB_HORIZON, 2 * SUB_HORIZON)):
        rows = path.q[t + k * move + 1: t + (k + 1) * move + 1]
        np.testing.assert_allclose(rows[-1], ep.info["restart_q"][k])  # ends at the drawn start configuration
        assert (path.grip[t + k * move + 1: t + (k + 1) * move + 1] == grip[t]).all()  # the grip command held
        tip, _ = tip_poses(np.concatenate([q[t][None], rows[:LIFT_STEPS]]))
        assert np.abs(tip[:, :2] - tip[0, :2]).max() < 2e-3 and (np.diff(tip[:, 2]) > -1e-6).all()  # straight up
    np.testing.assert_array_equal(path.q[: SUB_HORIZON + 1], q[: SUB_HORIZON + 1])  # the model's rows as they are
    np.testing.assert_array_equal(path.q[-SUB_HORIZON:], q[-SUB_HORIZON:])
    same = physics_path(q, grip, SUB_HORIZON, None)  # place pose: nothing inserted
    assert same.q is q and same.moved == [] and same.spans[1] == (SUB_HORIZON, 2 * SUB_HORIZON)


@pytest.mark.slow
def test_an_arm_that_never_moves_never_came_for_the_first_block():
    st = get_task("stack")
    ep = st.episodes(1, seed=1)[0]
    q = np.repeat(ep.q0[None], ep.horizon + 1, axis=0)
    r = st.evaluate(q, np.zeros(ep.horizon + 1), ep)
    assert r["success"] == 0.0 and r["failed_block"] == 1.0 and r["failed_never_came"] == 1.0
    assert sum(r[f"failed_{c}"] for c in FAILED_CHECKS) == 1.0
    assert "tower_stood_move_1" not in r and "tower_stood_move_2" not in r  # no scripted move to judge


@pytest.mark.slow
def test_the_expert_stacks_under_the_start_protocol_and_each_move_leaves_the_tower_standing():
    st = get_task("stack", restart="start")
    ep = st.episodes(1, seed=0)[0]
    q, grip = st.expert_rollout(ep)
    assert q.shape == (ep.horizon + 1, 7)
    np.testing.assert_allclose(q[SUB_HORIZON + 1] - ep.info["restart_q"][0], 0.0, atol=0.05)  # from the start
    r = st.evaluate(q, grip, ep)
    assert r["success"] == 1.0 and r["blocks_in_tower"] == 3 and r["failed_block"] == 0.0
    assert r["tower_stood_move_1"] == 1.0 and r["tower_stood_move_2"] == 1.0
    assert not any(r[f"failed_{c}"] for c in FAILED_CHECKS)
