"""`python -m stm.speed.bench --weights CHECKPOINT`: the training iteration on a trained checkpoint's weights, with
subnormals flushed (as training runs) and kept, and their ratio."""

from __future__ import annotations

import pytest
import torch

from envs.datasets import load_demos
from envs.tasks import get_task
from stm.config import ModelConfig, TrainConfig
from stm.training.loop import train
from stm.training.subnormals import flushing


def test_bench_times_a_checkpoints_weights_both_ways(tmp_path, monkeypatch):
    from stm.speed import bench

    task = get_task("reacher")
    ckpt = tmp_path / "model.pt"
    train(ModelConfig(hidden_size=8, num_layers=2, mixtures=2), TrainConfig(iters=3, v=0, checkpoint_every=3),
          task, load_demos(task, 0), checkpoint_path=ckpt)
    monkeypatch.setitem(bench.SIZES, "reacher", dict(hidden=8, mixtures=2, batch=4, steps=6, gripper=False))
    out = bench.main(["--json", "--sizes", "reacher", "--rounds", "1", "--reps", "1", "--no-rollouts", "--no-fk",
                      "--weights", str(ckpt)])
    tw = out["trained_weights"]
    assert (tw["task"], tw["iteration"], tw["head"], tw["v"]) == ("reacher", 3, "mdn", 0)
    assert set(tw["ms_per_iter"]) == {"flushed", "ieee"} and all(v > 0 for v in tw["ms_per_iter"].values())
    assert tw["subnormal_slowdown"] == pytest.approx(tw["ms_per_iter"]["ieee"] / tw["ms_per_iter"]["flushed"], rel=0.02)
    assert not flushing()  # the bench leaves the process's arithmetic as it found it
    assert torch.tensor([1e-40]).mul(1.0).item() > 0
