from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from envs.robot import NEUTRAL_Q
from stm.control.plans import FOUR_GOALS, jittery_skeletons, straight_line_plans
from stm.control.smoothing import smooth_exact, smooth_gd, smoothing_objective, smoothness_metrics


@pytest.fixture(scope="module")
def skeletons():
    return jittery_skeletons(straight_line_plans(FOUR_GOALS[:2], steps=20), seed=1)


def test_gradient_descent_converges_to_exact_solve(skeletons):
    exact = smooth_exact(skeletons, gamma=4.0)
    gd = smooth_gd(skeletons, gamma=4.0, iters=400)
    np.testing.assert_allclose(gd, exact, atol=1e-7)


def test_exact_solve_is_a_stationary_point_and_keeps_start(skeletons):
    sk = torch.as_tensor(skeletons)
    q = smooth_exact(sk, gamma=3.0).requires_grad_(True)
    smoothing_objective(q, sk, 3.0).sum().backward()
    assert q.grad[:, 1:].abs().max() < 1e-9  # zero gradient w.r.t. every free point
    assert torch.equal(q.detach()[:, 0], sk[:, 0])
    np.testing.assert_array_equal(smooth_gd(skeletons, 3.0, iters=5)[:, 0], skeletons[:, 0])


def test_gamma_zero_returns_the_skeleton(skeletons):
    np.testing.assert_allclose(smooth_exact(skeletons, 0.0), skeletons, atol=1e-12)


def test_smoothing_reduces_jerk_and_goal_term_reduces_goal_error(skeletons):
    goals = FOUR_GOALS[:2]
    plain = smooth_gd(skeletons, gamma=5.0, iters=200)
    with_goal = smooth_gd(skeletons, gamma=5.0, goal=goals, goal_weight=50.0, iters=200)
    before = smoothness_metrics(skeletons, skeletons, goals)
    after = smoothness_metrics(plain, skeletons, goals)
    after_goal = smoothness_metrics(with_goal, skeletons, goals)
    assert after["mean_sq_jerk"] < 0.05 * before["mean_sq_jerk"]
    assert after["peak_joint_speed"] < before["peak_joint_speed"]
    assert after_goal["goal_error_m"] < 0.5 * after["goal_error_m"]
    assert after_goal["goal_error_m"] < 0.02
    assert before["deviation_rad"] == 0.0 < after["deviation_rad"]


def test_metrics_on_known_signals():
    dt = 0.1
    t = np.arange(11) * dt
    cubic = np.repeat((2.0 * t**3 / 6.0)[None, :, None], 7, axis=2)  # constant jerk 2 rad/s^3
    m = smoothness_metrics(cubic, step_seconds=dt)
    assert m["mean_sq_jerk"] == pytest.approx(4.0, rel=1e-9)
    ramp = np.zeros((1, 11, 7))
    ramp[0, :, 3] = 0.5 * t  # 0.5 rad/s on one joint
    m = smoothness_metrics(ramp, skeleton=np.zeros_like(ramp), step_seconds=dt)
    assert m["mean_sq_jerk"] == pytest.approx(0.0, abs=1e-12)
    assert m["peak_joint_speed"] == pytest.approx(0.5)
    assert m["deviation_rad"] == pytest.approx(np.mean(0.5 * t))


def test_bad_shapes_raise_clear_errors():
    with pytest.raises(ValueError, match="shape"):
        smooth_exact(np.zeros((5, 7)))
    with pytest.raises(ValueError, match="NaN"):
        smooth_gd(np.full((1, 4, 7), np.nan))
    with pytest.raises(ValueError, match="gamma"):
        smooth_gd(np.zeros((1, 4, 7)), gamma=-1.0)


@pytest.mark.slow
def test_smoothing_study_writes_figure_and_metrics(tmp_path):
    from stm.control.smoothing import smoothing_study

    res = smoothing_study(steps=20, out_dir=tmp_path)
    assert res["gd_vs_exact_max_abs_rad"] < 1e-6
    assert res["gd_goal/goal_error_m"] < res["skeleton/goal_error_m"]
    assert res["exact/mean_sq_jerk"] < res["skeleton/mean_sq_jerk"]
    assert res["figures"] == [str(tmp_path / "smoothing_tip_paths.png"), str(tmp_path / "smoothing_tip_paths.pdf")]
    assert Path(res["figures"][1]).read_bytes().startswith(b"%PDF")
    with Image.open(res["figures"][0]) as im:
        pixels = np.asarray(im.convert("RGB")).reshape(-1, 3).astype(int)
    # every variant's line and the goals are drawn: pixels of each one's colour
    for name, rgb in {"exact C0": (31, 119, 180), "gd C1": (255, 127, 14), "gd_goal C2": (44, 160, 44),
                      "goal": (255, 0, 0)}.items():
        assert (np.abs(pixels - rgb).max(axis=1) <= 12).sum() >= 20, f"{name} not drawn"


def test_stm_plans_start_at_q_start():
    from envs.tasks.registry import get_task
    from stm.config import ModelConfig
    from stm.control.plans import stm_plans
    from stm.model import STM

    torch.manual_seed(0)
    model = STM(ModelConfig(hidden_size=8, num_layers=1, mixtures=2), get_task("reacher").layout)
    q = stm_plans(model, FOUR_GOALS[:2], horizon=5)
    assert q.shape == (2, 6, 7) and np.allclose(q[:, 0], NEUTRAL_Q, atol=1e-6)
