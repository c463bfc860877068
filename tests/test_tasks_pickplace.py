"""Pick-and-place, stacking and changing-goal pick-and-place: dataset shape, state
layout, and the physics success predicates on expert and hand-spoiled trajectories."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.blocks import BLOCK_SIZE, PICK_XY, level_z
from envs.kinematics import default_kinematics, tip_position_np
from envs.sim import TABLE_TOP_Z
from envs.tasks import get_task
from envs.tasks.base import Episode
from envs.tasks.pickplace import GOAL_REGION, LEVELS, PickPlace, pad_rows
from envs.tasks.stack import SUB_HORIZON


@pytest.fixture(scope="module")
def task() -> PickPlace:
    return PickPlace(n_demos=3)


@pytest.fixture(scope="module")
def demos(task):
    return task.demos(seed=0)


def _episode_of(demos, i: int) -> Episode:
    """The evaluation episode a demo solves."""
    goal = demos.psi[i, 0]
    T = int(demos.lengths[i])
    return Episode(q0=demos.q[i, 0], psi=demos.psi[i, : T + 1], horizon=T,
                   info={"goal": goal.tolist(), "level": int(round((goal[2] - TABLE_TOP_Z) / BLOCK_SIZE))})


def _demo(demos, i: int) -> tuple[np.ndarray, np.ndarray]:
    T = int(demos.lengths[i])
    return demos.q[i, : T + 1], demos.grip[i, : T + 1]


def test_registry_and_model_tasks():
    assert get_task("pick-place").model_task == "pick-place"
    assert get_task("stack").model_task == "pick-place"
    assert get_task("pick-place-changing-goal").model_task == "pick-place"
    # one dataset: the evaluation-only tasks describe the same demonstrations
    assert get_task("stack").config() == get_task("pick-place").config()
    assert PickPlace().n_demos == 150


@pytest.mark.slow
def test_dataset_counts_lengths_and_meta(task, demos):
    assert len(demos) == 3
    assert ((demos.lengths >= 166) & (demos.lengths <= 170)).all()
    assert demos.q.shape == (3, demos.lengths.max() + 1, 7)
    assert demos.grip.shape == demos.q.shape[:2] and demos.psi.shape == (*demos.q.shape[:2], 3)
    assert set(np.unique(demos.grip)) <= {0.0, 1.0}
    assert demos.meta["expert_success"] == 1.0
    assert set(demos.meta["rejections"]) == {"ik", "physics"}
    goals = demos.psi[:, 0]
    assert np.allclose(demos.psi, goals[:, None])  # one goal per demo
    levels = (goals[:, 2] - TABLE_TOP_Z) / BLOCK_SIZE
    assert np.allclose(levels, np.round(levels)) and set(np.round(levels).astype(int)) <= set(LEVELS)
    (x0, x1), (y0, y1) = GOAL_REGION
    assert ((goals[:, 0] >= x0) & (goals[:, 0] <= x1) & (goals[:, 1] >= y0) & (goals[:, 1] <= y1)).all()
    for i in range(3):  # the gripper closes once and opens once
        g = demos.grip[i, : demos.lengths[i] + 1]
        assert np.count_nonzero(np.diff(g) == 1) == 1 and np.count_nonzero(np.diff(g) == -1) == 1


def test_state_layout_consistency(task, demos):
    kin = default_kinematics(torch.float64)
    s = task.demo_states(demos, kin)
    L = task.layout
    assert s.shape == (*demos.q.shape[:2], L.dim) and L.dim == 14 and L.gripper
    assert np.allclose(s[:, 0, L.dq], 0.0)
    q_rebuilt = demos.q[:, :1] + np.cumsum(s[:, :, L.dq], axis=1)
    assert np.allclose(q_rebuilt, demos.q, atol=1e-9)
    assert np.array_equal(s[:, :, L.grip][..., 0], demos.grip)
    assert np.allclose(s[:, :, L.phi], tip_position_np(demos.q) - demos.psi, atol=1e-9)
    assert np.allclose(s[:, :, L.psi], demos.psi)
    # the grasp: tip 3 cm above the pick block's bottom, where the gripper closes
    for i in range(3):
        t_close = int(np.argmax(demos.grip[i] > 0.5))
        tip = tip_position_np(demos.q[i, t_close])
        assert np.allclose(tip, [PICK_XY[0], PICK_XY[1], level_z(0) + 0.03], atol=2e-3)


@pytest.mark.slow
def test_expert_demo_succeeds_when_replayed_and_evaluation_is_repeatable(task, demos):
    q, grip = _demo(demos, 0)
    r = task.evaluate(q, grip, _episode_of(demos, 0))
    assert r["success"] == 1.0 and r["final_distance"] < 0.005 and r["grip_closes"] == 1.0
    assert r["placed"] == r["success_strict"] == 1.0 and r["grip_close_steps"] == (int(np.argmax(grip > 0.5)),)
    task.evaluate(*_demo(demos, 1), _episode_of(demos, 1))  # whatever ran before ...
    assert task.evaluate(q, grip, _episode_of(demos, 0)) == r  # ... the same rollout gives the same numbers


def test_never_closing_the_gripper_fails(task, demos):
    q, grip = _demo(demos, 1)
    r = task.evaluate(q, np.zeros_like(grip), _episode_of(demos, 1))
    assert r["success"] == 0.0 and r["final_distance"] > 0.1  # the block stayed at the pick position


@pytest.mark.slow
def test_block_placed_5cm_off_fails(task):
    ep = task.episodes(1, seed=3)[0]
    off = np.asarray(ep.info["goal"]) + [0.05, 0.0, 0.0]
    q, grip = task.expert_trajectory(ep.q0, off)
    r = task.evaluate(q, grip, ep)
    assert r["success"] == 0.0 and abs(r["xy_error"] - 0.05) < 0.005 and abs(r["z_error"]) < 0.005


@pytest.mark.slow
def test_holding_on_or_staying_at_the_block_fails(task, demos):
    q, grip = _demo(demos, 2)
    ep = _episode_of(demos, 2)
    t_open = int(np.flatnonzero(np.diff(grip) == -1)[0]) + 1
    never_released = task.evaluate(q, np.where(np.arange(len(grip)) >= t_open, 1.0, grip), ep)
    assert never_released["success"] == 0.0 and never_released["grip_closed"] == 1.0
    assert never_released["grip_closes"] == 1.0 and never_released["placed"] == 0.0  # carried off in the hand
    # placed and retreated, then the command shut again in the last steps: it counts a second close
    shut_again = task.evaluate(q, np.where(np.arange(len(grip)) >= len(grip) - 2, 1.0, grip), ep)
    assert shut_again["success"] == 0.0 and shut_again["grip_closed"] == 1.0 and shut_again["grip_closes"] == 2.0
    assert shut_again["final_distance"] < 0.01  # the block itself stands placed
    # judged on the block it is placed; the strict criterion (success) also wants the last command open
    assert shut_again["placed"] == 1.0 and shut_again["success_strict"] == shut_again["success"] == 0.0
    t_close = int(np.flatnonzero(np.diff(grip) == 1)[0]) + 1
    assert shut_again["grip_close_steps"] == (t_close, len(grip) - 2)
    # an evaluation whose criterion is the block alone (eval.success = "placed") counts it a success
    judged_on_block = PickPlace.for_evaluation({}, {"success": "placed"})
    by_block = judged_on_block.evaluate(q, np.where(np.arange(len(grip)) >= len(grip) - 2, 1.0, grip), ep)
    assert by_block["success"] == by_block["placed"] == 1.0 and by_block["success_strict"] == 0.0
    # opened but never retreated: the fingers still straddle the block
    stayed = task.evaluate(pad_rows(q[: t_open + 3], len(q)), grip, ep)
    assert stayed["success"] == 0.0 and stayed["tip_to_block"] < 0.03 and stayed["final_distance"] < 0.005
    assert stayed["grip_closed"] == 0.0 and stayed["tilt"] < 0.2 and stayed["placed"] == 0.0  # the tip too close


def test_the_success_criterion_is_an_evaluation_option():
    assert PickPlace().success == "strict" and PickPlace.for_evaluation({}, {}).success == "strict"
    assert type(get_task("pick-place-changing-goal")).for_evaluation({}, {"success": "placed"}).success == "placed"
    assert PickPlace(success="placed").config() == PickPlace().config()  # the dataset stays as it is
    with pytest.raises(ValueError, match="success must be one of strict, placed, got 'loose'"):
        PickPlace.for_evaluation({}, {"success": "loose"})


def test_bad_input_is_rejected(task):
    ep = task.episodes(1, seed=0)[0]
    with pytest.raises(ValueError, match="gripper"):
        task.evaluate(np.zeros((ep.horizon + 1, 7)), None, ep)
    with pytest.raises(ValueError, match="shape"):
        task.evaluate(np.zeros((5, 6)), np.zeros(5), ep)
    with pytest.raises(ValueError):
        PickPlace(n_demos=0)


def test_episodes_are_deterministic_per_seed(task):
    a, b, c = task.episodes(4, seed=7), task.episodes(4, seed=7), task.episodes(4, seed=8)
    assert all(np.array_equal(x.q0, y.q0) and np.array_equal(x.psi, y.psi) for x, y in zip(a, b, strict=True))
    assert not np.array_equal(a[0].q0, c[0].q0)
    assert all(e.horizon == 170 and e.psi.shape == (171, 3) for e in a)


def test_stacking_episode_layout():
    st = get_task("stack")
    ep = st.episodes(1, seed=0)[0]
    assert ep.horizon == 3 * SUB_HORIZON and ep.psi.shape == (ep.horizon + 1, 3)
    assert np.allclose(ep.psi[:, :2], ep.info["tower_xy"])
    for k, t in enumerate([0, SUB_HORIZON, 2 * SUB_HORIZON]):
        assert np.isclose(ep.psi[t, 2], level_z(k)) and np.isclose(ep.psi[t + SUB_HORIZON - 1, 2], level_z(k))
    assert np.isclose(ep.psi[-1, 2], level_z(2))
    assert ep.info["restart_steps"] == [SUB_HORIZON, 2 * SUB_HORIZON]  # one fresh pick-and-place per block


@pytest.mark.slow
def test_expert_stacking_succeeds_in_physics():
    st = get_task("stack")
    ep = st.episodes(1, seed=0)[0]
    q, grip = st.expert_rollout(ep)
    assert q.shape == (ep.horizon + 1, 7) and grip.shape == (ep.horizon + 1,)
    r = st.evaluate(q, grip, ep)
    assert r["success"] == 1.0 and r["blocks_in_tower"] == 3 and r["final_distance"] < 0.01


@pytest.mark.slow
def test_stacking_with_the_top_block_off_axis_fails():
    st = get_task("stack")
    ep = st.episodes(1, seed=0)[0]
    ep.info["goals"][2][0] += 0.03  # the expert puts the third block 3 cm off the tower axis ...
    q, grip = st.expert_rollout(ep)
    ep.info["goals"][2][0] -= 0.03  # ... of the episode it is judged by
    r = st.evaluate(q, grip, ep)
    assert r["success"] == 0.0 and r["blocks_in_tower"] == 2


@pytest.mark.slow
def test_changing_goal_expert_adapts_and_a_blind_one_fails():
    cg = get_task("pick-place-changing-goal")
    ep = cg.episodes(1, seed=2)[0]
    k = ep.info["switch_step"]
    assert ep.horizon == 255 and np.allclose(ep.psi[:k], ep.info["goal"])
    assert np.allclose(ep.psi[k:], ep.info["new_goal"])
    q, grip = cg.expert_rollout(ep)
    assert grip[k - 1] == 1.0  # the switch comes right after the grasp closed
    assert cg.evaluate(q, grip, ep)["success"] == 1.0
    q_old, g_old = cg.expert_trajectory(ep.q0, ep.info["goal"])
    blind = cg.evaluate(pad_rows(q_old, ep.horizon + 1), pad_rows(g_old, ep.horizon + 1), ep)
    assert blind["success"] == 0.0 and blind["final_distance"] >= 0.09
    # the direct expert path from the switch state reaches the new goal's place pose
    q_direct, g_direct = cg.expert_after_switch(ep, q[k])
    assert np.allclose(q_direct[0], q[k]) and g_direct[0] == 1.0 and g_direct[-1] == 0.0
    tip_place = tip_position_np(q_direct[np.flatnonzero(np.diff(g_direct) == -1)[0]])
    assert np.allclose(tip_place, np.asarray(ep.info["new_goal"]) + [0, 0, 0.03], atol=1e-3)


def test_retreat_starts_are_poised_above_a_goal_in_the_grasp_frame():
    from envs.tasks.pickplace_expert import GRASP_HEIGHT, GRASP_ROT, RETREAT, tip_poses

    task = get_task("pick-place", retreat_starts=1.0)
    tip, rot = tip_poses(task.sample_starts(np.random.default_rng(3), 12))
    levels = (tip[:, 2] - GRASP_HEIGHT - RETREAT - level_z(0)) / (level_z(1) - level_z(0))
    assert np.allclose(levels, np.round(levels), atol=1e-3) and set(np.round(levels)) <= {0, 1, 2}
    (x0, x1), (y0, y1) = GOAL_REGION
    eps = 1e-3
    assert np.all((tip[:, 0] >= x0 - eps) & (tip[:, 0] <= x1 + eps) & (tip[:, 1] >= y0 - eps) & (tip[:, 1] <= y1 + eps))
    assert np.allclose(rot, GRASP_ROT, atol=1e-2)
    assert get_task("pick-place", retreat_starts=0.5).config() != get_task("pick-place").config()
    with pytest.raises(ValueError, match="retreat_starts must be a fraction"):
        get_task("pick-place", retreat_starts=1.5)


def test_goal_switch_demonstrations_replan_to_the_new_goal_after_the_grasp():
    """The goal_switches lever: a switched demo asks for its first goal (on the table) up to a step between the
    grasp's close and SWITCH_LATE steps into the lift, then for a new table goal at least MIN_GOAL_SWITCH away;
    the expert lifts, carries and places the block there (each demo was replayed in physics and kept only if
    placed there) and retreats."""
    from envs.tasks.pickplace import MAX_STEPS, MIN_GOAL_SWITCH, MIN_STEPS, SWITCH_LATE, grasp_step
    from envs.tasks.pickplace_expert import GRASP_HEIGHT, RETREAT, SEGMENTS

    task = get_task("pick-place", n_demos=3, goal_switches=1.0)
    demos = task.demos(5)
    assert demos.meta["goal_switches"] == 3 and demos.meta["expert_success"] == 1.0
    after = sum(SEGMENTS[s] for s in ("lift", "carry", "place", "release", "retreat"))
    for psi, q, grip, length in zip(demos.psi, demos.q, demos.grip, demos.lengths, strict=True):
        k = int(np.flatnonzero((psi != psi[0]).any(axis=1))[0])
        first, new = psi[0], psi[k]
        assert (psi[:k] == first).all() and (psi[k:] == new).all()
        assert first[2] == new[2] == level_z(0) and np.hypot(*(new - first)[:2]) >= MIN_GOAL_SWITCH
        assert grasp_step(MIN_STEPS) <= k <= grasp_step(MAX_STEPS) + SWITCH_LATE and length == k + after
        assert grip[k] == 1.0 and grip[length] == 0.0  # in hand at the switch, released at the end
        end_tip = tip_position_np(q[length][None])[0]
        assert np.allclose(end_tip, new + [0, 0, GRASP_HEIGHT + RETREAT], atol=5e-3)  # above the new goal
    assert task.config() != get_task("pick-place").config()
    with pytest.raises(ValueError, match="goal_switches must be a fraction"):
        get_task("pick-place", goal_switches=-0.1)


def test_start_joint_range_widens_the_starts_of_training_and_evaluation():
    """The start-range lever: starts spread with the range (tip still in START_BOX), the dataset's cache key
    changes only off the default, and the model's evaluation tasks (stacking, changing goal) inherit it."""
    from envs.tasks.pickplace import NEUTRAL_Q, START_BOX, START_JOINT_RANGE, tip_poses

    spreads = {}
    for r in (START_JOINT_RANGE, 0.3):
        q = get_task("pick-place", start_joint_range=r).sample_starts(np.random.default_rng(5), 64)
        assert np.all(np.abs(q - NEUTRAL_Q) <= r + 1e-9)
        tip, _ = tip_poses(q)
        assert all(np.all((tip[:, i] >= lo) & (tip[:, i] <= hi)) for i, (lo, hi) in enumerate(START_BOX))
        spreads[r] = np.abs(q - NEUTRAL_Q).max()
    assert spreads[0.3] > 2 * spreads[START_JOINT_RANGE] * 0.9
    assert get_task("pick-place", start_joint_range=START_JOINT_RANGE).config() == get_task("pick-place").config()
    assert get_task("pick-place", start_joint_range=0.3).config()["start_joint_range"] == 0.3
    for name in ("pick-place", "stack", "pick-place-changing-goal"):
        task = type(get_task(name)).for_evaluation({"start_joint_range": 0.2, "n_demos": 15, "retreat_starts": 0.3})
        assert task.start_joint_range == 0.2 and task.retreat_starts == 0.0
    with pytest.raises(ValueError, match="start_joint_range must be in"):
        get_task("pick-place", start_joint_range=-0.1)
