"""The validation metric a training run reports every val_every iterations (and a sweep or an early stop reads):
the closed-loop error of the model's rollouts."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.kinematics import tip_position_np
from envs.tasks.base import Demos, Episode, Task
from stm.model import STM
from stm.rollout import generate

VAL_SEED = 987_654  # validation episodes: fixed, and apart from the evaluation seeds


def demo_episodes(demos: Demos, n: int) -> list[Episode]:
    """The first n demonstrations as episodes (start, psi per step, horizon)."""
    return [Episode(q0=demos.q[i, 0], psi=demos.psi[i, : demos.lengths[i] + 1], horizon=int(demos.lengths[i]))
            for i in range(min(n, len(demos)))]


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
        ro = generate(model, task, self.episodes)
        if self.demos is None:
            return float(np.mean([task.kinematic_error(tip_position_np(ro.q[i, : ep.horizon + 1]), ep)
                                  for i, ep in enumerate(self.episodes)]))
        ends = np.array([ro.q[i, ep.horizon] for i, ep in enumerate(self.episodes)])
        demo_ends = np.array([self.demos.q[i, ep.horizon] for i, ep in enumerate(self.episodes)])
        return float(np.linalg.norm(tip_position_np(ends) - tip_position_np(demo_ends), axis=-1).mean())
