"""experiments.evaluation asks the task: episodes per training seed, sampling feedback,
the task's own metrics and expert timing, and per-rollout arrays that keep the seed."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.tasks import get_task
from experiments.evaluation import _timed_counts, episode_seed, evaluate_model, rollout_arrays, rollout_feedback
from stm.config import ModelConfig
from stm.model import STM

EVAL = {"rollouts": 2, "seed": 10_000, "feedback": "component_mean", "circle_radii": [0.05],
        "circle_unseen_radii": [0.075]}


def _model(task: str, head: str = "mdn") -> STM:
    """An untrained model with small output scales (its rollouts stay near the start)."""
    torch.manual_seed(0)
    layout = get_task(task).layout
    return STM(ModelConfig(hidden_size=8, num_layers=1, mixtures=2, head=head), layout,
               torch.zeros(layout.dim), torch.full((layout.dim,), 0.01))


def test_episode_seed_and_feedback_rules():
    assert [episode_seed(10_000, s) for s in range(3)] == [10_000, 10_001, 10_002]
    assert rollout_feedback("component_mean", "sample") == "sample"
    assert rollout_feedback("mixture_mean", "component_mean") == "mixture_mean"
    assert rollout_feedback("component_mean", None) == "component_mean"


def test_timings_take_a_bounded_share_of_the_episodes():
    # (one at a time, batched IK): at most a tenth / a third of them, 3 / 10 from 30 episodes on
    assert [_timed_counts(n) for n in (1, 4, 12, 30, 40, 100)] == [(1, 1), (1, 2), (2, 4), (3, 10), (3, 10),
                                                                   (3, 10)]


def test_each_training_seed_is_evaluated_on_its_own_episodes_and_rollouts_keep_the_seed():
    model = _model("reacher")
    out = {}
    for seed in (0, 1):
        metrics, details = evaluate_model(model, ["reacher"], EVAL, seed=seed, timings=False)
        (d,) = details
        assert d.seed == seed and d.episode_seed == 10_000 + seed and metrics["reacher/episode_seed"] == d.episode_seed
        assert metrics["reacher/n_rollouts"] == 2.0 and "reacher/final_distance_mean" in metrics
        arrays = rollout_arrays(d)
        assert arrays["seed"].tolist() == [seed, seed] and arrays["episode"].tolist() == [0, 1]
        assert arrays["episode_seed"].tolist() == [10_000 + seed] * 2
        out[seed] = arrays["goal"]
    assert not np.allclose(out[0], out[1])  # distinct episodes per seed
    expected = [ep.info["goal"] for ep in get_task("reacher").episodes(2, 10_000)]
    np.testing.assert_allclose(out[0], expected)  # seed 0 keeps the eval seed's episodes


def test_a_model_trained_sampling_is_evaluated_sampling():
    model = _model("reacher")
    _, (mean,) = evaluate_model(model, ["reacher"], EVAL, seed=0, timings=False)
    _, (sampled,) = evaluate_model(model, ["reacher"], EVAL, seed=0, timings=False, train_feedback="sample")
    _, (again,) = evaluate_model(model, ["reacher"], EVAL, seed=0, timings=False, train_feedback="sample")
    assert mean.feedback == "component_mean" and sampled.feedback == "sample"
    assert not np.allclose(mean.q, sampled.q)
    np.testing.assert_array_equal(sampled.q, again.q)  # sampling is seeded by the training seed


@pytest.mark.slow
def test_circle_radii_come_from_the_eval_section_and_metrics_from_the_task():
    metrics, (d,) = evaluate_model(_model("circle"), ["circle"], {**EVAL, "rollouts": 4}, seed=3, timings=True)
    assert [ep.info["radius"] for ep in d.episodes] == [0.05, 0.075, 0.05, 0.075]
    for r in ("r5", "r7.5"):
        assert metrics[f"circle/{r}/n_rollouts"] == 2.0 and np.isfinite(metrics[f"circle/{r}/radial_rmse"])
    assert metrics["circle/radial_rmse_mean"] == pytest.approx(
        np.mean([res["radial_rmse"] for res in d.results]))
    arrays = rollout_arrays(d)
    np.testing.assert_allclose(arrays["center"], [[0.60, 0.16, 0.00]] * 4)
    assert d.timing["ik_seconds_per_traj"] > 0 and d.timing["ik_batched_seconds_per_traj"] > 0


@pytest.mark.slow
def test_changing_goal_rollouts_carry_the_experts_path_after_the_switch():
    _, (d,) = evaluate_model(_model("reacher-changing-goal", "deterministic"), ["reacher-changing-goal"], EVAL,
                             seed=0, timings=True)
    arrays = rollout_arrays(d, n_expert=1)
    k = int(arrays["switch_step"][0])
    assert k > 0 and np.isfinite(arrays["expert_tip"][0]).all(axis=1).any()
    assert np.isnan(arrays["expert_tip"][1]).all()  # only the first n_expert episodes
    assert "ik_batched_seconds_per_traj" not in d.timing and d.timing["ik_seconds_per_traj"] > 0
