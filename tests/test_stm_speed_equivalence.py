"""The optimised auto-conditioned unroll (stm.training.autoconditioning.unroll: fused/stepped ground-truth chunks,
a feedback head cut to the rows it reads with the denormalisation folded in, the hand-written
LSTM stack step of stm.lstm_step with the input normalisation folded in, deferred weight gradients)
computes the same loss and gradients as a straightforward step-by-step reference: on the Python steps, and on the
default route (the C++ steps where the extension builds, stm.self_fed)."""

import dataclasses

import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.model import STM, feedback_state, normalization_stats
from stm.packed_lstm_step import PackedStackStepper
from stm.training.autoconditioning import batch_loss, schedule
from stm.training.batches import DemoTensors

KIN = default_tip_kinematics(torch.float32)


def reference_unroll(model: STM, batch, task, cfg: TrainConfig, kin, generator=None) -> torch.Tensor:
    """One nn.LSTM call per step; a self-fed step feeds back the state assembled from the full
    head's prediction one step earlier, exactly as the paper's schedule describes."""
    z_gt = model.normalize(batch.states[:, :-1])
    if cfg.input_noise > 0 and model.training:
        z_gt = z_gt + cfg.input_noise * torch.randn(z_gt.shape, generator=generator)
    T = z_gt.shape[1]
    gt = schedule(T, cfg.u, cfg.v)
    hc, q, raw_prev, outs = None, None, None, []
    for t in range(T):
        if gt[t]:
            z, q = z_gt[:, t], batch.q[:, t]
        else:
            pred = model.denormalize(model.predict(raw_prev, cfg.feedback, temperature=cfg.temperature,
                                                   generator=generator))
            s, q = feedback_state(task, kin, pred, q, batch.psi[:, t], cfg.phi_mode)
            z = model.normalize(s)
            if cfg.detach_feedback:
                z, q = z.detach(), q.detach()
        h, hc = model.lstm(z[:, None], hc)
        raw_prev = model.head(h[:, 0])
        outs.append(raw_prev)
    return torch.stack(outs, dim=1)


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=9, max_steps=13, gripper=True)
    return task, DemoTensors.build(task, task.demos(0))


def _loss_and_grads(model, loss):
    params = [p for p in model.parameters()]
    return loss.detach(), torch.autograd.grad(loss, params)


CASES = {  # (model config overrides, train config): every path through the optimised unroll
    "component_mean_u2v2": ({}, TrainConfig(u=2, v=2)),  # stepped ground-truth chunks
    "component_mean_u3v2": ({}, TrainConfig(u=3, v=2)),  # fused ground-truth chunks
    "mixture_mean_u1v3": ({}, TrainConfig(u=1, v=3, feedback="mixture_mean")),
    "free_phi": ({}, TrainConfig(u=2, v=3, phi_mode="free")),
    "detached": ({}, TrainConfig(u=2, v=2, detach_feedback=True)),
    "input_noise": ({}, TrainConfig(u=2, v=2, input_noise=0.1)),
    "sample": ({}, TrainConfig(u=2, v=3, feedback="sample", temperature=0.5)),
    "deterministic_head": ({"head": "deterministic"}, TrainConfig(u=2, v=2)),
}


@pytest.mark.parametrize("kernel", ["python", "auto"])
@pytest.mark.parametrize("case", list(CASES))
def test_optimised_unroll_matches_reference(toy, case, kernel):
    task, data = toy
    overrides, cfg = CASES[case]
    cfg = dataclasses.replace(cfg, step_kernel=kernel)
    valid = torch.arange(data.states.shape[1])[None] <= data.lengths[:, None]
    torch.manual_seed(0)
    model = STM(ModelConfig(hidden_size=16, num_layers=3, mixtures=3, **overrides), task.layout,
                *normalization_stats(data.states, valid), phi_mode=cfg.phi_mode)
    batch = data.batch(torch.arange(len(data.lengths)))
    target = model.normalize(batch.states[:, 1:])
    ref_loss, ref_grads = _loss_and_grads(model, model.loss(
        reference_unroll(model, batch, task, cfg, KIN, torch.Generator().manual_seed(3)), target, batch.mask))
    loss, grads = _loss_and_grads(model, batch_loss(model, batch, task, cfg, KIN, torch.Generator().manual_seed(3)))
    torch.testing.assert_close(loss, ref_loss, rtol=1e-5, atol=1e-6)
    for (name, _), g, g_ref in zip(model.named_parameters(), grads, ref_grads, strict=True):
        scale = g_ref.abs().max().clamp_min(1e-3)
        torch.testing.assert_close(g / scale, g_ref / scale, rtol=0, atol=2e-5, msg=lambda m, n=name: f"{n}: {m}")


def test_stack_stepper_matches_nn_lstm_with_folded_normalisation():
    """One model as a pack of one; also with a (nearly) constant input dimension: std at the floor, the input at
    its mean."""
    torch.manual_seed(1)
    B, D, H, T = 5, 4, 6, 7
    lstm = torch.nn.LSTM(D, H, 3, batch_first=True)
    mean, std = torch.randn(D), torch.rand(D) + 0.5
    std[1] = 1e-6  # STD_FLOOR
    x = torch.randn(B, T, D) * std + mean
    x[..., 1] = mean[1]
    x.requires_grad_()
    h0, c0 = torch.randn(3, B, H, requires_grad=True), torch.randn(3, B, H, requires_grad=True)
    w = torch.randn(B, T, H)
    params = [x, h0, c0, *lstm.parameters()]
    y, (hn, cn) = lstm((x - mean) / std, (h0, c0))
    ref = torch.autograd.grad((y * w).sum() + hn.sum() + cn.square().sum(), params)
    layers = [tuple(getattr(lstm, f"{name}_l{k}").unsqueeze(0) for name in ("weight_ih", "weight_hh", "bias_ih",
                                                                           "bias_hh")) for k in range(3)]
    stepper = PackedStackStepper(layers, std)
    h, c, ys = [v.unsqueeze(0) for v in h0.unbind(0)], [v.unsqueeze(0) for v in c0.unbind(0)], []
    for t in range(T):
        h, c = stepper((x[:, t] - mean).unsqueeze(0), h, c)
        ys.append(h[-1][0])
    h, c = [v[0] for v in h], [v[0] for v in c]
    y2 = torch.stack(ys, dim=1)
    torch.testing.assert_close(y2, y, atol=1e-6, rtol=1e-5)
    got = torch.autograd.grad((y2 * w).sum() + torch.stack(h).sum() + torch.stack(c).square().sum(), params)
    for a, b in zip(got, ref, strict=True):
        torch.testing.assert_close(a, b, atol=1e-5, rtol=1e-4)
