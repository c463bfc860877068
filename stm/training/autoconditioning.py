"""Auto-conditioning: the schedule of ground-truth and self-fed steps, and the unroll that follows it.

Over the input steps t = 0..T-1 of a sequence the model is fed [gt]*u + [self]*v, repeated (`schedule`). A
ground-truth step feeds the demonstration's state s_t; a self-fed step feeds the state assembled
(`stm.model.feedback_state`) from the model's own prediction of s_t made at step t-1, with q_t = q_{t-1} + dq_pred
integrated from the last fed state's q. v = 0 is plain teacher forcing, and so are a run's first tf_warmup
iterations (`iteration_schedule`). The loss is on every valid step (padded steps masked out), as in the acLSTM
reference.

`unroll` runs K models with independent weights (a pack, stm.packed; one model is a pack of one) through one
schedule. Known inputs go through the LSTM stack many steps at a time: a fused LSTM call per model where the run
is teacher-forced or there is one model, otherwise one batched layer sequence for all K (stm.packed_lstm_step); short
ground-truth chunks between self-fed ones are stepped (a sequence call's set-up costs more than two steps). The
self-fed steps go one by one through the stack step (one autograd node per step, hand-written backward, weight
gradients deferred to one matmul per layer), fed from a prediction computed from only the head rows the feedback
reads. tests/test_stm_speed_equivalence.py holds all of it to a plain step-by-step reference (loss and gradients).
"""

from __future__ import annotations

import dataclasses

import torch

from stm import mdn
from stm.config import TrainConfig
from stm.lstm_step import product_dtype
from stm.model import STM, feedback_state
from stm.packed import PackView
from stm.packed_lstm_step import PackedStackStepper, fused_sequence, layer_sequence
from stm.self_fed import cpp_steps
from stm.training.windows import burn_in_state

STEPPED_GT_CHUNK = 2  # ground-truth chunks up to this long (after the first) are stepped, not sequence calls


def schedule(T: int, u: int, v: int) -> torch.Tensor:
    """(T,) bool: True where input step t is ground truth ([gt]*u + [self]*v repeated)."""
    t = torch.arange(T)
    return torch.ones(T, dtype=torch.bool) if v == 0 else (t % (u + v)) < u


def segments(T: int, u: int, v: int) -> list[tuple[int, int]]:
    """The schedule over T steps as runs (ground-truth steps, self-fed steps), in order; the last may be short."""
    if v == 0:
        return [(T, 0)]
    out, t = [], 0
    while t < T:
        n = min(u, T - t)
        k = min(v, T - t - n)
        out.append((n, k))
        t += n + k
    return out


def iteration_schedule(cfg: TrainConfig, iteration: int) -> tuple[int, int]:
    """(u, v) of a run's next iteration when `iteration` are done: teacher forcing (v = 0) for the first
    tf_warmup."""
    return cfg.u, 0 if iteration < cfg.tf_warmup else cfg.v


def unroll(view: PackView, states: torch.Tensor, q: torch.Tensor, psi: torch.Tensor, steps: list[int], task,
           cfg: TrainConfig, kin, gens: list[torch.Generator | None],
           burn: tuple[torch.Tensor, torch.Tensor] | None = None, *, return_inputs: bool = False):
    """Head outputs (K, B, T, out) of the K models of `view` under cfg's (u, v) schedule. states (K, B, T+1, D),
    q (K, B, T+1, 7), psi (K, B, T+1, P): each model's batch padded to the longest; steps[k] = model k's own T
    (its input noise and samples are drawn for its own steps only, from gens[k], so each generator advances as
    alone). burn: windows' burn-in (stm.training.windows), raw states (K, B, n, D) and where they are valid. With
    return_inputs, also the normalised inputs actually fed (K, B, T, D)."""
    K, B, T1, D = states.shape
    T = T1 - 1
    dt = product_dtype(cfg.matmul_dtype)  # None: float32 products (the fused sequence's always are)
    view = view.with_products(dt)
    mean = view.state_mean
    z_gt = view.normalize(states[:, :, :-1])
    noisy = cfg.input_noise > 0
    if noisy:  # each model's noise from its own generator, over its own steps
        noise = torch.zeros_like(z_gt)
        for k in range(K):
            noise[k, :, : steps[k]] = cfg.input_noise * torch.randn((B, steps[k], D), generator=gens[k])
        z_gt = z_gt + noise
    hl = cl = None  # per-layer (h, c) (K, B, H): zero states, or where a window's burn-in leaves them
    if burn is not None:
        zeros = z_gt.new_zeros(K, B, view.lstm[0][1].shape[-1])
        hl, cl = burn_in_state(PackedStackStepper(view.lstm, view.state_std, dt), burn[0] - mean, burn[1],
                               [zeros] * len(view.lstm), [zeros] * len(view.lstm))
    if cfg.v == 0:
        raw = view.head(fused_sequence(view.lstm, z_gt, hl, cl)[0])
        return (raw, z_gt) if return_inputs else raw
    centred = z_gt * view.state_std if noisy else states[:, :, :-1] - mean  # the stepper folds in the std
    stepper = PackedStackStepper(view.lstm, view.state_std, dt)
    if hl is None:
        hl, cl = stepper.zeros(centred)
    layout = task.layout
    dims = layout.phi.stop if cfg.phi_mode == "free" else layout.phi.start
    point = view.feedback_predictor(cfg.feedback, dims)
    predict = (lambda h, _t: point(h)) if point is not None else _sampler(view, cfg, gens, steps)
    cpp = cpp_steps(view, cfg, task, kin, stepper, psi, return_inputs)  # the steps in C++ (stm.self_fed), or None
    hs: list[torch.Tensor] = []  # top hidden states, chunks (K, B, n, H)
    fed: list[tuple[int, torch.Tensor]] = []  # the self-fed (step, raw state), kept for return_inputs
    t = 0
    for n, k in segments(T, cfg.u, cfg.v):
        from_zero = t == 0 and burn is None  # the first chunk from zero states: a sequence call, however short
        if cpp is not None:
            h, hl, cl = cpp.known(centred[:, :, t: t + n], hl, cl)
        elif n <= STEPPED_GT_CHUNK and not from_zero:
            block = []
            for j in range(n):
                hl, cl = stepper(centred[:, :, t + j], hl, cl)
                block.append(hl[-1])
            h = torch.stack(block, dim=2)
        elif K == 1:  # one model: the fused LSTM kernel beats the layer sequence
            h, hl, cl = fused_sequence(view.lstm, z_gt[:, :, t: t + n], *((None, None) if from_zero else (hl, cl)))
        else:  # K models: one batched layer sequence beats K fused calls
            h, hl, cl = layer_sequence(stepper, centred[:, :, t: t + n], hl, cl)
        hs.append(h)
        t += n
        if k == 0:
            continue
        if cpp is not None:
            h, hl, cl = cpp.self_fed(hl, cl, q[:, :, t - 1], t, k)
            hs.append(h)
            t += k
            continue
        qt, block = q[:, :, t - 1], []
        for _ in range(k):  # self-fed steps
            s, qt = feedback_state(task, kin, predict(hl[-1], t), qt, psi[:, :, t], cfg.phi_mode)
            if cfg.detach_feedback:
                s, qt = s.detach(), qt.detach()
            hl, cl = stepper(s - mean, hl, cl)
            block.append(hl[-1])
            if return_inputs:
                fed.append((t, s))
            t += 1
        hs.append(torch.stack(block, dim=2))
    raw = view.head(torch.cat(hs, dim=2))
    if not return_inputs:
        return raw
    inputs = z_gt.clone()
    for t, s in fed:
        inputs[:, :, t] = view.normalize(s)
    return raw, inputs


def _sampler(view: PackView, cfg: TrainConfig, gens: list[torch.Generator | None], steps: list[int]):
    """Sampled feedback: each model draws from its own generator, only at its own steps."""

    def predict(h: torch.Tensor, t: int) -> torch.Tensor:
        raw = view.head(h)
        out = []
        for k in range(view.K):
            la, mu, ls = view.mixture(raw[k])
            if t < steps[k]:
                out.append(mdn.sample(la, mu, ls, temperature=cfg.temperature, generator=gens[k]))
            else:  # past this model's batch: masked out, no draw
                out.append(mdn.component_mean(la, mu))
        return view.denormalize(torch.stack(out))

    return predict


def unroll_model(model: STM, batch, task, cfg: TrainConfig, kin, generator: torch.Generator | None = None, *,
                 return_inputs: bool = False):
    """`unroll` for one STM (a pack of one whose weights are the model's own, so gradients reach it) on a batch
    (stm.training.batches.Batch): head outputs (B, T, out); with return_inputs also the normalised inputs fed (B, T, D).
    Input noise only in training mode."""
    if not model.training and cfg.input_noise > 0:
        cfg = dataclasses.replace(cfg, input_noise=0.0)
    view = PackView.of_model(model)
    burn = None if batch.burn is None else tuple(x.unsqueeze(0) for x in batch.burn)
    out = unroll(view, batch.states.unsqueeze(0), batch.q.unsqueeze(0), batch.psi.unsqueeze(0),
                 [batch.mask.shape[-1]], task, cfg, kin, [generator], burn, return_inputs=return_inputs)
    return (out[0][0], out[1][0]) if return_inputs else out[0]


def batch_loss(model: STM, batch, task, cfg: TrainConfig, kin, generator: torch.Generator | None = None
               ) -> torch.Tensor:
    """The training loss of one STM on a batch (stm.training.batches.Batch) under cfg's schedule."""
    raw = unroll_model(model, batch, task, cfg, kin, generator)
    return model.loss(raw, model.normalize(batch.states[:, 1:]), batch.mask, cfg.step_kernel)
