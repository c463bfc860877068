"""The training loop reproduces the results of the code it replaced: tests/data/stm_train_reference.pt holds what
the separate single-model and packed training loops (stm/training/loop.py and stm/packed_train.py at commit 66579d5)
computed for the four variants and for two cases that take the other paths of the auto-conditioned unroll
(sampled feedback with input noise, u = 3 and active clipping; windows with burn-in and held demos): per seed,
trained alone and two seeds packed, the losses and gradient norms of 8 iterations, the weights after them and
the rollouts of the trained models; and a checkpoint that code wrote mid-run, which this code must resume.

Tolerances: the old single-model and packed loops already differed in the last bits (torch.mm and oneDNN's fused
LSTM against batched matmuls and the stepped cell), measured on the reference: weights <= 1.2e-7, losses <= 2e-6
(absolute, on values of order 1-10), rollout joint angles <= 6e-8 rad. Asserted, with room for other CPUs' float
rounding: losses within 1e-5 (relative and absolute), gradient norms within 1e-4 relative, weights within 1e-5
absolute (2.7e-6 measured on an AMD EPYC for the plain LSTMs), rollout joint angles within 1e-5 rad, gripper
commands equal. Seeds differ by > 1e-3 in the weights, so every check can fail."""

from pathlib import Path

import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.rollout import generate
from stm.training.checkpoint import save_checkpoint
from stm.training.loop import train, train_packed

REFERENCE = Path(__file__).parent / "data" / "stm_train_reference.pt"
LOSS_TOL, GRAD_NORM_RTOL, WEIGHT_TOL, ROLLOUT_TOL = 1e-5, 1e-4, 1e-5, 1e-5


@pytest.fixture(scope="module")
def reference():
    return torch.load(REFERENCE, weights_only=True)


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    return task, task.demos(0), task.episodes(4, 7)


def _flat(model) -> torch.Tensor:
    return torch.cat([v.flatten() for v in model.state_dict().values()])


def _assert_matches(result, rollout, ref) -> None:
    np.testing.assert_allclose(result.history["train/loss"], ref["loss"].numpy(), rtol=LOSS_TOL, atol=LOSS_TOL)
    np.testing.assert_allclose(result.history["train/grad_norm"], ref["grad_norm"].numpy(), rtol=GRAD_NORM_RTOL)
    assert (_flat(result.model) - ref["weights"]).abs().max().item() < WEIGHT_TOL
    np.testing.assert_allclose(rollout.q, ref["rollout_q"].numpy(), atol=ROLLOUT_TOL, rtol=0)
    np.testing.assert_array_equal(rollout.grip, ref["rollout_grip"].numpy())


CASES = ["lstm", "ac-lstm", "lstm-mdn", "ac-lstm-mdn", "ac-lstm-mdn-sample-noise-u3", "ac-lstm-mdn-windows"]


@pytest.mark.parametrize("case", CASES)
def test_single_and_packed_training_reproduce_the_reference(reference, toy, case):
    task, demos, episodes = toy
    ref = reference["cases"][case]
    model_cfg = ModelConfig.from_dict(ref["model_config"])
    cfgs = [TrainConfig.from_dict({**c, "step_kernel": "python"}) for c in ref["train_configs"]]  # the old code's
    mode = ref["feedback"]
    for k, cfg in enumerate(cfgs):
        alone = train(model_cfg, cfg, task, demos)
        _assert_matches(alone, generate(alone.model, task, episodes, feedback=mode, seed=3), ref["single"][k])
    packed = train_packed(model_cfg, cfgs, task, demos)
    rollouts = generate([r.model for r in packed], task, episodes, feedback=mode, seed=3)
    for k, (result, rollout) in enumerate(zip(packed, rollouts, strict=True)):
        assert result.failure is None
        _assert_matches(result, rollout, ref["packed"][k])
    assert (ref["single"][0]["weights"] - ref["single"][1]["weights"]).abs().max() > 1e-3  # the checks can fail


def test_a_checkpoint_of_the_old_loop_resumes_to_the_reference(reference, toy, tmp_path):
    """Written by the old single-model loop at iteration 4 of the a.c. LSTM-MDN's seed 1: resumed alone and in a
    pack, both reach that seed's reference weights at iteration 8."""
    task, demos, episodes = toy
    ckpt = reference["checkpoint_ac-lstm-mdn_seed1_iter4"]
    ref = reference["cases"]["ac-lstm-mdn"]
    model_cfg = ModelConfig.from_dict(ckpt["model_config"])
    cfgs = [TrainConfig.from_dict({**c, "step_kernel": "python"}) for c in ref["train_configs"]]
    alone_path, packed_path = tmp_path / "alone.pt", tmp_path / "packed.pt"
    save_checkpoint(ckpt, alone_path)
    save_checkpoint(ckpt, packed_path)
    alone = train(model_cfg, cfgs[1], task, demos, checkpoint_path=alone_path)
    _assert_matches(alone, generate(alone.model, task, episodes, seed=3), ref["single"][1])
    packed = train_packed(model_cfg, cfgs, task, demos, checkpoint_paths=[None, packed_path])
    _assert_matches(packed[1], generate(packed[1].model, task, episodes, seed=3), ref["packed"][1])


def test_a_checkpoint_resumes_on_the_other_step_kernel_but_not_with_other_settings(reference, toy, tmp_path):
    """The step kernel is a route (TrainConfig.UNHASHED): a run checkpointed on the Python steps goes on with
    step_kernel "cpp" to the same weights (within the tolerances above); a changed setting is still refused."""
    import dataclasses

    task, demos, _episodes = toy
    ckpt = reference["checkpoint_ac-lstm-mdn_seed1_iter4"]
    ref = reference["cases"]["ac-lstm-mdn"]
    model_cfg = ModelConfig.from_dict(ckpt["model_config"])
    cfg = TrainConfig.from_dict(ref["train_configs"][1])
    path = tmp_path / "ckpt.pt"
    save_checkpoint(ckpt, path)
    with pytest.raises(ValueError, match=r"other settings \(lr\)"):
        train(model_cfg, dataclasses.replace(cfg, lr=cfg.lr * 2), task, demos, checkpoint_path=path)
    resumed = train(model_cfg, dataclasses.replace(cfg, step_kernel="cpp"), task, demos, checkpoint_path=path)
    assert (_flat(resumed.model) - ref["single"][1]["weights"]).abs().max().item() < WEIGHT_TOL
