"""reacher-posture-multimodal: bimodal demonstrations (two final arm postures), labels, the
expert's success in physics, and detection of a posture between the modes."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from multimodal_fixtures import task_fixtures

from envs.kinematics import default_kinematics, tip_position_np
from envs.tasks import TASKS
from envs.tasks.reacher_posture_multimodal import MODES, POSTURE_REFS, classify, nullspace_ik, posture_coordinate

task, demos, episodes = task_fixtures("reacher-posture-multimodal", n_demos=12)


def test_registered_and_named_multimodal():
    assert "multimodal" in TASKS["reacher-posture-multimodal"].description


@pytest.mark.slow
def test_demos_are_bimodal_and_labelled(task, demos):
    modes = np.array(demos.meta["modes"])
    assert demos.meta["mode_names"] == list(MODES)
    assert sorted(np.bincount(modes, minlength=2)) == [6, 6]
    assert np.array_equal(task.demo_modes(demos), modes)
    # the two modes really differ in posture: the upper-arm roll at the end has the mode's sign
    last = demos.q[np.arange(len(demos)), demos.lengths]
    assert np.all(np.sign(last[:, 2]) == np.where(modes == 0, 1, -1))


def test_tip_paths_do_not_reveal_the_mode(task, demos):
    """Both modes move the tip along the same straight line: phi and psi are mode-free."""
    for i, n in enumerate(demos.lengths):
        tip = tip_position_np(demos.q[i, : n + 1])
        a, b = tip[0], demos.psi[i, 0]
        u = (b - a) / np.linalg.norm(b - a)
        off_line = np.linalg.norm((tip - a) - ((tip - a) @ u)[:, None] * u, axis=-1)
        assert off_line.max() < 1e-3


def test_nullspace_ik_reaches_the_goal_in_the_reference_posture():
    goals = np.array([[0.6, 0.1, 0.05], [0.5, 0.3, 0.1]])
    refs = np.stack(POSTURE_REFS)
    q, ok = nullspace_ik(goals[[0, 0, 1, 1]], refs[[0, 1, 0, 1]], refs[[0, 1, 0, 1]])
    assert ok.all()
    assert np.allclose(tip_position_np(q), goals[[0, 0, 1, 1]], atol=2e-4)
    axis = default_kinematics(torch.float64).forward(torch.as_tensor(q)).tip_rot[..., :, 2].numpy()
    assert np.allclose(axis, [0, 0, -1], atol=2e-3)
    assert np.all(np.sign(q[:, 2]) == [1, -1, 1, -1])
    assert np.linalg.norm(q[0] - q[1]) > 0.8  # two distinct postures for one goal


def test_posture_coordinate_and_classify():
    P = np.stack([np.zeros(7), np.r_[np.ones(6), 5.0]])  # j6 is ignored
    assert posture_coordinate(P[0], P) == 0 and posture_coordinate(P[1], P) == pytest.approx(1)
    assert posture_coordinate(P.mean(0), P) == pytest.approx(0.5)
    assert [classify(c) for c in (-0.1, 0.2, 0.5, 0.8, 1.2)] == [0, 0, -1, 1, 1]


@pytest.mark.slow
def test_expert_succeeds_in_physics_in_both_postures(task, episodes):
    modes = np.arange(len(episodes)) % 2
    q0 = np.stack([ep.q0 for ep in episodes])
    goals = np.array([ep.info["goal"] for ep in episodes])
    q, steps, ok = task.expert(q0, goals, modes)
    results = [task.evaluate(q[i, : ep.horizon + 1], None, ep) for i, ep in enumerate(episodes)]
    success = np.array([r["success"] for r in results])
    assert ok.mean() >= 0.9 and success.mean() >= 0.9
    taken = np.array([0 if r[f"mode_{MODES[0]}"] else 1 if r[f"mode_{MODES[1]}"] else -1 for r in results])
    assert np.array_equal(taken[success == 1], modes[success == 1])


def test_averaged_posture_is_between_and_fails(task, episodes):
    eps = episodes[:4]
    q0 = np.stack([ep.q0 for ep in eps])
    goals = np.array([ep.info["goal"] for ep in eps])
    a, steps, _ = task.expert(q0, goals, np.zeros(4, int))
    b, _, _ = task.expert(q0, goals, np.ones(4, int), steps)
    for i, ep in enumerate(eps):
        r = task.evaluate(((a + b) / 2)[i, : ep.horizon + 1], None, ep)
        assert r["between"] == 1.0 and r["success"] == 0.0
        assert r["posture_coordinate"] == pytest.approx(0.5, abs=0.05)
