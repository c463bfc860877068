"""What stm.speed.bench times on: a task of the paper's state sizes, synthetic demonstrations and the plain reference
model."""

from __future__ import annotations

import numpy as np
import torch
from torch import nn

from envs.robot import NEUTRAL_Q
from envs.tasks.base import Demos, StateLayout, Task
from stm import mdn


class BenchTask(Task):
    """phi = tip - goal, psi = goal (reacher and pick-place alike); layout of the named task."""

    def __init__(self, name: str, gripper: bool):
        self.name = self.model_task = name
        self.layout = _task_layout(name, gripper)

    def phi(self, tip_pos, psi):
        return tip_pos - psi


def _task_layout(name: str, gripper: bool) -> StateLayout:
    try:
        from envs.tasks import get_task

        return get_task(name).layout
    except Exception:  # the task may not be registered yet: same sizes as documented
        return StateLayout(phi_dim=3, psi_dim=3, gripper=gripper)


def bench_demos(n: int, steps: int, gripper: bool, seed: int = 0) -> Demos:
    """Smooth random joint paths around the neutral pose (timing only needs realistic magnitudes)."""
    rng = np.random.default_rng(seed)
    dq = rng.normal(0, 0.01, size=(n, steps, 7)).cumsum(axis=1) * 0.1
    q = NEUTRAL_Q + np.concatenate([np.zeros((n, 1, 7)), dq.cumsum(axis=1)], axis=1)
    grip = (np.arange(steps + 1)[None] > steps // 2).astype(float).repeat(n, 0) if gripper else np.zeros((n, steps + 1))
    psi = np.repeat(rng.uniform([0.4, -0.2, 0.0], [0.8, 0.4, 0.2], size=(n, 1, 3)), steps + 1, axis=1)
    return Demos(q=q, grip=grip, psi=psi, lengths=np.full(n, steps))


class PlainMDN(nn.Module):
    """The reference: nn.LSTM + a linear MDN head, nothing else."""

    def __init__(self, dim: int, hidden: int, layers: int, m: int):
        super().__init__()
        self.m, self.dim = m, dim
        self.lstm = nn.LSTM(dim, hidden, layers, batch_first=True)
        self.head = nn.Linear(hidden, m * (dim + 2))

    def loss(self, x: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
        out = self.head(self.lstm(x)[0])
        return mdn.mixture_nll(*mdn.split_params(out, self.m, self.dim, 1e-3), y).mean()
