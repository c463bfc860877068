"""eval.mode_repeats: each episode of a task with modes rolled out R times with distinct, reproducible sampling
seeds; per-episode mode entropy and both-modes share right on hand-made modes; a deterministic model rolled
once and counted R times (entropy 0); the ordinary evaluation unchanged; bad values refused clearly."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

import stm.rollout
from envs.tasks import get_task
from experiments.evaluation import evaluate_model
from experiments.mode_repeats import (
    entropy_bits,
    every_mode,
    mode_metrics,
    repeat_rollouts,
    repeat_seed,
    rollout_modes,
)
from experiments.study_config import EvalConfig
from stm.config import ModelConfig
from stm.model import STM

TASK = "reacher-obstacle-multimodal"
EVAL = {"rollouts": 2, "seed": 10_000, "feedback": "component_mean", "circle_radii": [0.05],
        "circle_unseen_radii": [0.075]}


def _model(head: str) -> STM:
    torch.manual_seed(0)
    layout = get_task(TASK).layout
    return STM(ModelConfig(hidden_size=8, num_layers=1, mixtures=2, head=head), layout,
               torch.zeros(layout.dim), torch.full((layout.dim,), 0.05))


def test_entropy_and_both_modes_on_hand_made_modes():
    modes = np.array([[0, 0, 1, 1],     # an even split: 1 bit, both
                      [1, 1, 1, 1],     # one mode: 0 bits
                      [0, -1, -1, -1],  # one rollout with a mode, the others none: 0 bits, not both
                      [0, 1, 1, 1],     # 1/4 vs 3/4
                      [-1, -1, -1, -1]])  # no mode at all: 0 bits
    h = entropy_bits(modes, 2)
    q = -(0.25 * math.log2(0.25) + 0.75 * math.log2(0.75))
    np.testing.assert_allclose(h, [1.0, 0.0, 0.0, q, 0.0])
    assert every_mode(modes, 2).tolist() == [True, False, False, True, False]
    m = mode_metrics("t", ("a", "b"), modes)
    assert m["t/modes_repeats"] == 4
    assert m["t/modes_entropy_bits_mean"] == pytest.approx((1 + q) / 5)
    assert m["t/modes_both_share"] == pytest.approx(2 / 5)
    assert m["t/modes_share_a"] == pytest.approx(4 / 20) and m["t/modes_share_b"] == pytest.approx(9 / 20)
    assert m["t/modes_between_share"] == pytest.approx(7 / 20)


def test_rollout_modes_reads_the_one_hot_labels():
    results = [{"mode_left": 1.0, "mode_right": 0.0}, {"mode_left": 0.0, "mode_right": 1.0},
               {"mode_left": 0.0, "mode_right": 0.0, "between": 1.0}]
    assert rollout_modes(results, ("left", "right")).tolist() == [0, 1, -1]


def test_repeat_seeds_are_distinct_reproducible_and_repeat_zero_keeps_the_evaluation_seed():
    for train_seed in (0, 1, 2):
        seeds = [repeat_seed(train_seed, r) for r in range(10)]
        assert seeds[0] == train_seed and len(set(seeds)) == 10
        assert seeds == [repeat_seed(train_seed, r) for r in range(10)]
    later = {repeat_seed(s, r) for s in range(3) for r in range(1, 10)}
    assert len(later) == 27 and not later & {0, 1, 2}


def test_mode_repeats_rolls_each_episode_r_times_with_distinct_seeds(monkeypatch):
    seen = []
    real = stm.rollout.generate

    def spy(*args, **kwargs):
        seen.append(kwargs["seed"])
        return real(*args, **kwargs)

    model = _model("mdn")
    plain, (d0,) = evaluate_model(model, [TASK], EVAL, seed=1, timings=False, train_feedback="sample")
    monkeypatch.setattr(stm.rollout, "generate", spy)
    metrics, (d,) = evaluate_model(model, [TASK], {**EVAL, "mode_repeats": 4}, seed=1, timings=False,
                                   train_feedback="sample")
    assert seen == [repeat_seed(1, r) for r in range(4)]  # the ordinary rollout, then 3 repeats
    t = d.modes
    assert not t["deterministic"] and t["repeats"] == 4 and t["sampling_seeds"] == seen
    assert np.asarray(t["mode"]).shape == (2, 4) and np.asarray(t["success"]).shape == (2, 4)
    # repeat 0 is the ordinary evaluation's rollout, whose success is unchanged by the option
    assert [r[0] for r in t["success"]] == [int(r["success"]) for r in d0.results]
    def kept(m):
        return {k: v for k, v in m.items() if "modes_" not in k and not k.startswith("time/")}
    assert kept(metrics) == kept(plain)
    assert metrics[f"{TASK}/modes_repeats"] == 4
    assert metrics[f"{TASK}/modes_entropy_bits_mean"] == pytest.approx(np.mean(t["entropy_bits"]))
    _, (again,) = evaluate_model(model, [TASK], {**EVAL, "mode_repeats": 4}, seed=1, timings=False,
                                 train_feedback="sample")
    assert again.modes == t  # reruns reproduce


def test_a_deterministic_model_is_rolled_once_and_has_entropy_zero(monkeypatch):
    calls = []
    real = stm.rollout.generate
    monkeypatch.setattr(stm.rollout, "generate", lambda *a, **k: calls.append(1) or real(*a, **k))
    metrics, (d,) = evaluate_model(_model("deterministic"), [TASK], {**EVAL, "mode_repeats": 5}, seed=0, timings=False)
    assert len(calls) == 1 and d.modes["deterministic"]
    assert all(len(set(row)) == 1 for row in d.modes["mode"])  # the one path counted 5 times
    assert metrics[f"{TASK}/modes_entropy_bits_mean"] == 0 and metrics[f"{TASK}/modes_both_share"] == 0


def test_tasks_without_modes_are_not_repeated():
    metrics, (d,) = evaluate_model(_model("mdn"), ["reacher"], {**EVAL, "mode_repeats": 3}, seed=0, timings=False)
    assert d.modes is None and not any("modes_" in k for k in metrics)


def test_bad_values_are_refused_clearly():
    with pytest.raises(ValueError, match="mode_repeats"):
        EvalConfig(mode_repeats=-1)
    with pytest.raises(ValueError, match="mode_repeats"):
        EvalConfig(mode_repeats="many")
    with pytest.raises(ValueError, match="repeat must be >= 0"):
        repeat_seed(0, -1)
    task = get_task(TASK)
    with pytest.raises(ValueError, match="mode repeats must be >= 1"):
        repeat_rollouts(_model("mdn"), task, [], [], {"seed": 0}, 0)
    with pytest.raises(ValueError, match="defines no modes"):
        repeat_rollouts(_model("mdn"), get_task("reacher"), [], [], {"seed": 0}, 2)


def test_the_option_is_checked_on_the_command_line_and_hashed_only_when_set():
    from experiments.cells import build_cells
    from experiments.study_config import ConfigError, load_profile

    with pytest.raises(ConfigError, match=r"^eval.mode_repeats: "):
        load_profile("smoke", ["eval.mode_repeats=-2"])
    base = {c.key: c.config_hash for c in build_cells(load_profile("smoke"))}
    off = build_cells(load_profile("smoke", ["eval.mode_repeats=0"]))
    on = build_cells(load_profile("smoke", ["eval.mode_repeats=10"]))
    assert all(base[c.key] == c.config_hash and "mode_repeats" not in c.eval_dict() for c in off)
    assert all(base[c.key] != c.config_hash and c.eval_dict()["mode_repeats"] == 10 for c in on)
