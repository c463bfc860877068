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


def test_per_episode_step_lists_become_padded_arrays_and_stay_out_of_the_means():
    from experiments.evaluation import result_arrays, task_metrics

    results = [{"success": 1.0, "placed": 1.0, "grip_close_steps": (40,)},
               {"success": 0.0, "placed": 1.0, "grip_close_steps": (40, 169)},
               {"success": 0.0, "placed": 0.0, "grip_close_steps": ()}]
    arrays = result_arrays(results)
    assert arrays["grip_close_steps"].dtype.kind == "i"
    assert arrays["grip_close_steps"].tolist() == [[40, -1], [40, 169], [-1, -1]]
    assert arrays["placed"].tolist() == [1.0, 1.0, 0.0] and arrays["success"].tolist() == [1.0, 0.0, 0.0]
    assert result_arrays([{"success": 1.0, "grip_close_steps": ()}])["grip_close_steps"].shape == (1, 0)
    metrics = task_metrics(get_task("pick-place"), results, [])
    assert metrics["pick-place/placed_mean"] == pytest.approx(2 / 3)
    assert metrics["pick-place/success_rate"] == pytest.approx(1 / 3)
    assert not any("grip_close_steps" in k for k in metrics)


def _first_episode(task, seed: int) -> tuple[bytes, bytes]:
    ep = task.episodes(1, seed)[0]
    return np.asarray(ep.q0).tobytes(), np.asarray(ep.psi).tobytes()


def test_validation_episodes_never_are_test_episodes():
    """eval.split = validation draws every training seed's episodes from eval seed + 10,000 + seed: for seeds 0..99
    none of them is a test episode seed, and every task with random episodes draws other episodes there (a task
    whose episodes do not depend on the seed, the circle's, has no episodes to keep apart)."""
    from envs.tasks import task_names
    from experiments.evaluation import split_seed

    validation = {**EVAL, "split": "validation"}
    assert split_seed(EVAL) == 10_000 and split_seed(validation) == 20_000
    test_seeds = {episode_seed(split_seed(EVAL), s) for s in range(100)}
    validation_seeds = [episode_seed(split_seed(validation), s) for s in range(100)]
    assert not test_seeds & set(validation_seeds) and len(set(validation_seeds)) == 100
    for name in task_names():
        task = get_task(name)
        test = {_first_episode(task, s) for s in test_seeds}
        if len(test) == 1:
            continue  # deterministic episodes (one per radius)
        assert not test & {_first_episode(task, s) for s in validation_seeds}, name
    with pytest.raises(ValueError, match="eval.split: 'train' is not allowed"):
        split_seed({**EVAL, "split": "train"})
    metrics, (d,) = evaluate_model(_model("reacher"), ["reacher"], validation, seed=3, timings=False)
    assert d.episode_seed == 20_003 and metrics["reacher/episode_seed"] == 20_003


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
