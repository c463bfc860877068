"""Circle drawing: dataset, metrics on hand-made paths, state layout, physics evaluation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.datasets import load_demos
from envs.kinematics import default_kinematics, tip_position_np
from envs.sim import Scene
from envs.tasks import get_task
from envs.tasks.circle import CENTRE, circle_metrics, circle_path
from envs.tasks.expert import velocity_ratio


@pytest.fixture(scope="module")
def task():
    return get_task("circle")


@pytest.fixture(scope="module")
def demos(task, tmp_path_factory):
    return load_demos(task, seed=0, cache_dir=tmp_path_factory.mktemp("circle_cache"))


@pytest.mark.slow
def test_ten_demos_with_evenly_spaced_radii(demos, task):
    assert len(demos) == 10
    radii = demos.psi[:, 0, 0]
    assert np.allclose(radii, np.linspace(0.05, 0.20, 10), atol=1e-6)
    assert np.all(demos.psi == demos.psi[:, :1])  # r is constant along a demo
    assert np.all(demos.lengths == 100) and demos.q.shape == (10, 101, 7)
    assert demos.meta["expert_success"] == 1.0 and demos.meta["rejections"] == {"ik": 0, "physics": 0}
    assert velocity_ratio(demos.q, task.step_seconds).max() <= 1.0


def test_demos_draw_their_circle_in_kinematics(demos):
    for i, r in enumerate(demos.psi[:, 0, 0]):
        m = circle_metrics(tip_position_np(demos.q[i]), r)
        assert m["radial_rmse"] < 1e-3 and m["turns"] > 0.99 and m["closure"] < 1e-3


def test_state_layout_and_phi_is_the_tip_position(demos, task):
    s = task.demo_states(demos, default_kinematics(torch.float64))
    L = task.layout
    assert L.dim == 11 and s.shape == (10, 101, 11)
    assert np.allclose(demos.q[:, :1] + np.cumsum(s[:, :, L.dq], axis=1), demos.q, atol=1e-9)
    assert np.allclose(s[:, :, L.psi], demos.psi)
    with Scene(table=False) as scene:
        for i, t in [(0, 0), (4, 37), (9, 100)]:
            scene.robot.reset(demos.q[i, t])
            assert np.allclose(s[i, t, L.phi], scene.robot.link_pose(scene.robot.tip)[0], atol=1e-5)


def test_metrics_on_hand_made_paths():
    r = 0.1
    exact = circle_path(r)
    m = circle_metrics(exact, r)
    assert m["radial_rmse"] < 1e-12 and m["closure"] < 1e-12 and m["turns"] == pytest.approx(1.0)
    assert m["success"] == 1.0
    wide = circle_path(1.05 * r)  # 5% too wide everywhere: passes
    m = circle_metrics(wide, r)
    assert m["radial_rmse"] == pytest.approx(0.005) and m["max_radial_error_pct"] == pytest.approx(5.0)
    assert m["success"] == 1.0
    assert circle_metrics(circle_path(1.12 * r), r)["success"] == 0.0  # 12% too wide: fails
    lifted = exact + [0, 0, 0.003]  # the height error counts as radial error
    assert circle_metrics(lifted, r)["radial_rmse"] == pytest.approx(0.003)
    half = exact[:51]
    m = circle_metrics(half, r)
    assert m["turns"] == pytest.approx(0.5, abs=1e-6) and m["closure"] == pytest.approx(2 * r)
    assert m["success"] == 0.0
    still = np.repeat(exact[:1], 101, axis=0)  # no radial error, but nothing drawn
    m = circle_metrics(still, r)
    assert m["max_radial_error_pct"] < 1e-9 and m["success"] == 0.0


def test_episodes_at_requested_radii(task):
    eps = task.episodes(5, seed=0)
    assert [e.info["radius"] for e in eps] == [0.05, 0.10, 0.15, 0.075, 0.125]
    eps = task.episodes(2, seed=0, radii=(0.12,))
    for e in eps:
        assert e.info["radius"] == 0.12 and e.psi.shape == (101, 1) and np.all(e.psi == 0.12)
        start = np.add(CENTRE, [0.12, 0, 0])
        assert np.linalg.norm(tip_position_np(e.q0) - start) < 1e-3


def test_physics_evaluation_passes_the_expert_and_fails_wrong_circles(task, demos):
    ep = task.episodes(1, seed=0, radii=(0.10,))[0]
    q, ok = task.expert([0.10])
    assert ok[0]
    m = task.evaluate(q[0], None, ep)
    assert m["success"] == 1.0 and m["max_radial_error_pct"] < 1.0 and m["closure"] < 0.005
    # a 7.5 cm episode judged on the 10 cm expert: 33% radial error
    ep75 = task.episodes(1, seed=0, radii=(0.075,))[0]
    m = task.evaluate(q[0], None, ep75)
    assert m["success"] == 0.0 and m["max_radial_error_pct"] > 30
    standing = np.repeat(ep.q0[None], 101, axis=0)
    assert task.evaluate(standing, None, ep)["success"] == 0.0


def test_constant_speed_profile_is_its_own_dataset_and_unknown_profiles_fail():
    const = circle_path(0.1, profile="constant")
    steps = np.linalg.norm(np.diff(const, axis=0), axis=1)
    assert np.allclose(steps, steps[0]) and np.allclose(const[0], const[-1])
    assert np.allclose(circle_path(0.1)[0], const[0])  # same start: same episodes
    assert get_task("circle", profile="constant").config() != get_task("circle").config()
    with pytest.raises(ValueError, match="profile must be one of min-jerk, constant"):
        get_task("circle", profile="sine")
