"""What every task provides: its state layout, how phi and psi come from joint
positions, its demonstrations, evaluation episodes and a physics success check.

State convention (one row per time step t = 0..T):
    s_t = (dq_t [7], grip_t [1 if the task has a gripper], phi_t [phi_dim], psi_t [psi_dim])
with dq_t = q_t - q_{t-1} (dq_0 = 0), grip_t in {0 open, 1 closed},
phi_t = task.phi(tip(q_t), psi_t) and psi_t the task description at step t.
The same `Task.states` builds states for datasets, training feedback and rollouts.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch


@dataclass(frozen=True)
class StateLayout:
    phi_dim: int
    psi_dim: int
    gripper: bool = False
    n_joints: int = 7
    phi_names: tuple[str, ...] = ()
    psi_names: tuple[str, ...] = ()

    @property
    def dim(self) -> int:
        return self.n_joints + int(self.gripper) + self.phi_dim + self.psi_dim

    @property
    def dq(self) -> slice:
        return slice(0, self.n_joints)

    @property
    def grip(self) -> slice:
        """Empty slice when the task has no gripper channel."""
        return slice(self.n_joints, self.n_joints + int(self.gripper))

    @property
    def phi(self) -> slice:
        start = self.n_joints + int(self.gripper)
        return slice(start, start + self.phi_dim)

    @property
    def psi(self) -> slice:
        start = self.phi.stop
        return slice(start, start + self.psi_dim)

    @property
    def names(self) -> list[str]:
        phi = list(self.phi_names) or [f"phi{i}" for i in range(self.phi_dim)]
        psi = list(self.psi_names) or [f"psi{i}" for i in range(self.psi_dim)]
        return [f"dq{i}" for i in range(self.n_joints)] + (["grip"] if self.gripper else []) + phi + psi


@dataclass
class Demos:
    """A demonstration set, padded to a common length.

    q:       (N, T_max+1, 7) joint positions; rows past a demo's end repeat its last row
    grip:    (N, T_max+1) gripper command (0 open, 1 closed); zeros for tasks without one
    psi:     (N, T_max+1, psi_dim) task description at each step
    lengths: (N,) number of transitions of each demo (q[i, :lengths[i]+1] is valid)
    """

    q: np.ndarray
    grip: np.ndarray
    psi: np.ndarray
    lengths: np.ndarray
    meta: dict[str, Any] = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.lengths)

    def mask(self) -> np.ndarray:
        """(N, T_max+1) True on valid rows."""
        t = np.arange(self.q.shape[1])
        return t[None, :] <= self.lengths[:, None]


@dataclass
class Episode:
    """One evaluation episode: where the arm starts and what the task asks at each step.

    psi: (horizon+1, psi_dim) task description per step (a goal switch is a change of rows)
    info: task-specific facts (goal, new_goal, switch_step, radius, ...), JSON-serialisable
    """

    q0: np.ndarray
    psi: np.ndarray
    horizon: int
    info: dict[str, Any] = field(default_factory=dict)


class Task:
    """Base class of registered tasks. Subclasses set the class attributes and
    implement phi, demos, episodes and evaluate."""

    name: str = ""
    layout: StateLayout
    model_task: str = ""  # the task whose demonstrations train the model this task is evaluated with
    step_seconds: float = 0.1  # wall-clock duration of one state transition on the robot

    def phi(self, tip_pos: torch.Tensor, psi: torch.Tensor) -> torch.Tensor:
        """phi from the tool-tip position (..., 3) and psi (..., psi_dim); differentiable."""
        raise NotImplementedError

    def states(self, q: torch.Tensor, q_prev: torch.Tensor, grip: torch.Tensor | None,
               psi: torch.Tensor, kin) -> torch.Tensor:
        """Assemble states (..., D) from joint positions (..., 7), the previous joint
        positions, the gripper command (...,) and psi (..., psi_dim), with phi by FK."""
        parts = [q - q_prev]
        if self.layout.gripper:
            parts.append(grip.unsqueeze(-1).to(q.dtype))
        parts += [self.phi(kin.tip_position(q), psi), psi]
        return torch.cat(parts, dim=-1)

    def demo_states(self, demos: Demos, kin) -> np.ndarray:
        """States (N, T_max+1, D) of a demonstration set (dq_0 = 0)."""
        q = torch.as_tensor(demos.q, dtype=torch.float64)
        q_prev = torch.cat([q[:, :1], q[:, :-1]], dim=1)
        with torch.no_grad():
            s = self.states(q, q_prev, torch.as_tensor(demos.grip, dtype=torch.float64),
                            torch.as_tensor(demos.psi, dtype=torch.float64), kin)
        return s.numpy()

    def demos(self, seed: int = 0) -> Demos:
        """Generate demonstrations with the IK expert (uncached; see envs.datasets)."""
        raise NotImplementedError

    def episodes(self, n: int, seed: int) -> list[Episode]:
        """Evaluation episodes, deterministic per seed."""
        raise NotImplementedError

    def evaluate(self, q: np.ndarray, grip: np.ndarray | None, episode: Episode) -> dict[str, float]:
        """Execute a joint trajectory (T+1, 7) in pybullet physics; metrics including
        'success' (0.0 or 1.0) where the task has a success predicate."""
        raise NotImplementedError

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float | None:
        """A cheap, physics-free error (m, lower is better) of a tool-tip path (H+1, 3) on an
        episode: what validation during training tracks. None where the task has none."""
        return None

    def config(self) -> dict[str, Any]:
        """Everything that shapes the demonstrations (hashed for the dataset cache)."""
        raise NotImplementedError


TASKS: dict[str, type[Task]] = {}


def register(cls: type[Task]) -> type[Task]:
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    TASKS[cls.name] = cls
    return cls


class UnknownTaskError(KeyError):
    def __str__(self) -> str:
        return self.args[0]


def get_task(name: str, **overrides) -> Task:
    """Instantiate a registered task; an unknown name lists the known ones."""
    import envs.tasks  # noqa: F401  (registers the built-in tasks)

    if name not in TASKS:
        raise UnknownTaskError(f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}")
    return TASKS[name](**overrides)
