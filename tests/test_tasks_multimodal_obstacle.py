"""reacher-obstacle-multimodal: bimodal demonstrations (left/right of the pillar), labels,
the expert's success in physics with the pillar, and detection of a path between the modes."""

from __future__ import annotations

import numpy as np
import pytest
from multimodal_fixtures import task_fixtures

from envs.kinematics import tip_position_np
from envs.tasks import TASKS
from envs.tasks.reacher import Reacher
from envs.tasks.reacher_obstacle_multimodal import MODES, OBSTACLE_XY, classify

task, demos, episodes = task_fixtures("reacher-obstacle-multimodal", n_demos=16)


def test_registered_and_named_multimodal():
    assert "reacher-obstacle-multimodal" in TASKS
    assert "multimodal" in TASKS["reacher-obstacle-multimodal"].description


@pytest.mark.slow
def test_demos_are_bimodal_and_labelled(task, demos):
    modes = np.array(demos.meta["modes"])
    assert demos.meta["mode_names"] == list(MODES)
    assert sorted(np.bincount(modes, minlength=2)) == [8, 8]  # a balanced coin flip over the demos
    # the labels are what the demonstrated paths do: recomputed from the kinematic tip paths
    assert np.array_equal(task.demo_modes(demos), modes)


def test_state_does_not_reveal_the_mode(demos):
    """Start tip and goal (what s_0 carries) have the same spread in both modes: the label is
    the expert's coin flip, and the same (start, goal) region is demonstrated both ways."""
    modes = np.array(demos.meta["modes"])
    x = np.concatenate([tip_position_np(demos.q[:, 0]), demos.psi[:, 0]], axis=1)
    gap = np.abs(x[modes == 0].mean(0) - x[modes == 1].mean(0))
    stderr = x.std(0) * np.sqrt(1 / (modes == 0).sum() + 1 / (modes == 1).sum())
    assert np.all(gap < 3 * stderr)  # no coordinate separates the modes beyond chance
    assert np.allclose(demos.psi, demos.psi[:, :1])  # psi is the goal only, constant along a demo


@pytest.mark.slow
def test_expert_succeeds_in_physics_both_ways(task, episodes):
    modes = np.arange(len(episodes)) % 2
    q0 = np.stack([ep.q0 for ep in episodes])
    goals = np.array([ep.info["goal"] for ep in episodes])
    q, steps, ok = task.expert(q0, goals, modes)
    results = [task.evaluate(np.concatenate([q[i], np.repeat(q[i, -1:], ep.horizon + 1 - len(q[i]), 0)]), None, ep)
               for i, ep in enumerate(episodes)]
    success = np.array([r["success"] for r in results])
    assert ok.mean() >= 0.9 and success.mean() >= 0.9
    taken = np.array([0 if r["mode_left"] else 1 if r["mode_right"] else -1 for r in results])
    assert np.array_equal(taken[success == 1], modes[success == 1])
    assert all(r["collided"] == 0.0 for r, s in zip(results, success, strict=True) if s)


@pytest.mark.slow
def test_direct_and_averaged_paths_are_between_and_fail(task, episodes):
    eps = episodes[:4]
    q0 = np.stack([ep.q0 for ep in eps])
    goals = np.array([ep.info["goal"] for ep in eps])
    direct, _, _ = Reacher.expert(task, q0, goals)  # the straight line the pillar blocks
    left, steps, _ = task.expert(q0, goals, np.zeros(4, int))
    right, _, _ = task.expert(q0, goals, np.ones(4, int), steps)
    for paths in (direct, (left + right) / 2):  # a deterministic model's average of the modes
        for i, ep in enumerate(eps):
            r = task.evaluate(paths[i, : ep.horizon + 1], None, ep)
            assert r["between"] == 1.0 and r["collided"] == 1.0 and r["success"] == 0.0
            assert r["mode_left"] == r["mode_right"] == 0.0


def test_classify_synthetic_paths():
    o = np.array([*OBSTACLE_XY, 0.05])
    start, goal = o + [0, -0.2, 0], o + [0, 0.2, 0]
    s = np.linspace(0, 1, 41)[:, None]
    line = start + s * (goal - start)
    bump = np.sin(np.pi * s) * np.array([0.15, 0, 0])  # travelling +y, left is -x
    assert classify(line - bump, start, goal)[0] == 0
    mode, offset = classify(line + bump, start, goal)
    assert mode == 1 and offset == pytest.approx(-0.15, abs=1e-3)
    assert classify(line[:10], start, goal)[0] == -1  # stopped before the pillar


def test_the_detour_expert_solves_its_paths_as_the_reacher_solves_its_line(task, episodes, monkeypatch):
    """The obstacle expert shares Reacher.solve_tip_paths: with no bump it is the reacher's expert."""
    import envs.tasks.reacher_obstacle_multimodal as obstacle

    eps = episodes[:3]
    q0 = np.stack([ep.q0 for ep in eps])
    goals = np.array([ep.info["goal"] for ep in eps])
    monkeypatch.setattr(obstacle, "DETOUR", 0.0)
    for got, want in zip(task.expert(q0, goals, np.array([0, 1, 0])), Reacher.expert(task, q0, goals), strict=True):
        np.testing.assert_allclose(got, want, atol=1e-9)


def test_rollout_arrays_carry_every_per_episode_result(task):
    """The rollouts artifact keeps each episode's mode label (a figure colours paths by it)."""
    from experiments.evaluation import TaskEvaluation, result_arrays, rollout_arrays

    eps = task.episodes(3, seed=11)
    q0 = np.stack([ep.q0 for ep in eps])
    goals = np.array([ep.info["goal"] for ep in eps])
    q, steps, _ = task.expert(q0, goals, np.array([0, 1, 0]), np.full(3, eps[0].horizon))
    results = [task.evaluate(q[i], None, ep) for i, ep in enumerate(eps)]
    arrays = rollout_arrays(TaskEvaluation(task.name, eps, q, results))
    for key in ("success", "final_distance", "mode_left", "mode_right", "between", "collided", "lateral_offset"):
        assert arrays[key].shape == (3,) and arrays[key].dtype == float
        assert arrays[key].tolist() == [r[key] for r in results]
    assert arrays["mode_left"].tolist() == [1.0, 0.0, 1.0] and arrays["mode_right"].tolist() == [0.0, 1.0, 0.0]
    mixed = result_arrays([{"success": True, "note": "text", "x": 2}, {"final_distance": 0.1}])
    assert sorted(mixed) == ["final_distance", "success", "x"]  # numbers only, NaN where missing
    np.testing.assert_array_equal(mixed["success"], [1.0, np.nan])
    np.testing.assert_array_equal(mixed["x"], [2.0, np.nan])
