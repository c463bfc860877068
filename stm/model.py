"""The state transition model (STM): p(s_{t+1} | s_t, h_t).

A multi-layer LSTM reads normalised states and a head maps each hidden state to
the next state: a point (deterministic head, MSE) or an isotropic Gaussian
mixture (MDN head, NLL). What is predicted is the whole next state
s_{t+1} = (dq, grip?, phi, psi) in normalised units; what is *used* when the
prediction is fed back (training feedback and rollouts, `feedback_state`):
  - dq: integrated into the joint positions, q_{t+1} = clamp(q_t + dq);
  - grip: rounded to {0, 1} (straight-through gradient);
  - phi: recomputed by forward kinematics of q_{t+1} ("grounded", default) or
    the model's own prediction ("free");
  - psi: never the prediction; always the task's psi at t+1.
Per-dimension normalisation statistics are buffers, so they live in the
checkpoint with the weights.
"""

from __future__ import annotations

from dataclasses import asdict

import torch
from torch import nn

from envs.tasks.base import StateLayout
from stm import mdn, mdn_fused
from stm.config import ModelConfig
from stm.cpp_ext import step_kernel

STD_FLOOR = 1e-6  # a constant state dimension normalises to 0 instead of dividing by 0


def layout_to_dict(layout: StateLayout) -> dict:
    d = asdict(layout)
    d["phi_names"], d["psi_names"] = list(d["phi_names"]), list(d["psi_names"])
    return d


def layout_from_dict(d: dict) -> StateLayout:
    d = dict(d)
    d["phi_names"], d["psi_names"] = tuple(d.get("phi_names", ())), tuple(d.get("psi_names", ()))
    return StateLayout(**d)


class STM(nn.Module):
    def __init__(self, config: ModelConfig, layout: StateLayout,
                 state_mean: torch.Tensor | None = None, state_std: torch.Tensor | None = None,
                 phi_mode: str = "grounded"):
        super().__init__()
        self.config, self.layout = config, layout
        self.phi_mode = phi_mode  # how fed-back phi was built in training; rollouts default to the same
        dim = layout.dim
        self.dim = dim
        self.register_buffer("state_mean", torch.zeros(dim) if state_mean is None else state_mean.float().clone())
        self.register_buffer("state_std", torch.ones(dim) if state_std is None else state_std.float().clone())
        self.lstm = nn.LSTM(dim, config.hidden_size, config.num_layers, batch_first=True)
        out = mdn.head_size(config.mixtures, dim) if config.head == "mdn" else dim
        self.head = nn.Linear(config.hidden_size, out)

    @property
    def is_mdn(self) -> bool:
        return self.config.head == "mdn"

    # normalisation -------------------------------------------------------
    def normalize(self, s: torch.Tensor) -> torch.Tensor:
        return (s - self.state_mean) / self.state_std

    def denormalize(self, z: torch.Tensor) -> torch.Tensor:
        return z * self.state_std + self.state_mean

    # network -------------------------------------------------------------
    def forward(self, z: torch.Tensor, hc: tuple[torch.Tensor, torch.Tensor] | None = None):
        """Normalised states (B, T, D) -> head outputs (B, T, out), (h, c)."""
        h, hc = self.lstm(z, hc)
        return self.head(h), hc

    def loss(self, raw: torch.Tensor, target: torch.Tensor, mask: torch.Tensor, kernel: str = "python"
             ) -> torch.Tensor:
        """Mean per-step loss over the valid steps (step_losses): raw (B, T, out), target (B, T, D) normalised
        next states, mask (B, T) bool; kernel as step_losses'."""
        per_step = step_losses(raw, target, self.config, kernel)
        m = mask.to(per_step.dtype)
        return (per_step * m).sum() / m.sum().clamp_min(1.0)

    def mixture(self, raw: torch.Tensor):
        return mdn.split_params(raw, self.config.mixtures, self.dim, self.config.sigma_min)

    def predict(self, raw: torch.Tensor, mode: str = "component_mean", *, temperature: float = 1.0,
                generator: torch.Generator | None = None) -> torch.Tensor:
        """Head output -> one predicted next state in normalised units (the deterministic head ignores mode)."""
        if not self.is_mdn:
            return raw
        if mode == "sample":
            return mdn.sample(*self.mixture(raw), temperature=temperature, generator=generator)
        m = self.config.mixtures  # the means need neither sigmas nor a softmax: skip them (hot path)
        logit_alpha, mu = raw[..., :m], raw[..., 2 * m:].unflatten(-1, (m, self.dim))
        if mode == "component_mean":
            return mdn.component_mean(logit_alpha, mu)
        if mode == "mixture_mean":
            return mdn.mixture_mean(logit_alpha, mu)
        raise ValueError(f"unknown feedback mode {mode!r}; known: sample, component_mean, mixture_mean")

    def feedback_predictor(self, mode: str, dims: int):
        """For the self-fed steps: a function top hidden state (B, H) -> the first `dims`
        dimensions of the predicted next state in raw units, equal to
        denormalize(predict(head(h), mode))[..., :dims]. Built once per unroll, inside the
        autograd graph: only the head rows it reads are kept (the mixture logits and the
        first `dims` mean coordinates per component; no sigmas) and the denormalisation is
        folded into them. None where that does not apply (sampling needs the sigmas)."""
        std, mean = self.state_std[:dims], self.state_mean[:dims]
        w, b = self.head.weight, self.head.bias
        if not self.is_mdn:
            w_fb, b_fb = (w[:dims] * std[:, None]).t(), torch.addcmul(mean, b[:dims], std)
            return lambda h: torch.addmm(b_fb, h, w_fb)
        if mode not in ("component_mean", "mixture_mean"):
            return None
        m, D = self.config.mixtures, self.dim
        w_mu = w[2 * m:].unflatten(0, (m, D))[:, :dims] * std[:, None]  # (m, dims, H)
        b_mu = torch.addcmul(mean, b[2 * m:].unflatten(0, (m, D))[:, :dims], std)
        w_fb = torch.cat([w[:m], w_mu.flatten(0, 1)]).t()  # (H, m + m * dims)
        b_fb = torch.cat([b[:m], b_mu.flatten()])

        def predict(h: torch.Tensor) -> torch.Tensor:
            out = torch.addmm(b_fb, h, w_fb)
            logit_alpha, mu = out[:, :m], out[:, m:].view(-1, m, dims)
            if mode == "component_mean":
                return mdn.component_mean(logit_alpha, mu)
            return mdn.mixture_mean(logit_alpha, mu)  # sum alpha_i = 1: the folded mean carries over

        return predict


def step_losses(raw: torch.Tensor, target: torch.Tensor, config: ModelConfig, kernel: str = "python") -> torch.Tensor:
    """The loss of each step (...) of head outputs raw (..., out) against normalised next states target (..., D):
    the NLL of an MDN head, the MSE averaged over dims of a deterministic one. kernel (TrainConfig.step_kernel):
    where it runs "cpp" (stm.cpp_ext.step_kernel) the NLL is the fused C++ op where it applies (stm.mdn_fused),
    else stm.mdn's (the reference). One model's loss (STM.loss) and a pack's (stm.packed.PackView.losses)."""
    if config.head != "mdn":
        return (raw - target).square().mean(-1)
    if step_kernel(kernel, raw.device.type) == "cpp":
        return mdn_fused.mixture_nll(raw, target, config.mixtures, config.sigma_min)
    return mdn.mixture_nll(*mdn.split_params(raw, config.mixtures, target.shape[-1], config.sigma_min), target)


def initial_state(task, kin, q0: torch.Tensor, psi0: torch.Tensor, grip0: torch.Tensor | None = None) -> torch.Tensor:
    """s_0 of an episode (dq_0 = 0; gripper open unless given)."""
    grip = None
    if task.layout.gripper:
        grip = torch.zeros(q0.shape[:-1], dtype=q0.dtype, device=q0.device) if grip0 is None else grip0
    return task.states(q0, q0, grip, psi0, kin).to(q0.dtype)


def feedback_state(task, kin, pred: torch.Tensor, q_prev: torch.Tensor, psi: torch.Tensor,
                   phi_mode: str = "grounded") -> tuple[torch.Tensor, torch.Tensor]:
    """Assemble the state fed back from a predicted next state (raw units, (B, D)).

    Returns (state (B, D), q (B, 7)). The same function serves training feedback
    and rollouts, so both see identically built states.
    """
    layout = task.layout
    q = torch.clamp(q_prev + pred[..., layout.dq], kin.lower, kin.upper)  # the robot stays within its limits
    grip = None
    if layout.gripper:
        g = pred[..., layout.grip.start].clamp(0.0, 1.0)
        grip = g + (torch.round(g) - g).detach()  # binary command, straight-through gradient
    if phi_mode == "grounded":
        s = task.states(q, q_prev, grip, psi, kin)
    elif phi_mode == "free":
        parts = [q - q_prev] + ([grip.unsqueeze(-1)] if grip is not None else [])
        s = torch.cat(parts + [pred[..., layout.phi], psi], dim=-1)
    else:
        raise ValueError(f"unknown phi_mode {phi_mode!r}; known: grounded, free")
    return s.to(pred.dtype), q


# Floors of the normalisation std per part of the state, in its units (below every spread seen in the
# reacher and pick-place demos, so those are unchanged). Why: a dimension constant in the demos (the
# circle's tip height) would otherwise normalise a 1 mm drift in closed loop to ~1000 std and derail
# the model.
STD_FLOORS = {"dq": 5e-4, "grip": 0.05, "phi": 0.01, "psi": 0.01}  # rad, command, m, m


def std_floor(layout: StateLayout) -> torch.Tensor:
    """(D,) normalisation std floors of a state layout (STD_FLOORS per part)."""
    floor = torch.full((layout.dim,), STD_FLOOR)
    for part, value in STD_FLOORS.items():
        floor[getattr(layout, part)] = value  # grip: an empty slice without a gripper
    return floor


def normalization_stats(states: torch.Tensor, mask: torch.Tensor,
                        layout: StateLayout | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """Per-dimension mean and std over the valid rows of (N, T+1, D) states; with a layout, each
    std is at least its part's floor (std_floor), else at least STD_FLOOR."""
    rows = states[mask]
    mean = rows.mean(0)
    std = rows.std(0, unbiased=False).clamp_min(STD_FLOOR)
    if layout is not None:
        std = torch.maximum(std, std_floor(layout).to(std.dtype))
    return mean, std

