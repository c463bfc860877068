"""stm.training.weights: a checkpoint's weights alone, the file a study export carries per model: deterministic
bytes (the same again from the weights file itself), nothing of resuming, read with weights_only=True, and
checkpoint.load_model rebuilds the very model from it."""

from __future__ import annotations

import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.training.checkpoint import load_checkpoint, load_model
from stm.training.loop import train
from stm.training.weights import weights_bytes, weights_file_bytes

TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)


@pytest.fixture(scope="module")
def checkpoint(tmp_path_factory):
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    path = tmp_path_factory.mktemp("ckpt") / "model.pt"
    cfg = TrainConfig(iters=3, batch_size=2, u=1, v=1, phi_mode="free", step_kernel="python")  # no C++ build
    train(TINY, cfg, task, task.demos(0), checkpoint_path=path)
    return path


def test_weights_are_the_checkpoints_model_alone_and_deterministic(checkpoint, tmp_path):
    ckpt = load_checkpoint(checkpoint)
    data = weights_bytes(ckpt)
    assert data == weights_bytes(load_checkpoint(checkpoint))  # the same weights, the same bytes
    out = tmp_path / "weights.pt"
    out.write_bytes(data)
    assert weights_file_bytes(out) == (data, 3)  # a weights file re-exported: the same bytes again
    assert len(data) < checkpoint.stat().st_size  # no Adam moments, RNG states or history

    saved = torch.load(out, weights_only=True)
    assert not {"optimizer", "rng", "history", "seconds"} & set(saved) and saved["weights_only"] is True
    assert saved["model"].keys() == ckpt["model"].keys()
    assert all(v.dtype == torch.float32 and torch.equal(v, ckpt["model"][k])
               for k, v in saved["model"].items() if v.is_floating_point())


def test_load_model_rebuilds_the_same_model_from_its_weights(checkpoint, tmp_path):
    out = tmp_path / "weights.pt"
    out.write_bytes(weights_file_bytes(checkpoint)[0])
    mine, theirs = load_model(out), load_model(checkpoint)
    assert mine.phi_mode == theirs.phi_mode == "free"
    x = torch.randn(2, 5, mine.dim)
    with torch.no_grad():
        assert torch.equal(mine(x)[0], theirs(x)[0])
