"""Closed-loop generation of joint trajectories with a trained STM, then their
execution in pybullet through the task's physics check.

Generation is batched: B episodes (of possibly different horizons, padded to the
longest) advance together, one LSTM step and one batched FK per time step, with
the same state assembly as training (`stm.model.feedback_state`). Each episode's
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


def _feedback_point(model: STM, raw: torch.Tensor, feedback: str, chosen: torch.Tensor, temperature: float,
                    gen: torch.Generator, prev: torch.Tensor | None = None,
                    fresh: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """(normalised next state (B, D), component index (B,) fed back, -1 where none or a blend).
    segment_track: prev (B, D) is the previous step's point, fresh (B,) where a segment starts."""
    none = torch.full(raw.shape[:1], -1, dtype=torch.long, device=raw.device)
    if not model.is_mdn or feedback in ("mixture_mean", "sample"):
        return model.predict(raw, feedback, temperature=temperature, generator=gen), none
    if feedback == "component_mean":  # model.predict's path, unchanged; the index only for the record
        return model.predict(raw, feedback), raw[:, : model.config.mixtures].argmax(dim=-1)
    logit_alpha, mu, log_sigma = model.mixture(raw)
    if feedback == "sample_component":
        chosen = mdn.sample_component(logit_alpha, temperature=temperature, generator=gen)
    if feedback == "segment_track" and prev is not None:
        chosen = torch.where(fresh, chosen, mdn.most_responsible(logit_alpha, mu, log_sigma, prev))
    return mdn.select(mu, chosen), chosen


@torch.no_grad()
def generate(model: STM, task: Task, episodes: list[Episode], *, feedback: str = "component_mean", seed: int = 0,
             temperature: float = 1.0, phi_mode: str | None = None) -> Rollouts:
    """Unroll the model from each episode's q0 for its horizon.

    feedback: what the MDN head feeds back (FEEDBACKS, see the module docstring), drawn with
    `temperature` where it samples; phi_mode: None = as the model was trained (model.phi_mode). Runs on the
    model's device (stm.device), drawing from a CPU generator; the rollouts come back as NumPy arrays."""
    phi_mode = phi_mode or model.phi_mode
    if not episodes:
        raise ValueError("generate needs at least one episode")
    if feedback not in FEEDBACKS:
        raise ValueError(f"unknown feedback {feedback!r}; known: {', '.join(FEEDBACKS)}")
    if temperature <= 0:
        raise ValueError(f"temperature must be > 0, got {temperature}")
    if model.layout.dim != task.layout.dim:
        raise ValueError(f"model state size {model.layout.dim} does not match task {task.name!r} "
                         f"state size {task.layout.dim}")
    was_training = model.training
    model.eval()
    device = model.state_mean.device
    kin = default_tip_kinematics(torch.float32).to(device)
    gen = torch.Generator().manual_seed(seed)
    horizons = np.array([ep.horizon for ep in episodes], dtype=np.int64)
    H = int(horizons.max())
    start = time.perf_counter()
    psi = padded_psi(episodes, H).to(device)
    q = torch.as_tensor(np.stack([ep.q0 for ep in episodes]), dtype=torch.float32).to(device)
    s = initial_state(task, kin, q, psi[:, 0])
    B = len(episodes)
    qs, grips = torch.empty(B, H + 1, 7, device=device), torch.zeros(B, H + 1, device=device)
    comps = torch.full((B, H), -1, dtype=torch.long, device=device)
    qs[:, 0] = q
    hc = None
    grip_idx = task.layout.grip.start if task.layout.gripper else None
    restarts = restart_mask(episodes, H)
    restarts[:, 0] = True  # every episode starts a segment
    starting = restarts.any(0).tolist()  # per step: does an episode start a segment (no device sync per step)
    restarts = restarts.to(device)
    configs = restart_configs(episodes, H)
    configs = None if configs is None else configs.to(device)
    commit = feedback in ("segment_component", "segment_track") and model.is_mdn
    chosen = torch.zeros(B, dtype=torch.long, device=device)
    z = None  # the previous step's fed-back point (normalised)
    for t in range(H):
        if t > 0 and starting[t]:
            rows = restarts[:, t]
            q = restart_from(q, configs, rows, t)
            s = s.clone()
            s[rows] = initial_state(task, kin, q[rows], psi[rows, t])
            hc = tuple(x.clone() for x in hc)
            for x in hc:
                x[:, rows] = 0.0
        raw, hc = model(model.normalize(s).unsqueeze(1), hc)
        if commit and starting[t]:  # draw the segment's component from its first step's weights
            rows = restarts[:, t]
            logit_alpha = model.mixture(raw[rows, 0])[0]
            chosen[rows] = mdn.sample_component(logit_alpha, temperature=temperature, generator=gen)
        z, comps[:, t] = _feedback_point(model, raw[:, 0], feedback, chosen, temperature, gen,
                                         prev=z, fresh=restarts[:, t])
        pred = model.denormalize(z)
        s, q = feedback_state(task, kin, pred, q, psi[:, t + 1], phi_mode)
        qs[:, t + 1] = q
        if grip_idx is not None:
            grips[:, t + 1] = s[:, grip_idx]
    seconds = time.perf_counter() - start
    model.train(was_training)
    q_np, grip_np = qs.cpu().numpy().astype(np.float64), grips.cpu().numpy().astype(np.float64)
    for i, h in enumerate(horizons):  # pad past each horizon with the last valid row
        q_np[i, h + 1:] = q_np[i, h]
        grip_np[i, h + 1:] = grip_np[i, h]
    return Rollouts(q=q_np, grip=grip_np, seconds=seconds, horizons=horizons, components=comps.cpu().numpy())


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
