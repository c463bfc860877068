"""What every task provides: its state layout, how phi and psi come from joint
positions, its demonstrations, evaluation episodes, a physics success check, its
expert's timing, its metrics and sweep objective, and what its figures show.

State convention (one row per time step t = 0..T):
    s_t = (dq_t [7], grip_t [1 if the task has a gripper], phi_t [phi_dim], psi_t [psi_dim])
with dq_t = q_t - q_{t-1} (dq_0 = 0), grip_t in {0 open, 1 closed},
phi_t = task.phi(tip(q_t), psi_t) and psi_t the task description at step t.
The same `Task.states` builds states for datasets, training feedback and rollouts.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch

__all__ = ["Demos", "Episode", "StateLayout", "Task"]


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

    def with_hold(self, steps: int) -> Demos:
        """Each demo followed by `steps` steps of holding its last row (q, grip, psi), counted in its length: a
        training lever (TrainConfig.hold_steps), since rollouts run past where the shorter demos end and the
        paper's demos never show the arm staying put."""
        if steps < 0:
            raise ValueError(f"hold steps must be >= 0, got {steps}")
        if steps == 0:
            return self
        rows = np.minimum(np.arange(self.q.shape[1] + steps)[None, :], self.lengths[:, None])  # (N, T_max+1+steps)
        take = lambda a: np.take_along_axis(a, rows.reshape(rows.shape + (1,) * (a.ndim - 2)), axis=1)  # noqa: E731
        return Demos(q=take(self.q), grip=take(self.grip), psi=take(self.psi), lengths=self.lengths + steps,
                     meta={**self.meta, "hold_steps": steps})


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
    """Base class of registered tasks: one module in envs/tasks/ defines a subclass and
    decorates it with `@register` (envs.tasks.registry imports every module there).

    A subclass must set `name` and `layout` and implement `phi`, `episodes`, `evaluate`
    and, for a task with its own demonstrations, `demos` and `config`. Everything else has
    a default that fits a task with a goal position; override what differs. Nothing outside
    envs/ compares a task's name: experiments/ and reports/ ask the task.

    Identity and reports (class attributes):
        name            registry key; also the MLflow metric prefix "<name>/..."
        label           display name in tables and figures (default: name)
        model_task      the task whose demonstrations train the model this task is evaluated
                        with ("" or name: its own; an evaluation-only task names another)
        step_seconds    wall-clock duration of one state transition on the robot
        report_rank     position in reports (lower first; ties by name)
        panels          report panels showing this task's rollouts: "tip_paths" (3D tip paths),
                        "changing_goal" (adapted vs expert path after a goal switch),
                        "circles" (drawn vs ideal circles)
        primary_metric  per-rollout metric (a key of `evaluate`'s dict, lower is better) that
                        summarises the error; the sweep's error objective minimises its mean
        success_criterion  one line saying when an episode succeeds (for reports)
        block_size      edge (m) of the blocks the task handles, None without blocks (figures)
        episode_options constructor options of the model task's dataset that also shape this
                        task's evaluation episodes (start range, horizon): a model trained with
                        them is evaluated with them (see for_evaluation); others (the number of
                        demos, training-only start mixes) leave the evaluation as it is
    """

    name: str = ""
    label: str = ""
    layout: StateLayout
    model_task: str = ""
    step_seconds: float = 0.1
    report_rank: float = 100.0
    panels: tuple[str, ...] = ("tip_paths",)
    primary_metric: str = "final_distance"
    success_criterion: str = ""
    block_size: float | None = None
    episode_options: tuple[str, ...] = ()

    def __init_subclass__(cls, **kwargs) -> None:
        super().__init_subclass__(**kwargs)
        if "label" not in cls.__dict__:  # a subclass with its own name gets its own default label
            cls.label = cls.name

    # state ---------------------------------------------------------------------------
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

    # demonstrations ------------------------------------------------------------------
    def demos(self, seed: int = 0) -> Demos:
        """Generate demonstrations with the IK expert (uncached; see envs.datasets)."""
        raise NotImplementedError

    def config(self) -> dict[str, Any]:
        """Everything that shapes the demonstrations (hashed for the dataset cache). Options
        that shape only the evaluation stay out of it (they must not invalidate the cache)."""
        raise NotImplementedError

    # evaluation ----------------------------------------------------------------------
    def episodes(self, n: int, seed: int) -> list[Episode]:
        """n evaluation episodes, deterministic per seed; different seeds give different
        episodes where the task is random (the evaluation derives one seed per training seed)."""
        raise NotImplementedError

    def evaluate(self, q: np.ndarray, grip: np.ndarray | None, episode: Episode) -> dict[str, float]:
        """Execute a joint trajectory (T+1, 7) in pybullet physics; metrics including
        'success' (0.0 or 1.0) where the task has a success predicate."""
        raise NotImplementedError

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float | None:
        """A cheap, physics-free error (m, lower is better) of a tool-tip path (H+1, 3) on an
        episode: what validation during training tracks. None where the task has none."""
        return None

    @classmethod
    def eval_options(cls, eval_cfg: Mapping[str, Any]) -> dict[str, Any]:
        """Constructor options of this task read from a study's eval section (a dict); raises
        ValueError (one line naming the field) on a bad value. Default: none."""
        return {}

    @classmethod
    def for_evaluation(cls, data: Mapping[str, Any] | None = None,
                       eval_cfg: Mapping[str, Any] | None = None) -> Task:
        """This task as a model trained with the dataset options `data` (its model task's
        constructor options) is evaluated on it: those of `episode_options` (so episodes come
        from the trained start range and horizon), plus its own eval_options."""
        options = {k: v for k, v in (data or {}).items() if k in cls.episode_options}
        return cls(**options, **cls.eval_options(eval_cfg or {}))

    def episode_metrics(self, results: list[dict[str, float]], episodes: list[Episode]) -> dict[str, float]:
        """Extra aggregate metrics over one evaluation (names without the task prefix, e.g. a
        breakdown per episode group); the evaluation adds success and every metric's mean."""
        return {}

    def sweep_objective(self, objective: str, metrics: Mapping[str, float]) -> float:
        """The value a sweep minimises, from the metrics of one evaluation (keys
        "<name>/..."): "failure_rate" = 1 - success rate; "final_distance" (the historical
        name of the error objective) = the mean of this task's primary_metric."""
        if objective == "failure_rate":
            return 1.0 - float(metrics[f"{self.name}/success_rate"])
        if objective == "final_distance":
            return float(metrics[f"{self.name}/{self.primary_metric}_mean"])
        raise ValueError(f"unknown evaluation objective {objective!r}; known: failure_rate, final_distance")

    # the expert on evaluation episodes (compute-time comparison, figures) ------------
    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, np.ndarray | None]:
        """What the IK expert does in `episode`: joint path (T+1, 7) and gripper commands
        (T+1,) or None. Default: the task's `expert_rollout`, where it has one."""
        rollout = getattr(self, "expert_rollout", None)
        if rollout is None:
            raise NotImplementedError(f"task {self.name!r} has no expert for its episodes")
        out = rollout(episode)
        return (out[0], out[1]) if isinstance(out, tuple) else (out, None)

    def expert_batch(self, episodes: list[Episode]) -> np.ndarray | None:
        """The expert on several episodes in one batched IK solve (joint paths (B, T+1, 7)),
        or None where the task has no batched expert (then only one-at-a-time is timed)."""
        return None

    def expert_after_switch(self, episode: Episode, q_switch: np.ndarray):
        """The expert's direct path from the configuration at a goal switch to the new goal
        (q, or (q, grip)), for comparison figures; None where episodes have no switch."""
        return None

    # figures -------------------------------------------------------------------------
    def landmarks(self) -> dict[str, tuple[float, float, float]]:
        """Fixed points of the scene worth marking in figures (label -> base-frame xyz)."""
        return {}

    def scene_blocks(self) -> list[tuple[float, float, float]]:
        """Bottom centres of the blocks standing in the scene when an episode starts."""
        return []

    def describe_paths(self, psis: list[np.ndarray]) -> str:
        """A few words on a set of drawn paths (their psi rows), appended to figure titles."""
        return ""
