"""Closed-loop generation of joint trajectories with trained STMs, then their
execution in pybullet through the task's physics check.

Generation is batched: B episodes (of possibly different horizons, padded to the
longest) advance together, one LSTM step and one batched FK per time step, with
the same state assembly as training (`stm.model.feedback_state`). K models (the seeds of
a cell: a list or a stm.packed.PackedSTM) run the same episodes in the same loop, one
batched matmul per layer and step for all K and one FK call for all K x B states; one
model is the case K = 1, stepped through its own nn.LSTM and head so that its numbers
are exactly what it computes alone (the batched step sums its products in another order:
about 1e-7 apart per step, enough to flip an MDN's most likely component). Each episode's
psi is read per step from `episode.psi`, so a goal switch is a change of rows.
A task that chains skills (stacking: three pick-and-places) lists the steps at which
a new skill starts in `episode.info["restart_steps"]`: there the LSTM state is reset
and the input is built as an episode start (dq = 0, gripper open) from the current q, or,
where the episode lists one configuration per restart step in `info["restart_q"]`, from
that configuration (the task moves the arm there by script between the two rows; the row
of the restart step keeps where the last skill ended).

What an MDN feeds back (`feedback`; a deterministic head ignores it):
  component_mean     the mean of the most likely component, each step (the default)
  mixture_mean       sum_i alpha_i mu_i, each step
  sample             a draw of the mixture, each step (weights and sigmas tempered)
  sample_component   the mean of a component drawn each step from the tempered weights
  segment_component  the mean of ONE component drawn from the tempered weights at the first
                     step of each segment (the episode start and each restart step), followed
                     for the whole segment: a rollout that commits to one mode of
                     multimodal demonstrations instead of switching or averaging between them
  segment_track      drawn at the first step of each segment as segment_component, then at each
                     step the component most responsible for the previous step's fed-back point:
                     a head need not keep a mode in the same component slot over time, so
                     following the mode by continuity instead of by slot
"""

from __future__ import annotations

import logging
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
from tqdm.auto import tqdm

from envs.tasks.base import Episode, Task
from stm import mdn
from stm.fk import default_tip_kinematics
from stm.model import STM, feedback_state, initial_state
from stm.packed import PackedSTM
from stm.packed_lstm_step import PackedStackStepper

log = logging.getLogger(__name__)

FEEDBACKS = ("component_mean", "mixture_mean", "sample", "sample_component", "segment_component", "segment_track")


@dataclass
class Rollouts:
    """q (B, H+1, 7) and grip (B, H+1) numpy; rows past an episode's horizon repeat its last row.
    seconds: wall time of the generation (model + FK), not of physics."""

    q: np.ndarray
    grip: np.ndarray
    seconds: float
    horizons: np.ndarray
    components: np.ndarray | None = None  # (B, H) MDN component fed back at each step (-1: none / a blend)

    def __len__(self) -> int:
        return len(self.horizons)


def padded_psi(episodes: list[Episode], horizon: int) -> torch.Tensor:
    rows = []
    for ep in episodes:
        psi = np.asarray(ep.psi, dtype=np.float32)
        if psi.shape[0] < ep.horizon + 1:
            raise ValueError(f"episode psi has {psi.shape[0]} rows, needs horizon+1 = {ep.horizon + 1}")
        psi = psi[: ep.horizon + 1]
        pad = np.repeat(psi[-1:], horizon + 1 - psi.shape[0], axis=0)
        rows.append(np.concatenate([psi, pad], axis=0))
    return torch.as_tensor(np.stack(rows))


def restart_mask(episodes: list[Episode], horizon: int) -> torch.Tensor:
    """(B, H+1) bool: True where an episode starts a new skill (info["restart_steps"])."""
    mask = torch.zeros(len(episodes), horizon + 1, dtype=torch.bool)
    for i, ep in enumerate(episodes):
        for t in ep.info.get("restart_steps", ()):
            if not 0 < int(t) <= ep.horizon:
                raise ValueError(f"restart step {t} outside the episode (horizon {ep.horizon})")
            mask[i, int(t)] = True
    return mask


def restart_configs(episodes: list[Episode], horizon: int) -> torch.Tensor | None:
    """(B, H+1, 7) the configuration each episode restarts from at its restart steps (info["restart_q"], one per
    step of info["restart_steps"], in order), NaN elsewhere; None when no episode lists any."""
    if not any(ep.info.get("restart_q") for ep in episodes):
        return None
    out = torch.full((len(episodes), horizon + 1, 7), float("nan"))
    for i, ep in enumerate(episodes):
        configs = ep.info.get("restart_q") or []
        steps = list(ep.info.get("restart_steps", ()))
        if configs and len(configs) != len(steps):
            raise ValueError(f"{len(configs)} restart configurations for {len(steps)} restart steps")
        for t, q in zip(steps, configs, strict=False):
            out[i, int(t)] = torch.as_tensor(q, dtype=torch.float32)
    return out


def restart_from(q: torch.Tensor, configs: torch.Tensor | None, rows: torch.Tensor, t: int) -> torch.Tensor:
    """q (..., B, 7) with the rows that restart at step t from a listed configuration (restart_configs) set to it."""
    if configs is None:
        return q
    given = rows & ~torch.isnan(configs[:, t, 0])
    return torch.where(given[:, None], configs[:, t], q)


class _OwnLayers:
    """One STM stepped through its own nn.LSTM and head: the numbers it gives alone."""

    K = 1

    def __init__(self, model: STM):
        self.model = self.head = model
        self.layout, self.phi_mode = model.layout, model.phi_mode

    def zeros(self, batch: int) -> None:
        return None  # nn.LSTM starts from zeros

    def __call__(self, s: torch.Tensor, hc):
        """States (1, B, D) -> head outputs (1, B, out), the next (h, c) (layers, B, H)."""
        raw, hc = self.model(self.model.normalize(s).transpose(0, 1), hc)  # (B, 1, D): one time step
        return raw.transpose(0, 1), hc


class _BatchedLayers:
    """K models' stacks in one batched matmul per layer and step (gates i, f, o, 2g as PackedStackStepper's, the
    normalisation's division folded into the first layer), the head one baddbmm (stm.packed.PackView)."""

    def __init__(self, pack: PackedSTM):
        self.head, self.layout, self.phi_mode = pack.view(), pack.layout, pack.phi_mode
        self.K, self.layers, self.hidden = pack.K, pack.config.num_layers, pack.config.hidden_size
        self.wb = PackedStackStepper(self.head.lstm, self.head.state_std).wb

    def zeros(self, batch: int) -> tuple[torch.Tensor, ...]:
        zero = torch.zeros(self.K, batch, self.hidden, device=self.head.state_mean.device)
        return (zero,) * (2 * self.layers)  # h per layer, then c per layer

    def __call__(self, s: torch.Tensor, hc: tuple[torch.Tensor, ...]):
        """States (K, B, D) -> head outputs (K, B, out), the next (h..., c...) (K, B, H) each."""
        x, H = s - self.head.state_mean, hc[0].shape[-1]
        h_out, c_out = [], []
        for k in range(self.layers):
            w, b = self.wb[2 * k], self.wb[2 * k + 1]
            sig = torch.sigmoid(torch.baddbmm(b, torch.cat([x, hc[k]], -1), w))
            g = sig[..., 3 * H:] * 2.0 - 1.0
            c_new = torch.addcmul(sig[..., H: 2 * H] * hc[self.layers + k], sig[..., :H], g)
            x = sig[..., 2 * H: 3 * H] * torch.tanh(c_new)
            h_out.append(x)
            c_out.append(c_new)
        return self.head.head(x), (*h_out, *c_out)


def _layers(models: STM | PackedSTM | list[STM]) -> _OwnLayers | _BatchedLayers:
    if isinstance(models, STM):
        return _OwnLayers(models)
    if isinstance(models, PackedSTM):
        return _BatchedLayers(models)
    if not models:
        raise ValueError("generate needs at least one model")
    return _OwnLayers(models[0]) if len(models) == 1 else _BatchedLayers(PackedSTM.from_models(models))


def _feedback_point(model: STM, raw: torch.Tensor, feedback: str, chosen: torch.Tensor | None, temperature: float,
                    gen: torch.Generator | None, prev: torch.Tensor | None = None,
                    fresh: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(normalised next state (..., B, D), component index (..., B) fed back, -1 where none or a blend), of head
    outputs raw (..., B, out) (model: an STM or a stm.packed.PackView); the modes that draw take one model's (B, out).
    segment_track: prev (B, D) is the previous step's point, fresh (B,) where a segment starts."""
    if not model.is_mdn or feedback in ("mixture_mean", "sample"):
        none = torch.full(raw.shape[:-1], -1, dtype=torch.long, device=raw.device)
        return model.predict(raw, feedback, temperature=temperature, generator=gen), none
    if feedback == "component_mean":  # model.predict's path, unchanged; the index only for the record
        return model.predict(raw, feedback), raw[..., : model.config.mixtures].argmax(dim=-1)
    logit_alpha, mu, log_sigma = model.mixture(raw)
    if feedback == "sample_component":
        chosen = mdn.sample_component(logit_alpha, temperature=temperature, generator=gen)
    if feedback == "segment_track" and prev is not None:
        chosen = torch.where(fresh, chosen, mdn.most_responsible(logit_alpha, mu, log_sigma, prev))
    return mdn.select(mu, chosen), chosen


@torch.no_grad()
def generate(model: STM | PackedSTM | list[STM], task: Task, episodes: list[Episode], *,
             feedback: str = "component_mean", seed: int = 0, temperature: float = 1.0,
             phi_mode: str | None = None) -> Rollouts | list[Rollouts]:
    """Unroll the model from each episode's q0 for its horizon.

    model: one STM (its Rollouts), or K models as a list or a stm.packed.PackedSTM (one Rollouts per model, each
    what the model gives alone up to float rounding, exactly where the list holds one model; each model draws from
    its own generator seeded `seed`; each Rollouts' seconds is the K models' generation time / K).
    feedback: what the MDN head feeds back (FEEDBACKS, see the module docstring), drawn with
    `temperature` where it samples; phi_mode: None = as the model was trained (model.phi_mode). Runs on the
    model's device (stm.device), drawing from CPU generators; the rollouts come back as NumPy arrays."""
    if not episodes:
        raise ValueError("generate needs at least one episode")
    if feedback not in FEEDBACKS:
        raise ValueError(f"unknown feedback {feedback!r}; known: {', '.join(FEEDBACKS)}")
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    layers = _layers(model)
    head, K = layers.head, layers.K
    if layers.layout.dim != task.layout.dim:
        raise ValueError(f"model state size {layers.layout.dim} does not match task {task.name!r} "
                         f"state size {task.layout.dim}")
    phi_mode = phi_mode or layers.phi_mode
    was_training = isinstance(layers, _OwnLayers) and layers.model.training
    if was_training:
        layers.model.eval()
    device = head.state_mean.device
    kin = default_tip_kinematics(torch.float32).to(device)
    gens = [torch.Generator().manual_seed(seed) for _ in range(K)]
    horizons = np.array([ep.horizon for ep in episodes], dtype=np.int64)
    H, B = int(horizons.max()), len(episodes)
    start = time.perf_counter()
    psi = padded_psi(episodes, H).to(device).expand(K, -1, -1, -1)  # (K, B, H+1, P): every state has the model axis
    q0 = torch.as_tensor(np.stack([ep.q0 for ep in episodes]), dtype=torch.float32).to(device)
    s = initial_state(task, kin, q0, psi[0, :, 0]).expand(K, B, -1)
    q = q0.expand(K, B, 7)
    qs, grips = torch.empty(K, B, H + 1, 7, device=device), torch.zeros(K, B, H + 1, device=device)
    comps = torch.full((K, B, H), -1, dtype=torch.long, device=device)
    comps_of = comps.unbind(0)  # each model's, a view
    qs[:, :, 0] = q
    hc = layers.zeros(B)
    grip_idx = task.layout.grip.start if task.layout.gripper else None
    restarts = restart_mask(episodes, H)
    restarts[:, 0] = True  # every episode starts a segment
    starting = restarts.any(0).tolist()  # per step: does an episode start a segment (no device sync per step)
    restarts = restarts.to(device)
    configs = restart_configs(episodes, H)
    configs = None if configs is None else configs.to(device)
    commit = feedback in ("segment_component", "segment_track") and head.is_mdn
    draws = head.is_mdn and feedback not in ("component_mean", "mixture_mean")
    chosen = [torch.zeros(B, dtype=torch.long, device=device) for _ in range(K)]  # each model's component
    points = [None] * K  # each model's previous fed-back point (B, D), normalised
    for t in range(H):
        if t > 0 and starting[t]:
            rows = restarts[:, t]
            q = restart_from(q, configs, rows, t)
            s = s.clone()
            s[:, rows] = initial_state(task, kin, q[:, rows], psi[:, rows, t])
            hc = tuple(x.clone() for x in hc)
            for x in hc:  # the batch axis is the second to last of every layout's state
                x[..., rows, :] = 0.0
        raw, hc = layers(s, hc)
        if not draws:  # nothing drawn: all K models at once
            z, comps[:, :, t] = _feedback_point(head, raw, feedback, None, temperature, None)
        else:  # each model draws from its own generator
            for k, raw_k in enumerate(raw.unbind(0)):
                if commit and starting[t]:  # draw the segment's component from its first step's weights
                    rows = restarts[:, t]
                    logit_alpha = head.mixture(raw_k[rows])[0]
                    chosen[k][rows] = mdn.sample_component(logit_alpha, temperature=temperature, generator=gens[k])
                points[k], comps_of[k][:, t] = _feedback_point(head, raw_k, feedback, chosen[k], temperature,
                                                               gens[k], prev=points[k], fresh=restarts[:, t])
            z = torch.stack(points)
        s, q = feedback_state(task, kin, head.denormalize(z), q, psi[:, :, t + 1], phi_mode)
        qs[:, :, t + 1] = q
        if grip_idx is not None:
            grips[:, :, t + 1] = s[..., grip_idx]
    seconds = time.perf_counter() - start
    if was_training:
        layers.model.train()
    out = []
    for k in range(K):
        q_np, grip_np = qs[k].cpu().numpy().astype(np.float64), grips[k].cpu().numpy().astype(np.float64)
        for i, h in enumerate(horizons):  # pad past each horizon with the last valid row
            q_np[i, h + 1:] = q_np[i, h]
            grip_np[i, h + 1:] = grip_np[i, h]
        out.append(Rollouts(q=q_np, grip=grip_np, seconds=seconds / K, horizons=horizons,
                            components=comps[k].cpu().numpy()))
    return out[0] if isinstance(model, STM) else out


def evaluate(task: Task, rollouts: Rollouts, episodes: list[Episode], progress: bool = False) -> list[dict[str, float]]:
    """Execute each generated trajectory in pybullet (task.evaluate); one metrics dict per episode."""
    if len(rollouts) != len(episodes):
        raise ValueError(f"{len(rollouts)} rollouts for {len(episodes)} episodes")
    out = []
    bar = tqdm(episodes, desc=f"physics {task.name}", disable=not (progress and sys.stderr.isatty()))
    for i, ep in enumerate(bar):
        h = int(rollouts.horizons[i])
        grip = rollouts.grip[i, : h + 1] if task.layout.gripper else None
        out.append(task.evaluate(rollouts.q[i, : h + 1], grip, ep))
    return out
