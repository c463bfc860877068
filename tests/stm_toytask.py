"""A small real task for the STM tests (not registered): reach the tip of a random
goal configuration along a joint-space line. phi = tip - goal, psi = goal; an
optional gripper channel closes halfway. Evaluation plays the trajectory in pybullet."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from envs.kinematics import tip_position_np
from envs.robot import NEUTRAL_Q
from envs.sim import Scene
from envs.tasks.base import Demos, Episode, StateLayout, Task


class ToyReach(Task):
    name = "stm-toy-reach"
    model_task = "stm-toy-reach"

    def __init__(self, n_demos: int = 8, min_steps: int = 10, max_steps: int = 14, gripper: bool = False):
        self.n_demos, self.min_steps, self.max_steps = n_demos, min_steps, max_steps
        self.layout = StateLayout(phi_dim=3, psi_dim=3, gripper=gripper)

    def phi(self, tip_pos: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        return tip_pos - psi

    def _sample(self, rng, n):
        q0 = NEUTRAL_Q + rng.uniform(-0.2, 0.2, size=(n, 7))
        qg = NEUTRAL_Q + rng.uniform(-0.3, 0.3, size=(n, 7))
        return q0, qg

    def demos(self, seed: int = 0) -> Demos:
        rng = np.random.default_rng(seed)
        q0, qg = self._sample(rng, self.n_demos)
        lengths = rng.integers(self.min_steps, self.max_steps + 1, size=self.n_demos)
        T = int(lengths.max())
        q = np.empty((self.n_demos, T + 1, 7))
        grip = np.zeros((self.n_demos, T + 1))
        for i, L in enumerate(lengths):
            a = np.minimum(np.arange(T + 1) / L, 1.0)[:, None]
            q[i] = q0[i] + a * (qg[i] - q0[i])
            if self.layout.gripper:
                grip[i, L // 2:] = 1.0
        goals = tip_position_np(qg)
        psi = np.repeat(goals[:, None], T + 1, axis=1)
        return Demos(q=q, grip=grip, psi=psi, lengths=lengths)

    def episodes(self, n: int, seed: int) -> list[Episode]:
        q0, qg = self._sample(np.random.default_rng(seed + 1000), n)
        goals = tip_position_np(qg)
        return [Episode(q0=q0[i], psi=np.repeat(goals[i][None], self.max_steps + 1, axis=0), horizon=self.max_steps)
                for i in range(n)]

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        with Scene(table=False) as scene:
            tip = scene.play(np.asarray(q), None, self.step_seconds).tip
        d = float(np.linalg.norm(tip[-1] - episode.psi[-1]))
        return {"success": float(d < 0.05), "final_distance": d}

    def config(self) -> dict:
        return {"n_demos": self.n_demos, "min_steps": self.min_steps, "max_steps": self.max_steps}


@pytest.fixture(autouse=True, scope="module")
def single_torch_thread():
    """Tiny models run fastest on one thread, and much faster on a contended machine; restored after."""
    before = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(before)
