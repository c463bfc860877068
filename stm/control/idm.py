"""Inverse dynamics model (IDM) for torque control of STM plans.

The paper's IDM: a 3-layer MDN with 256 units per layer and 15 Gaussians per torque
dimension (7 joints), given the current state, the two previous states and actions
(H = 2) and the desired next state; trained by negative log-likelihood in a
simulator, then used at 10x the STM's rate to track its plans.

- `InverseDynamicsMDN`: MLP trunk (tanh) + one 1-D Gaussian mixture per joint
  (stm.mdn maths with D = 1); inputs and torques standardised with the training
  data's statistics (kept as buffers, so a checkpoint is self-contained).
- `train_idm`: NLL training (Adam), also fine-tuning of a trained model.
- `FastIDM`: the same network as plain numpy matmuls for the control loop (batch 1).
- `IDMController`, `track_plan`: the control loop (see stm.control.idm_study for metrics,
  the sim-to-"real" study and figures).
"""

from __future__ import annotations

import logging
import time
from dataclasses import asdict, dataclass
from typing import Annotated, Literal

import numpy as np
import torch
import torch.nn as nn
from pydantic import Field
from pydantic.dataclasses import dataclass as pydantic_dataclass
from scipy.interpolate import CubicSpline
from tqdm.auto import tqdm

from envs.robot import LIMITS
from stm import mdn
from stm.config import STRICT, NonNegativeInt, PositiveFloat, PositiveInt
from stm.control.idm_data import FEATURE_DIM, HISTORY, IDMData, idm_features
from stm.control.torque_sim import TorqueWorld

log = logging.getLogger(__name__)

N_JOINTS = 7


@pydantic_dataclass(frozen=True, config=STRICT)
class IDMConfig:
    """Network and training settings of the IDM (all logged as parameters)."""

    hidden: PositiveInt = 256  # units per layer (paper)
    layers: PositiveInt = 3  # hidden layers (paper)
    mixtures: PositiveInt = 15  # Gaussians per torque dimension (paper)
    sigma_min: PositiveFloat = 1e-3  # floor of each component's std, in standardised torque units
    lr: PositiveFloat = 1e-3
    batch_size: PositiveInt = 512
    epochs: NonNegativeInt = 40
    val_fraction: Annotated[float, Field(ge=0.0, lt=1.0)] = 0.1
    seed: int = 0
    point: Literal["mixture_mean", "component_mean"] = "mixture_mean"  # torque from the mixture


class InverseDynamicsMDN(nn.Module):
    def __init__(self, cfg: IDMConfig, x_mean=None, x_std=None, y_mean=None, y_std=None):
        super().__init__()
        self.cfg = cfg
        dims = [FEATURE_DIM] + [cfg.hidden] * cfg.layers
        layers: list[nn.Module] = []
        for a, b in zip(dims[:-1], dims[1:], strict=True):
            layers += [nn.Linear(a, b), nn.Tanh()]
        self.trunk = nn.Sequential(*layers)
        self.head = nn.Linear(cfg.hidden, N_JOINTS * mdn.head_size(cfg.mixtures, 1))

        def buf(v, n):
            return torch.as_tensor(np.zeros(n) if v is None else v, dtype=torch.float32)

        self.register_buffer("x_mean", buf(x_mean, FEATURE_DIM))
        self.register_buffer("x_std", buf(x_std, FEATURE_DIM) if x_std is not None else torch.ones(FEATURE_DIM))
        self.register_buffer("y_mean", buf(y_mean, N_JOINTS))
        self.register_buffer("y_std", buf(y_std, N_JOINTS) if y_std is not None else torch.ones(N_JOINTS))

    def mixture(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Per-joint mixtures over standardised torques: logit_alpha (B, 7, m),
        mu (B, 7, m, 1), log_sigma (B, 7, m)."""
        raw = self.head(self.trunk((x - self.x_mean) / self.x_std))
        return mdn.split_params(raw.unflatten(-1, (N_JOINTS, -1)), self.cfg.mixtures, 1, self.cfg.sigma_min)

    def nll(self, x: torch.Tensor, tau: torch.Tensor) -> torch.Tensor:
        """Mean over the batch of the NLL of the torques (summed over joints), in
        standardised units."""
        logit_alpha, mu, log_sigma = self.mixture(x)
        target = ((tau - self.y_mean) / self.y_std).unsqueeze(-1)
        return mdn.mixture_nll(logit_alpha, mu, log_sigma, target).sum(-1).mean()

    def torques(self, x: torch.Tensor) -> torch.Tensor:
        """Joint torques (B, 7) in N m."""
        logit_alpha, mu, log_sigma = self.mixture(x)
        z = mdn.point(logit_alpha, mu, log_sigma, self.cfg.point).squeeze(-1)
        return z * self.y_std + self.y_mean


def standardisation(x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    std = x.std(axis=0)
    return x.mean(axis=0), np.where(std > 1e-6, std, 1.0)  # constant features pass unscaled


def train_idm(data: IDMData, cfg: IDMConfig | None = None, model: InverseDynamicsMDN | None = None,
              progress: bool | None = None) -> tuple[InverseDynamicsMDN, dict[str, list[float]]]:
    """Train a new IDM on `data` (or fine-tune `model`, keeping its standardisation).
    Returns the model and its history: train_nll and val_nll per epoch."""
    cfg = cfg or IDMConfig()
    torch.manual_seed(cfg.seed)
    x, y = data.samples()
    if len(x) < 2:
        raise ValueError(f"IDM training needs at least 2 samples, got {len(x)}")
    rng = np.random.default_rng(cfg.seed)
    order = rng.permutation(len(x))
    n_val = int(round(cfg.val_fraction * len(x)))
    val, tr = order[:n_val], order[n_val:]
    if model is None:
        model = InverseDynamicsMDN(cfg, *standardisation(x[tr]), *standardisation(y[tr]))
    xt, yt = torch.from_numpy(x), torch.from_numpy(y)
    opt = torch.optim.Adam(model.parameters(), lr=cfg.lr)
    history: dict[str, list[float]] = {"train_nll": [], "val_nll": []}
    disable = True if progress is None else not progress
    for _ in tqdm(range(cfg.epochs), desc="IDM training", disable=disable):
        model.train()
        perm = torch.from_numpy(rng.permutation(tr))
        total = 0.0
        for i in range(0, len(perm), cfg.batch_size):
            idx = perm[i:i + cfg.batch_size]
            loss = model.nll(xt[idx], yt[idx])
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            total += loss.item() * len(idx)
        history["train_nll"].append(total / len(tr))
        if n_val:
            model.eval()
            with torch.inference_mode():
                history["val_nll"].append(float(model.nll(xt[val], yt[val])))
    model.eval()
    log.info("IDM trained: %d samples, final train NLL %.3f, val NLL %s", len(tr),
             history["train_nll"][-1] if history["train_nll"] else float("nan"),
             f"{history['val_nll'][-1]:.3f}" if history["val_nll"] else "n/a")
    return model, history


def save_idm(model: InverseDynamicsMDN, path) -> None:
    torch.save({"config": asdict(model.cfg), "state_dict": model.state_dict()}, path)


def load_idm(path) -> InverseDynamicsMDN:
    ckpt = torch.load(path, map_location="cpu", weights_only=True)
    model = InverseDynamicsMDN(IDMConfig(**ckpt["config"]))
    model.load_state_dict(ckpt["state_dict"])
    return model.eval()


class FastIDM:
    """The trained network as numpy matmuls (float64) for one state at a time:
    torch's per-call overhead is larger than this small network's arithmetic."""

    def __init__(self, model: InverseDynamicsMDN):
        sd = {k: v.detach().double().numpy() for k, v in model.state_dict().items()}
        linears = [m for m in model.trunk if isinstance(m, nn.Linear)] + [model.head]
        self.weights = [(lin.weight.detach().double().numpy().T.copy(), lin.bias.detach().double().numpy())
                        for lin in linears]
        self.x_mean, self.x_inv_std = sd["x_mean"], 1.0 / sd["x_std"]
        self.y_mean, self.y_std = sd["y_mean"], sd["y_std"]
        self.m, self.sigma_min, self.point = model.cfg.mixtures, model.cfg.sigma_min, model.cfg.point

    def __call__(self, x: np.ndarray) -> np.ndarray:
        """Torques (..., 7) for features (..., 70)."""
        h = (x - self.x_mean) * self.x_inv_std
        for w, b in self.weights[:-1]:
            h = np.tanh(h @ w + b)
        w, b = self.weights[-1]
        raw = (h @ w + b).reshape(*h.shape[:-1], N_JOINTS, 3 * self.m)
        logits, mu = raw[..., : self.m], raw[..., 2 * self.m:]  # same layout as mdn.split_params
        if self.point == "component_mean":
            z = np.take_along_axis(mu, logits.argmax(-1)[..., None], -1)[..., 0]
        else:
            e = np.exp(logits - logits.max(-1, keepdims=True))
            z = (e * mu).sum(-1) / e.sum(-1)
        return z * self.y_std + self.y_mean


class IDMController:
    """Keeps the IDM's history (two previous states and applied torques) and turns
    (current state, desired next state) into torques clipped to the effort limits."""

    def __init__(self, policy):
        self.policy = policy
        self.effort = LIMITS.effort.astype(float)
        self.states: list[np.ndarray] = []
        self.actions: list[np.ndarray] = []

    def reset(self, s0: np.ndarray, warm_start_iters: int = 3) -> None:
        """Start at rest in s0: past states = s0; past torques = the IDM's own
        holding torque (a few fixed-point passes of 'stay at s0')."""
        s0 = np.asarray(s0, dtype=float)
        self.states = [s0] * HISTORY
        tau = np.zeros(N_JOINTS)
        for _ in range(warm_start_iters):
            tau = np.clip(self.policy(idm_features(s0, s0, s0, tau, tau, s0)), -self.effort, self.effort)
        self.actions = [tau] * HISTORY

    def __call__(self, s: np.ndarray, s_desired_next: np.ndarray) -> np.ndarray:
        x = idm_features(s, self.states[-1], self.states[-2], self.actions[-1], self.actions[-2], s_desired_next)
        tau = np.clip(self.policy(x), -self.effort, self.effort)
        self.states = [self.states[-1], s]
        self.actions = [self.actions[-1], tau]
        return tau


@dataclass
class Tracking:
    """A plan tracked under IDM torque control, at the control rate."""

    times: np.ndarray  # (N+1,) s
    q: np.ndarray  # (N+1, 7) measured
    tip: np.ndarray  # (N+1, 3) measured
    tau: np.ndarray  # (N, 7) applied
    q_desired: np.ndarray  # (N+1, 7) the plan's spline at the control rate
    ratio: int  # control steps per plan step: row k * ratio is plan step k
    step_time_s: float  # mean wall time of one control step (IDM + bookkeeping, no physics)


def desired_states(plan: np.ndarray, step_seconds: float, control_period: float) -> tuple[np.ndarray, ...]:
    """Times (N+1,), joint positions and speeds (N+1, 7) at the control rate: a cubic
    spline through the plan's rows with zero speed at both ends."""
    plan = np.asarray(plan, dtype=float)
    if plan.ndim != 2 or plan.shape[1] != 7 or len(plan) < 2:
        raise ValueError(f"plan must have shape (T+1, 7) with T >= 1, got {plan.shape}")
    ratio = max(1, round(step_seconds / control_period))
    spline = CubicSpline(np.arange(len(plan)) * step_seconds, plan, axis=0, bc_type="clamped")
    times = np.arange((len(plan) - 1) * ratio + 1) * (step_seconds / ratio)
    return times, spline(times), spline(times, 1)


def track_plan(world: TorqueWorld, policy, plan: np.ndarray, step_seconds: float = 0.1) -> Tracking:
    """Track a joint plan (T+1, 7) given at the STM rate with IDM torques at the
    world's control rate, starting at rest at plan[0]."""
    ratio = max(1, round(step_seconds / world.control_period))
    times, q_des, dq_des = desired_states(plan, step_seconds, step_seconds / ratio)
    s_des = np.concatenate([q_des, dq_des], axis=1)
    ctrl = IDMController(policy)
    s = world.reset(q_des[0])
    ctrl.reset(s)
    qs, tips, taus = [s[:7]], [world.tip()], []
    busy = 0.0
    for k in range(len(times) - 1):
        t0 = time.perf_counter()
        tau = ctrl(s, s_des[k + 1])
        busy += time.perf_counter() - t0
        taus.append(world.apply(tau))
        s = world.state()
        if not np.isfinite(s).all():
            raise RuntimeError(f"IDM tracking diverged at control step {k}")
        qs.append(s[:7])
        tips.append(world.tip())
    return Tracking(times, np.array(qs), np.array(tips), np.array(taus), q_des, ratio, busy / max(1, len(taus)))

