"""Training: teacher forcing and auto-conditioning, Adam, gradient clipping, a
NaN/inf guard, exact resume from checkpoints, callbacks for tracking.

Auto-conditioning schedule over the input steps t = 0..T-1 of a sequence:
[gt]*u + [self]*v repeated (`schedule`). A ground-truth step feeds the demo state
s_t; a self step feeds the state assembled (`stm.model.feedback_state`) from the
model's own prediction of s_t made at step t-1, with q_t = q_{t-1} + dq_pred
integrated from the last fed state's q. v = 0 is plain teacher forcing. The loss
is on every valid step (padded steps masked out), as in the acLSTM reference.

Speed: consecutive ground-truth steps go through the LSTM in one fused call
(cuDNN-style multi-step kernel; chunks of <= 2 steps are stepped, cheaper than a
call's set-up); the self-fed steps go one by one through stm.cell's stack step (one
autograd node per step, hand-written backward, weight gradients deferred to one
matmul per layer), fed from a prediction computed from only the head rows the
feedback reads. tests/test_stm_speed_equivalence.py holds all of it to a plain
step-by-step reference (loss and gradients).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from envs.kinematics import default_kinematics
from envs.tasks.base import Demos, Episode, Task
from stm.cell import StackStepper
from stm.checkpoint import check_resumable, checkpoint_payload, load_checkpoint, save_checkpoint
from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.interrupts import whole_step
from stm.model import STM, feedback_state, normalization_stats
from stm.windows import Windows, burn_in_state, sample_windows, take_steps

log = logging.getLogger(__name__)


class TrainingDiverged(RuntimeError):
    """The loss or the gradient became NaN/inf; the last good checkpoint is left on disk."""

    def __init__(self, iteration: int, what: str = "loss"):
        super().__init__(f"training diverged at iteration {iteration}: non-finite {what}")
        self.iteration = iteration


@dataclass
class TrainResult:
    model: STM
    history: dict[str, list[float]]
    seconds: float
    iterations: int
    stopped_early: bool = False
    checkpoint_path: Path | None = None


@dataclass
class Batch:
    """Tensors of a batch of demos, cropped to the longest: states (B, T+1, D) raw units,
    q (B, T+1, 7), psi (B, T+1, P), mask (B, T) True where transition t -> t+1 is valid.
    Windows of demos (stm.windows) carry their burn-in: raw states (B, n, D) and where they are valid."""

    states: torch.Tensor
    q: torch.Tensor
    psi: torch.Tensor
    mask: torch.Tensor
    burn: tuple[torch.Tensor, torch.Tensor] | None = None


@dataclass
class DemoTensors:
    states: torch.Tensor
    q: torch.Tensor
    psi: torch.Tensor
    lengths: torch.Tensor
    extra: dict = field(default_factory=dict)

    @classmethod
    def build(cls, task: Task, demos: Demos) -> DemoTensors:
        if len(demos) == 0:
            raise ValueError("the demonstration set is empty")
        states = task.demo_states(demos, default_kinematics(torch.float64))
        if states.shape[-1] != task.layout.dim:
            raise ValueError(f"demo states have size {states.shape[-1]}, task layout says {task.layout.dim}")
        return cls(states=torch.as_tensor(states, dtype=torch.float32),
                   q=torch.as_tensor(demos.q, dtype=torch.float32),
                   psi=torch.as_tensor(demos.psi, dtype=torch.float32),
                   lengths=torch.as_tensor(demos.lengths, dtype=torch.long))

    def batch(self, idx: torch.Tensor) -> Batch:
        lengths = self.lengths[idx]
        T = int(lengths.max())
        mask = torch.arange(T)[None, :] < lengths[:, None]
        return Batch(self.states[idx, : T + 1], self.q[idx, : T + 1], self.psi[idx, : T + 1], mask)

    def windows(self, idx: torch.Tensor, window: int, burn_in: int, generator: torch.Generator) -> Windows:
        return sample_windows(self.lengths[idx], window, burn_in, generator, self.states.shape[1] - 1)

    def window_batch(self, idx: torch.Tensor, windows: Windows) -> Batch:
        """The windows of demos idx (self.windows), cropped to the longest, with their burn-in."""
        T = windows.longest
        steps = windows.steps[..., : T + 1]
        states = self.states[idx]
        burn = (take_steps(states, windows.burn), windows.burn_valid) if windows.burn.shape[-1] else None
        return Batch(take_steps(states, steps), take_steps(self.q[idx], steps), take_steps(self.psi[idx], steps),
                     windows.mask[..., :T], burn)

    def sample(self, n: int, cfg: TrainConfig, generator: torch.Generator) -> Batch:
        """A training batch: cfg.batch_size demos, or windows of them when cfg.window is set."""
        idx = _sample_indices(n, cfg.batch_size, generator)
        return self.window_batch(idx, self.windows(idx, cfg.window, cfg.burn_in, generator)) if cfg.window \
            else self.batch(idx)


def schedule(T: int, u: int, v: int) -> torch.Tensor:
    """(T,) bool: True where input step t is ground truth ([gt]*u + [self]*v repeated)."""
    t = torch.arange(T)
    return torch.ones(T, dtype=torch.bool) if v == 0 else (t % (u + v)) < u


_STEPPED_GT_CHUNK = 2  # ground-truth chunks up to this long (after the first) go through the stepper too:
# a fused nn.LSTM call costs ~100 us of set-up per layer, more than stepping 2 steps (measured, stm.bench)


def unroll(model: STM, batch: Batch, task: Task, cfg: TrainConfig, kin, generator: torch.Generator | None = None,
           *, return_inputs: bool = False):
    """Head outputs (B, T, out) for the inputs of `batch` under cfg's schedule.

    With return_inputs, also the normalised inputs actually fed (B, T, D).
    """
    z_gt = model.normalize(batch.states[:, :-1])
    noisy = cfg.input_noise > 0 and model.training
    if noisy:
        z_gt = z_gt + cfg.input_noise * torch.randn(z_gt.shape, generator=generator)
    T = z_gt.shape[1]
    hl = cl = None  # per-layer (h, c) lists: zero states, or where a window's burn-in leaves them
    if batch.burn is not None:
        zeros = [z_gt.new_zeros(z_gt.shape[0], model.lstm.hidden_size)] * model.lstm.num_layers
        hl, cl = burn_in_state(StackStepper(model.lstm, model.state_std), batch.burn[0] - model.state_mean,
                               batch.burn[1], zeros, zeros)
    if cfg.v == 0:
        raw, _ = model(z_gt, None if hl is None else (torch.stack(hl), torch.stack(cl)))
        return (raw, z_gt) if return_inputs else raw
    # Per self-fed step: predicted dq (and grip; and phi if "free") -> fed-back state (raw units)
    # -> one step of the LSTM stack. Set up once here, inside the autograd graph: a predictor
    # that computes only the head rows the feedback reads, with the denormalisation folded in
    # (sampling falls back to the full head), and a stepper (stm.cell) that takes centred states.
    layout = task.layout
    dims = layout.phi.stop if cfg.phi_mode == "free" else layout.phi.start
    predict = model.feedback_predictor(cfg.feedback, dims)
    if predict is None:
        def predict(h: torch.Tensor) -> torch.Tensor:
            return model.denormalize(model.predict(model.head(h), cfg.feedback, temperature=cfg.temperature,
                                                   generator=generator))
    stepper = StackStepper(model.lstm, model.state_std)
    mean = model.state_mean
    centred_gt = z_gt * model.state_std if noisy else batch.states[:, :-1] - mean  # ground truth for the stepper
    hs, fed = [], []  # top hidden states (pieces of (B, n, H)) and the self-fed (t, state) pairs
    runs = iter(torch.unique_consecutive(schedule(T, cfg.u, cfg.v), return_counts=True)[1].tolist())  # gt, self, ...
    t = 0
    while t < T:
        n = next(runs)  # ground-truth chunk
        if hl is not None and n <= _STEPPED_GT_CHUNK:
            block = []
            for j in range(n):
                hl, cl = stepper(centred_gt[:, t + j], hl, cl)
                block.append(hl[-1])
            h = torch.stack(block, dim=1)
        else:  # one fused LSTM call
            hc = None if hl is None else (torch.stack(hl), torch.stack(cl))
            h, hc = model.lstm(z_gt[:, t: t + n], hc)
            hl, cl = list(hc[0].unbind(0)), list(hc[1].unbind(0))
        hs.append(h)
        t += n
        k = next(runs, 0)  # self-fed chunk
        if k == 0:
            continue
        q = batch.q[:, t - 1]
        last = h[:, -1]
        block = []
        for _ in range(k):  # self-fed steps
            s, q = feedback_state(task, kin, predict(last), q, batch.psi[:, t], cfg.phi_mode)
            if cfg.detach_feedback:
                s, q = s.detach(), q.detach()
            hl, cl = stepper(s - mean, hl, cl)
            last = hl[-1]
            block.append(last)
            fed.append((t, s))
            t += 1
        hs.append(torch.stack(block, dim=1))
    raw = model.head(torch.cat(hs, dim=1))
    if not return_inputs:
        return raw
    inputs = z_gt.clone()
    for t, s in fed:
        inputs[:, t] = model.normalize(s)
    return raw, inputs


def batch_loss(model: STM, batch: Batch, task: Task, cfg: TrainConfig, kin,
               generator: torch.Generator | None = None) -> torch.Tensor:
    raw = unroll(model, batch, task, cfg, kin, generator)
    return model.loss(raw, model.normalize(batch.states[:, 1:]), batch.mask)


def demo_episodes(demos: Demos, n: int) -> list[Episode]:
    """The first n demonstrations as episodes (start, psi per step, horizon)."""
    return [Episode(q0=demos.q[i, 0], psi=demos.psi[i, : demos.lengths[i] + 1], horizon=int(demos.lengths[i]))
            for i in range(min(n, len(demos)))]


VAL_SEED = 987_654  # validation episodes: fixed, and apart from the evaluation seeds


@dataclass
class Validation:
    """What the validation metric rolls out: fresh task episodes scored by the task's
    kinematic error (new starts and goals: memorising the demos does not help), or, for a
    task without one, the first demos replayed (end-tip distance to the demo's end)."""

    episodes: list[Episode]
    demos: Demos | None = None  # set when replaying demos

    @classmethod
    def build(cls, task: Task, demos: Demos, n: int) -> Validation:
        try:
            episodes = task.episodes(n, VAL_SEED)
        except NotImplementedError:
            episodes = []
        if episodes and type(task).kinematic_error is not Task.kinematic_error:
            return cls(episodes)
        return cls(demo_episodes(demos, n), demos)

    def error(self, model: STM, task: Task) -> float:
        """Mean error (m, lower is better) of closed-loop rollouts (component mean, as trained)."""
        from envs.kinematics import tip_position_np
        from stm.rollout import generate

        ro = generate(model, task, self.episodes)
        if self.demos is None:
            return float(np.mean([task.kinematic_error(tip_position_np(ro.q[i, : ep.horizon + 1]), ep)
                                  for i, ep in enumerate(self.episodes)]))
        ends = np.array([ro.q[i, ep.horizon] for i, ep in enumerate(self.episodes)])
        demo_ends = np.array([self.demos.q[i, ep.horizon] for i, ep in enumerate(self.episodes)])
        return float(np.linalg.norm(tip_position_np(ends) - tip_position_np(demo_ends), axis=-1).mean())


def _sample_indices(n: int, b: int, gen: torch.Generator) -> torch.Tensor:
    if b <= n:
        return torch.randperm(n, generator=gen)[:b]
    return torch.randint(n, (b,), generator=gen)


def train(model_cfg: ModelConfig, train_cfg: TrainConfig, task: Task, demos: Demos, *,
          checkpoint_path: Path | None = None, resume: bool = True,
          on_metrics: Callable[[int, dict[str, float]], None] | None = None,
          on_checkpoint: Callable[[Path, int], None] | None = None,
          on_validation: Callable[[int, float], bool] | None = None,
          progress: bool = False) -> TrainResult:
    """Train an STM on `demos` of `task`; see the module docstring for the schedule."""
    kin = default_tip_kinematics(torch.float32)
    demos = demos.with_hold(train_cfg.hold_steps)
    data = DemoTensors.build(task, demos)
    N = len(demos)
    valid = torch.arange(data.states.shape[1])[None, :] <= data.lengths[:, None]
    torch.manual_seed(train_cfg.seed)
    model = STM(model_cfg, task.layout, *normalization_stats(data.states, valid, task.layout),
                phi_mode=train_cfg.phi_mode)
    opt = torch.optim.Adam(model.parameters(), lr=train_cfg.lr)
    gen = torch.Generator().manual_seed(train_cfg.seed)
    history: dict[str, list[float]] = {"train/loss": [], "train/grad_norm": [], "val/iteration": [],
                                       "val/metric": []}
    start_iter, seconds_before, stopped_early = 0, 0.0, False
    ckpt_path = Path(checkpoint_path) if checkpoint_path is not None else None

    if ckpt_path is not None and resume and ckpt_path.exists():
        ckpt = load_checkpoint(ckpt_path)
        check_resumable(ckpt, model_cfg, train_cfg, task, ckpt_path)
        model.load_state_dict(ckpt["model"])
        opt.load_state_dict(ckpt["optimizer"])
        torch.set_rng_state(ckpt["rng"]["torch"])
        gen.set_state(ckpt["rng"]["batch"])
        history = {k: list(v) for k, v in ckpt["history"].items()}
        start_iter, seconds_before = int(ckpt["iteration"]), float(ckpt["seconds"])
        stopped_early = bool(ckpt.get("stopped_early", False))
        log.info("resuming from %s at iteration %d", ckpt_path, start_iter)

    validation = Validation.build(task, demos, train_cfg.val_episodes) if train_cfg.val_every else None
    warmup_cfg = dataclasses.replace(train_cfg, v=0)  # teacher forcing for the first tf_warmup iterations
    t0 = time.perf_counter()

    saved = start_iter  # the iteration the checkpoint on disk holds (at the start: nothing newer to lose)

    def save(iteration: int) -> None:
        nonlocal saved
        if ckpt_path is None:
            return
        payload = checkpoint_payload(model, opt, model_cfg, train_cfg, task, iteration, gen, history,
                                      seconds_before + time.perf_counter() - t0, stopped_early)
        save_checkpoint(payload, ckpt_path)
        saved = iteration
        if on_checkpoint is not None:
            on_checkpoint(ckpt_path, iteration)

    iteration = start_iter
    show = progress and sys.stderr.isatty()
    bar = tqdm(total=train_cfg.iters, initial=start_iter, desc="train", disable=not show)
    model.train()
    try:
        while iteration < train_cfg.iters and not stopped_early:
            if train_cfg.max_seconds and seconds_before + time.perf_counter() - t0 >= train_cfg.max_seconds:
                log.info("time budget of %.0f s reached at iteration %d", train_cfg.max_seconds, iteration)
                break
            with whole_step():  # a Ctrl-C waits for the step: the state checkpointed below is one iteration's
                batch = data.sample(N, train_cfg, gen)
                schedule_cfg = warmup_cfg if iteration < train_cfg.tf_warmup else train_cfg
                loss = batch_loss(model, batch, task, schedule_cfg, kin, gen)
                if not torch.isfinite(loss):
                    raise TrainingDiverged(iteration + 1, "loss")
                opt.zero_grad(set_to_none=True)
                loss.backward()
                clip = train_cfg.grad_clip if train_cfg.grad_clip > 0 else math.inf
                grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), clip)
                if not torch.isfinite(grad_norm):
                    raise TrainingDiverged(iteration + 1, "gradient")
                opt.step()
                iteration += 1
                history["train/loss"].append(loss.item())
                history["train/grad_norm"].append(grad_norm.item())
            bar.update(1)
            if train_cfg.log_every and iteration % train_cfg.log_every == 0:
                window = history["train/loss"][-train_cfg.log_every:]
                bar.set_postfix(loss=f"{window[-1]:.4g}")
                if on_metrics is not None:
                    on_metrics(iteration, {"train/loss": float(np.mean(window)),
                                           "train/grad_norm": history["train/grad_norm"][-1],
                                           "train/seconds": seconds_before + time.perf_counter() - t0})
            if train_cfg.val_every and iteration % train_cfg.val_every == 0:
                value = validation.error(model, task)
                model.train()
                history["val/iteration"].append(float(iteration))
                history["val/metric"].append(value)
                if on_validation is not None and on_validation(iteration, value):
                    stopped_early = True
                    log.info("stopped early at iteration %d (validation %.4g)", iteration, value)
            if train_cfg.checkpoint_every and iteration % train_cfg.checkpoint_every == 0 and not stopped_early:
                save(iteration)
    except KeyboardInterrupt:  # no finished iteration is lost: checkpointed where it stands, then passed on
        if iteration != saved:
            log.info("interrupted at iteration %d: checkpointed there", iteration)
            save(iteration)
        raise
    finally:
        bar.close()
    save(iteration)
    model.eval()
    return TrainResult(model=model, history=history, seconds=seconds_before + time.perf_counter() - t0,
                       iterations=iteration, stopped_early=stopped_early, checkpoint_path=ckpt_path)
