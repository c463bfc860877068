"""Reacher and reacher-changing-goal: dataset shape, state layout, expert, success predicate."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.datasets import load_demos
from envs.kinematics import default_kinematics, tip_position_np
from envs.robot import LIMITS, NEUTRAL_Q
from envs.sim import Scene
from envs.tasks import Episode, get_task, task_class
from envs.tasks.expert import velocity_ratio
from envs.tasks.reacher import GOAL_BOX, MIN_DISTANCE, START_BOX, START_JOINT_RANGE, SUCCESS_RADIUS, SWITCH_HOLD


@pytest.fixture(scope="module")
def task():
    return get_task("reacher")


@pytest.fixture(scope="module")
def demos(task, tmp_path_factory):
    return load_demos(task, seed=0, cache_dir=tmp_path_factory.mktemp("reacher_cache"))


def _in(box, x):
    return all(lo <= v <= hi for (lo, hi), v in zip(box, x, strict=True))


@pytest.mark.slow
def test_counts_lengths_and_padding(demos, task):
    assert len(demos) == 45
    assert demos.lengths.min() >= 50 and demos.lengths.max() <= 70
    assert demos.q.shape == (45, demos.lengths.max() + 1, 7)
    assert demos.psi.shape == (45, demos.lengths.max() + 1, 3)
    for i, n in enumerate(demos.lengths):
        assert np.array_equal(demos.q[i, n:], np.repeat(demos.q[i, n][None], demos.q.shape[1] - n, axis=0))
        assert np.all(demos.psi[i] == demos.psi[i, 0])  # the goal is constant along a demo
        assert _in(GOAL_BOX, demos.psi[i, 0])
    assert demos.meta["expert_success"] == 1.0
    assert demos.meta["count"] == 45


def test_starts_are_tool_down_near_neutral_and_in_the_start_box(demos):
    q0 = demos.q[:, 0]
    kin = default_kinematics(torch.float64)
    axis = kin.forward(torch.as_tensor(q0)).tip_rot[..., :, 2].numpy()
    assert np.allclose(axis, [0, 0, -1], atol=2e-3)
    assert all(_in(START_BOX, t) for t in tip_position_np(q0))
    # the IK projection keeps q_raw's tip, so the start tip lies where a perturbation of at most
    # START_JOINT_RANGE per joint can put it: within r * sum_j |d tip / d q_j| of the neutral tip
    # (first order; +5% for the curvature at 0.1 rad)
    tip_n = tip_position_np(NEUTRAL_Q[None])[0]
    jac = np.stack([(tip_position_np((NEUTRAL_Q + 1e-6 * np.eye(7)[j])[None])[0] - tip_n) / 1e-6 for j in range(7)])
    reach = START_JOINT_RANGE * np.linalg.norm(jac, axis=1).sum()
    assert np.linalg.norm(tip_position_np(q0) - tip_n, axis=1).max() < 1.05 * reach
    # turning the tool down moves the joints a few tenths of a radian (at most 0.32 over 600 sampled starts)
    assert np.abs(q0 - NEUTRAL_Q).max() < START_JOINT_RANGE + 0.4
    assert LIMITS.contains(demos.q).all()


def test_demos_respect_joint_velocity_limits(demos, task):
    assert velocity_ratio(demos.q, task.step_seconds).max() <= 1.0


def test_state_layout_integrates_to_joint_path_and_phi_matches_pybullet_fk(demos, task):
    kin = default_kinematics(torch.float64)
    s = task.demo_states(demos, kin)
    L = task.layout
    assert s.shape == (45, demos.q.shape[1], L.dim) and L.dim == 13 and len(L.names) == 13
    assert np.all(s[:, 0, L.dq] == 0)
    q_rebuilt = demos.q[:, :1] + np.cumsum(s[:, :, L.dq], axis=1)
    assert np.allclose(q_rebuilt, demos.q, atol=1e-9)
    assert np.allclose(s[:, :, L.psi], demos.psi)
    with Scene(table=False) as scene:  # pybullet's own FK is the independent check of phi
        for i, t in [(0, 0), (3, 20), (10, int(demos.lengths[10]))]:
            scene.robot.reset(demos.q[i, t])
            tip = scene.robot.link_pose(scene.robot.tip)[0]
            assert np.allclose(s[i, t, L.phi], tip - demos.psi[i, t], atol=1e-5)


def test_demo_ends_at_goal_in_kinematics(demos):
    ends = tip_position_np(demos.q[np.arange(45), demos.lengths])
    assert np.linalg.norm(ends - demos.psi[:, 0], axis=-1).max() < 1e-3


def test_success_predicate_on_hand_made_cases(task):
    ep = task.episodes(1, seed=5)[0]
    goal = ep.psi[-1]
    q = task.expert_trajectory(ep.q0, goal)
    res = task.evaluate(q, None, ep)
    assert res["success"] == 1.0 and res["final_distance"] < 0.01
    # the same motion judged against goals moved 4 cm (inside) and 6 cm (outside) away
    end = tip_position_np(q[-1])
    for offset, expected in [(0.04, 1.0), (0.06, 0.0)]:
        moved = Episode(ep.q0, np.repeat((end + [0, 0, offset])[None], len(ep.psi), 0), ep.horizon, ep.info)
        r = task.evaluate(q, None, moved)
        assert r["success"] == expected
        assert abs(r["final_distance"] - offset) < 0.005
    standing = np.repeat(ep.q0[None], ep.horizon + 1, axis=0)  # never moves: fails
    r = task.evaluate(standing, None, ep)
    assert r["success"] == 0.0
    assert r["final_distance"] == pytest.approx(np.linalg.norm(tip_position_np(ep.q0) - goal), abs=0.01)
    assert SUCCESS_RADIUS == 0.05


def test_evaluate_rejects_bad_trajectories(task):
    ep = task.episodes(1, seed=0)[0]
    with pytest.raises(ValueError, match="shape"):
        task.evaluate(np.zeros((10, 6)), None, ep)
    bad = np.repeat(ep.q0[None], 5, axis=0)
    bad[2, 1] = np.nan
    with pytest.raises(ValueError, match="NaN"):
        task.evaluate(bad, None, ep)


@pytest.mark.slow
def test_demos_are_deterministic_per_seed():
    small = get_task("reacher", n_demos=2)
    a, b, c = small.demos(7), small.demos(7), small.demos(8)
    assert np.array_equal(a.q, b.q) and np.array_equal(a.psi, b.psi)
    assert not np.array_equal(a.psi[:, 0], c.psi[:, 0])


def test_episodes_deterministic_and_within_documented_ranges(task):
    e1, e2 = task.episodes(4, seed=3), task.episodes(4, seed=3)
    for a, b in zip(e1, e2, strict=True):
        assert np.array_equal(a.q0, b.q0) and np.array_equal(a.psi, b.psi)
        assert a.horizon == 70 and a.psi.shape == (71, 3) and _in(GOAL_BOX, a.info["goal"])


def test_changing_goal_episodes_switch_halfway():
    task = get_task("reacher-changing-goal")
    assert task.model_task == "reacher"
    eps = task.episodes(3, seed=1)
    for ep in eps:
        assert ep.horizon == 105 and ep.info["switch_step"] == 52 and ep.psi.shape == (106, 3)
        assert np.allclose(ep.psi[:52], ep.info["goal"]) and np.allclose(ep.psi[52:], ep.info["new_goal"])
        assert np.linalg.norm(np.subtract(ep.info["goal"], ep.info["new_goal"])) >= 0.1


def test_changing_goal_expert_adapts_and_holding_the_first_goal_fails():
    task = get_task("reacher-changing-goal")
    ep = task.episodes(1, seed=2)[0]
    q = task.expert_rollout(ep)
    assert q.shape == (106, 7) and velocity_ratio(q, task.step_seconds) <= 1.0
    assert task.evaluate(q, None, ep)["success"] == 1.0
    # the expert's direct path from the state at the switch starts there and ends at the new goal
    k = ep.info["switch_step"]
    direct = task.expert_after_switch(ep, q[k])
    assert np.allclose(direct[0], q[k])
    assert len(direct) - 1 <= ep.horizon - k
    assert np.linalg.norm(tip_position_np(direct[-1]) - ep.info["new_goal"]) < 1e-3
    # ignoring the switch: reach the first goal and stay there
    first = task.expert_trajectory(ep.q0, np.asarray(ep.info["goal"]))
    hold = np.concatenate([first, np.repeat(first[-1:], 106 - len(first), axis=0)])
    assert task.evaluate(hold, None, ep)["success"] == 0.0


@pytest.mark.slow
def test_goal_switch_demonstrations_replan_to_the_new_goal():
    """The goal_switches lever: each switched demo holds its first goal up to a step in the documented window,
    then the new goal (MIN_DISTANCE away) to its end, which the expert reaches within the joint speed limits."""
    task = get_task("reacher", n_demos=4, goal_switches=1.0)
    demos = task.demos(3)
    assert demos.meta["goal_switches"] == 4
    for i, n in enumerate(demos.lengths):
        psi = demos.psi[i, : n + 1]
        k = int(np.flatnonzero((psi != psi[0]).any(axis=1))[0])
        assert task.min_steps // 2 <= k <= task.max_steps + SWITCH_HOLD
        assert np.all(psi[k:] == psi[-1]) and np.linalg.norm(psi[-1] - psi[0]) >= MIN_DISTANCE
        assert task.min_steps <= n - k <= task.max_steps  # the second reach is a whole expert reach
        assert velocity_ratio(demos.q[i, : n + 1], task.step_seconds) <= 1.0
        assert np.linalg.norm(tip_position_np(demos.q[i, n]) - psi[-1]) < SUCCESS_RADIUS
    half = get_task("reacher", n_demos=8, goal_switches=0.5).demos(3)
    assert 0 < half.meta["goal_switches"] < 8


def test_goal_switches_is_a_cache_key_only_when_used_and_checked():
    assert "goal_switches" not in get_task("reacher").config()
    assert get_task("reacher", goal_switches=0.0).config() == get_task("reacher").config()
    assert get_task("reacher", goal_switches=0.5).config()["goal_switches"] == 0.5
    with pytest.raises(ValueError, match="goal_switches must be a fraction"):
        get_task("reacher", goal_switches=1.5)
    # a training-data lever: the changing-goal evaluation of such a model keeps the paper's episodes
    assert task_class("reacher-changing-goal").for_evaluation({"goal_switches": 0.5}, {}).goal_switches == 0.0
