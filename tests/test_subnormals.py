"""Training flushes subnormal floats to zero (stm.training.subnormals): on while the loop runs, as before after it,
and the same training as with IEEE subnormals wherever none arise."""

from __future__ import annotations

import contextlib

import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.training import loop
from stm.training.subnormals import flushing, subnormals_flushed

pytestmark = pytest.mark.skipif(not torch.set_flush_denormal(False), reason="no flush-to-zero mode on this CPU")


def test_the_scope_flushes_inside_and_restores_what_was_there():
    tiny = torch.tensor([1e-39])
    assert not flushing() and tiny.item() > 0
    with subnormals_flushed():
        assert flushing()
        assert (tiny * 1.0).item() == 0.0  # a subnormal operand reads as zero
        assert (torch.tensor([1e-30]) * 1e-10).item() == 0.0  # a subnormal result is written as zero
    assert not flushing() and (tiny * 1.0).item() > 0
    torch.set_flush_denormal(True)
    try:
        with subnormals_flushed():
            pass
        assert flushing()  # a caller's own setting outlives the scope
    finally:
        torch.set_flush_denormal(False)


def _train(monkeypatch, flush: bool):
    if not flush:
        monkeypatch.setattr(loop, "subnormals_flushed", contextlib.nullcontext)
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    seen = []
    result = loop.train(ModelConfig(hidden_size=12, num_layers=2, mixtures=4), TrainConfig(iters=25, v=0, lr=1e-2),
                        task, task.demos(0), on_metrics=lambda _it, _m: seen.append(flushing()))
    return result, seen


def test_training_runs_flushed_and_leaves_the_process_as_it_was(monkeypatch):
    result, seen = _train(monkeypatch, flush=True)
    assert seen and all(seen)
    assert not flushing()
    plain, seen_plain = _train(monkeypatch, flush=False)
    assert seen_plain and not any(seen_plain)
    # a toy model's values stay far above the subnormal range: the two arithmetics train it alike
    assert result.history["train/loss"] == plain.history["train/loss"]
    for a, b in zip(result.model.state_dict().values(), plain.model.state_dict().values(), strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
