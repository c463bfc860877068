"""Reacher: from a random joint configuration, bring the tool tip to a random goal.

Documented choices (all positions in the base frame; the table top is at z = -0.15,
the table spans x 0.30..1.00, y -0.60..0.60):
- start: q_raw = NEUTRAL_Q + U(-r, +r) per joint, r = start_joint_range (constructor
  argument, default START_JOINT_RANGE = 0.1 rad), then
  projected by IK onto the tool-down configurations that keep q_raw's tip position
  (nearest in joint space, warm-started from q_raw); kept only if that tip lies in START_BOX.
- goal: uniform in GOAL_BOX (in front of the robot, 10-35 cm above the table), at least
  MIN_DISTANCE from the start tip.
- expert: a straight tip line with a minimum-jerk profile, tool pointing down, solved by
  warm-started IK; steps = 50 + 20 * min(distance / 0.6 m, 1) (rounded), i.e. 50-70.
- one step lasts STEP_SECONDS = 0.1 s; demos must stay under the URDF joint velocity limits.
- phi = tip - goal, psi = goal; success: the measured tip (pybullet, position control)
  is within 5 cm of the goal at the end of the trajectory.

reacher-changing-goal: the same start/goal distribution, a rollout of 1.5x the longest
demonstration (105 steps) whose goal switches to `new_goal` at step `switch_step` (52);
success is judged against the new goal. The model is trained on the reacher demos.

goal_switches (a training-data lever, not the paper's protocol; 0 by default): that fraction of the
demonstrations switches goal on the way, as the changing-goal episodes do: at a step k drawn uniformly from
half-way along the first reach to SWITCH_HOLD steps after it ends (the evaluation switches at step 52 of
reaches of 50-70 steps), psi becomes a new goal at least MIN_DISTANCE from the first, and the expert replans
a straight line to it from where the arm is at k. Such a demonstration lasts k + (50-70) steps.
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
from tqdm import tqdm

from envs.kinematics import tip_position_np
from envs.robot import LIMITS, NEUTRAL_Q
from envs.tasks.base import Demos, Episode, StateLayout, Task
from envs.tasks.expert import (
    check_trajectory,
    line_paths,
    physics_scene,
    solve_tool_down_path,
    tool_down_at,
    velocity_ratio,
)
from envs.tasks.registry import register

log = logging.getLogger(__name__)

# rad, half-width of the uniform start range around NEUTRAL_Q. 0.1, not wider: with the paper's 45 demos
# an ac-lstm-mdn reached 76-80% on new episodes at 0.1 (and 0.05) but 23% at 0.3, where the demos are too
# sparse in (start tip, goal) space and the model memorises them (measured 26 Nov 2026).
START_JOINT_RANGE = 0.1
START_BOX = ((0.35, 0.80), (-0.15, 0.45), (-0.05, 0.30))  # (x, y, z) ranges of the start tip (m)
GOAL_BOX = ((0.45, 0.80), (-0.10, 0.40), (-0.05, 0.20))  # (x, y, z) ranges of the goal (m)
MIN_DISTANCE = 0.10  # m between the start tip and the goal (and between the two goals of a switch)
SUCCESS_RADIUS = 0.05  # m: the reacher's success criterion, defined here only (others import it)
STEP_SECONDS = 0.1
DISTANCE_FOR_MAX_STEPS = 0.6  # m: paths this long or longer get the most steps
SWITCH_HOLD = 10  # steps: a goal-switch demonstration may switch this long after its first reach ends


def _sample_box(rng: np.random.Generator, box, n: int) -> np.ndarray:
    lo = np.array([b[0] for b in box])
    hi = np.array([b[1] for b in box])
    return rng.uniform(lo, hi, size=(n, 3))


def _in_box(x: np.ndarray, box) -> np.ndarray:
    lo = np.array([b[0] for b in box])
    hi = np.array([b[1] for b in box])
    return np.all((x >= lo) & (x <= hi), axis=-1)


@register
class Reacher(Task):
    """Bring the tool tip from a random start configuration to a random goal."""

    name = "reacher"
    model_task = "reacher"
    step_seconds = STEP_SECONDS
    report_rank = 10
    episode_options = ("start_joint_range", "min_steps", "max_steps")
    success_criterion = f"tool tip within {SUCCESS_RADIUS * 100:g} cm of the goal at the end (physics)"
    layout = StateLayout(
        phi_dim=3, psi_dim=3,
        phi_names=("tip_minus_goal_x", "tip_minus_goal_y", "tip_minus_goal_z"),
        psi_names=("goal_x", "goal_y", "goal_z"),
    )

    def __init__(self, n_demos: int = 45, min_steps: int = 50, max_steps: int = 70,
                 start_joint_range: float = START_JOINT_RANGE, goal_switches: float = 0.0):
        """start_joint_range: half-width (rad) of the uniform start range around NEUTRAL_Q;
        it is part of config(), so another value gets its own dataset cache entry.
        goal_switches: the fraction of demonstrations whose goal switches on the way (module docstring)."""
        if not 1 <= min_steps <= max_steps:
            raise ValueError(f"need 1 <= min_steps <= max_steps, got {min_steps}, {max_steps}")
        if n_demos < 1:
            raise ValueError(f"n_demos must be >= 1, got {n_demos}")
        if not 0.0 <= start_joint_range <= np.pi:
            raise ValueError(f"start_joint_range must be in [0, pi] rad, got {start_joint_range}")
        if not 0.0 <= goal_switches <= 1.0:
            raise ValueError(f"goal_switches must be a fraction in [0, 1], got {goal_switches}")
        self.n_demos, self.min_steps, self.max_steps = n_demos, min_steps, max_steps
        self.start_joint_range = float(start_joint_range)
        self.goal_switches = float(goal_switches)

    def config(self) -> dict[str, Any]:
        return {
            "task": self.model_task, "n_demos": self.n_demos, "min_steps": self.min_steps,
            "max_steps": self.max_steps, "start_joint_range": self.start_joint_range, "start_box": START_BOX,
            "goal_box": GOAL_BOX, "min_distance": MIN_DISTANCE, "step_seconds": self.step_seconds,
            "success_radius": SUCCESS_RADIUS, "profile": "min-jerk line, tool down",
            # only when used, so the paper's datasets keep their cache entries
            **({"goal_switches": self.goal_switches, "switch_hold": SWITCH_HOLD} if self.goal_switches else {}),
        }

    def phi(self, tip_pos, psi):
        return tip_pos - psi

    # sampling ----------------------------------------------------------------
    def sample_starts(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n tool-down start configurations (n, 7), see the module docstring."""
        out: list[np.ndarray] = []
        while len(out) < n:
            r = self.start_joint_range
            raw = NEUTRAL_Q + rng.uniform(-r, r, size=(n, 7))
            q, ok = tool_down_at(tip_position_np(raw), raw)
            ok &= _in_box(tip_position_np(q), START_BOX) & LIMITS.contains(q)
            out.extend(q[ok])
        return np.array(out[:n])

    def sample_goals(self, rng: np.random.Generator, start_tips: np.ndarray) -> np.ndarray:
        """One goal per start tip (n, 3), at least MIN_DISTANCE away from it."""
        goals = _sample_box(rng, GOAL_BOX, len(start_tips))
        while True:
            near = np.linalg.norm(goals - start_tips, axis=-1) < MIN_DISTANCE
            if not near.any():
                return goals
            goals[near] = _sample_box(rng, GOAL_BOX, int(near.sum()))

    def steps_for(self, distance: np.ndarray) -> np.ndarray:
        frac = np.clip(np.asarray(distance) / DISTANCE_FOR_MAX_STEPS, 0.0, 1.0)
        return np.rint(self.min_steps + (self.max_steps - self.min_steps) * frac).astype(int)

    # expert ------------------------------------------------------------------
    def expert(self, q0: np.ndarray, goals: np.ndarray, steps: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Expert joint paths from q0 (B, 7) to goals (B, 3).

        Returns q (B, max(steps)+1, 7) (rows past a path's end repeat its last row),
        steps (B,) and ok (B,): IK converged, within joint limits and joint speeds
        under the URDF limits."""
        start = tip_position_np(q0)
        if steps is None:
            steps = self.steps_for(np.linalg.norm(goals - start, axis=-1))
        steps = np.asarray(steps, dtype=int)
        return self.solve_tip_paths(q0, line_paths(start, goals, steps, int(steps.max())), steps)

    def solve_tip_paths(self, q0: np.ndarray, path: np.ndarray, steps: np.ndarray
                        ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Tool-down joint paths along tip paths (B, max(steps)+1, 3) from q0 (B, 7), as `expert`
        returns them: q (rows past steps[b] repeat row steps[b]), steps and ok."""
        q, converged, _ = solve_tool_down_path(path[:, 1:], q0)
        q = np.concatenate([q0[:, None], q], axis=1)
        for b in range(len(q)):
            q[b, steps[b] + 1:] = q[b, steps[b]]
        ok = converged & LIMITS.contains(q).all(axis=1) & (velocity_ratio(q, self.step_seconds) <= 1.0)
        return q, steps, ok

    def expert_trajectory(self, q_start: np.ndarray, goal: np.ndarray, max_steps: int | None = None) -> np.ndarray:
        """The expert's direct path (n+1, 7) from a configuration q_start (7,) to goal (3,).
        From a configuration whose tool does not point down, the first step turns it down."""
        q_start = np.asarray(q_start, dtype=float).reshape(1, 7)
        goal = np.asarray(goal, dtype=float).reshape(1, 3)
        steps = self.steps_for(np.linalg.norm(goal - tip_position_np(q_start), axis=-1))
        if max_steps is not None:
            steps = np.minimum(steps, max_steps)
        q, steps, _ = self.expert(q_start, goal, steps)
        return q[0, : steps[0] + 1]

    # demonstrations ------------------------------------------------------------
    def demos(self, seed: int = 0) -> Demos:
        rng = np.random.default_rng(seed)
        accepted: list[tuple[np.ndarray, np.ndarray]] = []  # (path (n+1, 7), psi (n+1, 3))
        rejections = {"ik": 0, "physics": 0}
        while len(accepted) < self.n_demos:
            need = self.n_demos - len(accepted)
            q0 = self.sample_starts(rng, need)
            goals = self.sample_goals(rng, tip_position_np(q0))
            q, steps, ok = self.expert(q0, goals)
            candidates = [(q[b, : steps[b] + 1], np.repeat(goals[b][None], steps[b] + 1, axis=0), ok[b])
                          for b in range(need)]
            if self.goal_switches:  # drawn only then, so the paper's datasets stay as they were
                candidates = self._switch_some(rng, candidates)
            for path, psi, ok_b in tqdm(candidates, desc=f"{self.name} demos: physics replay", disable=None,
                                        leave=False):
                if not ok_b:
                    rejections["ik"] += 1
                    continue
                if self.final_distance(path, psi[-1]) >= SUCCESS_RADIUS:
                    rejections["physics"] += 1
                    continue
                accepted.append((path, psi))
        if sum(rejections.values()):
            log.info("reacher demos: resampled %s", rejections)
        lengths = np.array([len(a[0]) - 1 for a in accepted])
        T = int(lengths.max())
        qs, psi = (np.stack([np.concatenate([a[i], np.repeat(a[i][-1:], T + 1 - len(a[i]), axis=0)])
                             for a in accepted]) for i in (0, 1))
        meta = {"rejections": rejections, "expert_success": 1.0, "replayed_in_physics": len(accepted)}
        if self.goal_switches:
            meta["goal_switches"] = int(sum(bool((a[1] != a[1][:1]).any()) for a in accepted))
        return Demos(q=qs, grip=np.zeros(qs.shape[:2]), psi=psi, lengths=lengths, meta=meta)

    def _switch_some(self, rng: np.random.Generator, candidates: list[tuple[np.ndarray, np.ndarray, bool]]
                     ) -> list[tuple[np.ndarray, np.ndarray, bool]]:
        """A `goal_switches` fraction of the candidate demonstrations (path, psi, ok) with a goal switch
        (module docstring): the first reach up to step k (held at its end if k lies past it), then the
        expert's straight reach from there to a new goal; psi is the new goal from row k on."""
        chosen = np.flatnonzero(rng.random(len(candidates)) < self.goal_switches)
        if not len(chosen):
            return candidates
        steps = np.array([len(candidates[b][0]) - 1 for b in chosen])
        k = rng.integers(steps // 2, steps + SWITCH_HOLD + 1)
        firsts = [np.concatenate([candidates[b][0], np.repeat(candidates[b][0][-1:], max(0, kb - s), axis=0)])[: kb + 1]
                  for b, kb, s in zip(chosen, k, steps, strict=True)]
        new_goals = self.sample_goals(rng, np.stack([candidates[b][1][0] for b in chosen]))
        q2, steps2, ok2 = self.expert(np.stack([f[-1] for f in firsts]), new_goals)
        out = list(candidates)
        for i, b in enumerate(chosen):
            second = q2[i, 1: steps2[i] + 1]
            psi = np.concatenate([np.repeat(candidates[b][1][:1], k[i], axis=0),
                                  np.repeat(new_goals[i][None], len(second) + 1, axis=0)])
            out[b] = (np.concatenate([firsts[i], second]), psi, bool(candidates[b][2] and ok2[i]))
        return out

    # evaluation --------------------------------------------------------------
    def final_distance(self, q: np.ndarray, goal: np.ndarray) -> float:
        """Play q (T+1, 7) in physics; distance (m) of the measured tip to goal at the end."""
        tip = physics_scene().play(q, None, self.step_seconds).tip
        return float(np.linalg.norm(tip[-1] - goal))

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, tip_position_np(q0))
        horizon = self.max_steps
        return [Episode(q0=q0[i], psi=np.repeat(goals[i][None], horizon + 1, axis=0), horizon=horizon,
                        info={"goal": goals[i].tolist()}) for i in range(n)]

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, None]:
        return self.expert_trajectory(episode.q0, np.asarray(episode.info["goal"])), None

    def expert_batch(self, episodes: list[Episode]) -> np.ndarray:
        """One IK solve for every episode's straight line to its goal."""
        q0 = np.stack([ep.q0 for ep in episodes])
        return self.expert(q0, np.array([ep.info["goal"] for ep in episodes]))[0]

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float:
        """Distance of the path's last point to the (last) goal."""
        return float(np.linalg.norm(tip[-1] - np.asarray(episode.psi[-1])))

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q = check_trajectory(q)
        d = self.final_distance(q, np.asarray(episode.psi[-1]))
        return {"success": float(d < SUCCESS_RADIUS), "final_distance": d}


@register
class ReacherChangingGoal(Reacher):
    """Reacher whose goal switches halfway through a rollout 1.5x the longest demo."""

    name = "reacher-changing-goal"
    label = "changing-goal reacher"
    model_task = "reacher"
    report_rank = 11
    panels = ("tip_paths", "changing_goal")
    success_criterion = f"tool tip within {SUCCESS_RADIUS * 100:g} cm of the new goal at the end (physics)"

    @property
    def horizon(self) -> int:
        return int(round(1.5 * self.max_steps))

    @property
    def switch_step(self) -> int:
        return self.horizon // 2

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, tip_position_np(q0))
        new_goals = self.sample_goals(rng, goals)  # at least MIN_DISTANCE from the first goal
        H, k = self.horizon, self.switch_step
        out = []
        for i in range(n):
            psi = np.repeat(goals[i][None], H + 1, axis=0)
            psi[k:] = new_goals[i]
            out.append(Episode(q0=q0[i], psi=psi, horizon=H, info={
                "goal": goals[i].tolist(), "new_goal": new_goals[i].tolist(), "switch_step": k}))
        return out

    def expert_after_switch(self, episode: Episode, q_switch: np.ndarray) -> np.ndarray:
        """The expert's direct path (n+1, 7) from the configuration at the switch to the
        new goal, at most horizon - switch_step steps (for comparison figures)."""
        return self.expert_trajectory(q_switch, np.asarray(episode.info["new_goal"]),
                                      max_steps=episode.horizon - episode.info["switch_step"])

    def expert_rollout(self, episode: Episode) -> np.ndarray:
        """What the expert does in this episode (horizon+1, 7): head for the first goal,
        replan straight to the new goal at the switch, then hold."""
        k, H = episode.info["switch_step"], episode.horizon
        first = self.expert_trajectory(episode.q0, np.asarray(episode.info["goal"]))
        first = np.concatenate([first, np.repeat(first[-1:], max(0, k + 1 - len(first)), axis=0)])[: k + 1]
        second = self.expert_after_switch(episode, first[-1])
        q = np.concatenate([first, second[1:]])
        return np.concatenate([q, np.repeat(q[-1:], H + 1 - len(q), axis=0)])

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, None]:
        return self.expert_rollout(episode), None

    def expert_batch(self, episodes: list[Episode]) -> None:
        return None  # two plans per episode (before and after the switch): timed one at a time only

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q = check_trajectory(q)
        d = self.final_distance(q, np.asarray(episode.info["new_goal"]))
        return {"success": float(d < SUCCESS_RADIUS), "final_distance": d}
