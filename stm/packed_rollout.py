"""Closed-loop generation with K models at once: stm.rollout.generate for each model of a
pack, on the same episodes, in one batched loop (one batched matmul per layer and step for
all K models, one FK call for all K x B states). Model k's rollouts equal
generate(pack.extract(k), ...) up to float rounding (tests/test_stm_packed.py)."""

from __future__ import annotations

import time

import numpy as np
import torch

from envs.tasks.base import Episode, Task
from stm import mdn
from stm.fk import default_tip_kinematics
from stm.model import STM, feedback_state, initial_state
from stm.packed import PackedSTM, PackView
from stm.packed_lstm_step import PackedStackStepper
from stm.rollout import Rollouts, padded_psi, restart_configs, restart_from, restart_mask


def _step(wb: list[torch.Tensor], x: torch.Tensor, h: list[torch.Tensor], c: list[torch.Tensor]):
    """One inference step of the K stacks (gates i, f, o, 2g as PackedStackStepper's weights)."""
    H = h[0].shape[-1]
    h_out, c_out = [], []
    for k in range(len(h)):
        sig = torch.sigmoid(torch.baddbmm(wb[2 * k + 1], torch.cat([x, h[k]], -1), wb[2 * k]))
        g = sig[..., 3 * H:] * 2.0 - 1.0
        c_new = torch.addcmul(sig[..., H: 2 * H] * c[k], sig[..., :H], g)
        x = sig[..., 2 * H: 3 * H] * torch.tanh(c_new)
        h_out.append(x)
        c_out.append(c_new)
    return h_out, c_out


def _predictor(view: PackView, feedback: str, temperature: float, gens: list[torch.Generator]):
    """Top hidden states (K, B, H) -> predicted next states (K, B, D), raw units."""
    point = view.feedback_predictor(feedback, view.dim)
    if point is not None:
        return point
    if feedback != "sample":
        raise ValueError(f"unknown feedback mode {feedback!r}; known: sample, component_mean, mixture_mean")

    def predict(h: torch.Tensor) -> torch.Tensor:
        raw = view.head(h)
        return view.denormalize(torch.stack([mdn.sample(*view.mixture(raw[k]), temperature=temperature,
                                                        generator=gens[k]) for k in range(view.K)]))

    return predict


@torch.no_grad()
def generate_packed(models: PackedSTM | list[STM], task: Task, episodes: list[Episode], *,
                    feedback: str = "component_mean", seed: int = 0, temperature: float = 1.0,
                    phi_mode: str | None = None) -> list[Rollouts]:
    """One Rollouts per model, as stm.rollout.generate gives each (each model samples from its
    own generator seeded `seed`); each Rollouts' seconds is the pack's generation time / K."""
    pack = models if isinstance(models, PackedSTM) else PackedSTM.from_models(models)
    phi_mode = phi_mode or pack.phi_mode
    if not episodes:
        raise ValueError("generate_packed needs at least one episode")
    if pack.layout.dim != task.layout.dim:
        raise ValueError(f"model state size {pack.layout.dim} does not match task {task.name!r} "
                         f"state size {task.layout.dim}")
    device = pack.state_mean.device  # the pack's device; samples from CPU generators (stm.device)
    K, kin = pack.K, default_tip_kinematics(torch.float32).to(device)
    view = pack.view()
    gens = [torch.Generator().manual_seed(seed) for _ in range(K)]
    predict = _predictor(view, feedback, temperature, gens)
    wb = PackedStackStepper(view.lstm, view.state_std).wb
    horizons = np.array([ep.horizon for ep in episodes], dtype=np.int64)
    H = int(horizons.max())
    start = time.perf_counter()
    psi = padded_psi(episodes, H).to(device)
    B = len(episodes)
    q0 = torch.as_tensor(np.stack([ep.q0 for ep in episodes]), dtype=torch.float32).to(device)
    s = initial_state(task, kin, q0, psi[:, 0]).expand(K, B, -1)
    q = q0.expand(K, B, 7)
    qs, grips = torch.empty(K, B, H + 1, 7, device=device), torch.zeros(K, B, H + 1, device=device)
    qs[:, :, 0] = q
    zeros = torch.zeros(K, B, pack.config.hidden_size, device=device)
    h, c = [zeros] * pack.config.num_layers, [zeros] * pack.config.num_layers
    grip_idx = task.layout.grip.start if task.layout.gripper else None
    restarts = restart_mask(episodes, H)
    starting = restarts.any(0).tolist()  # per step (no device sync per step)
    restarts = restarts.to(device)
    configs = restart_configs(episodes, H)
    configs = None if configs is None else configs.to(device)
    for t in range(H):
        if t > 0 and starting[t]:
            rows = restarts[:, t]
            q = restart_from(q, configs, rows, t)
            s = s.clone()
            s[:, rows] = initial_state(task, kin, q[:, rows], psi[rows, t].expand(K, -1, -1))
            h, c = [x.clone() for x in h], [x.clone() for x in c]
            for x in h + c:
                x[:, rows] = 0.0
        h, c = _step(wb, s - view.state_mean, h, c)
        s, q = feedback_state(task, kin, predict(h[-1]), q, psi[:, t + 1].expand(K, -1, -1), phi_mode)
        qs[:, :, t + 1] = q
        if grip_idx is not None:
            grips[:, :, t + 1] = s[..., grip_idx]
    seconds = time.perf_counter() - start
    out = []
    for k in range(K):
        q_np, grip_np = qs[k].cpu().numpy().astype(np.float64), grips[k].cpu().numpy().astype(np.float64)
        for i, hz in enumerate(horizons):  # pad past each horizon with the last valid row
            q_np[i, hz + 1:] = q_np[i, hz]
            grip_np[i, hz + 1:] = grip_np[i, hz]
        out.append(Rollouts(q=q_np, grip=grip_np, seconds=seconds / K, horizons=horizons))
    return out
