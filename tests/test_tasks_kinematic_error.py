"""Task.kinematic_error: the physics-free validation error of each training task."""

import numpy as np

from envs.tasks import get_task
from envs.tasks.circle import circle_path
from envs.tasks.pickplace_expert import GRASP_HEIGHT


def test_reacher_error_is_the_end_distance_to_the_last_goal():
    task = get_task("reacher-changing-goal")
    ep = task.episodes(1, seed=3)[0]
    tip = np.linspace([0.5, 0.0, 0.1], ep.psi[-1], ep.horizon + 1)
    assert task.kinematic_error(tip, ep) < 1e-12
    assert np.isclose(task.kinematic_error(tip + [0.0, 0.0, 0.07], ep), 0.07)


def test_circle_error_is_zero_on_the_circle_and_penalises_standing_still():
    task = get_task("circle")
    ep = task.episodes(1, seed=0)[0]
    r = ep.info["radius"]
    assert task.kinematic_error(circle_path(r), ep) < 1e-3
    still = np.repeat(circle_path(r)[:1], 50, axis=0)
    assert np.isclose(task.kinematic_error(still, ep), 2 * np.pi * r, rtol=1e-3)


def test_pick_place_error_is_the_closest_approach_to_the_release_point():
    task = get_task("pick-place")
    ep = task.episodes(1, seed=0)[0]
    place = np.asarray(ep.psi[-1]) + [0.0, 0.0, GRASP_HEIGHT]
    tip = np.stack([place + [0.2, 0.0, 0.1], place + [0.0, 0.0, 0.02], place + [0.1, 0.0, 0.2]])
    assert np.isclose(task.kinematic_error(tip, ep), 0.02)
