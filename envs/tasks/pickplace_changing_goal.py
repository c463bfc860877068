"""Changing-goal pick-and-place, evaluated with the pick-place model.

A level-0 goal, then at switch_step (the first step after the expert's grasp closes:
approach + descend + close = 74 for T = 170) psi switches to new_goal (level 0, at least
10 cm from goal); horizon 255 (1.5x the longest demo); success is judged at new_goal.
`expert_after_switch` gives the expert's direct trajectory to the new goal from any
configuration at the switch (block in hand).
"""

from __future__ import annotations

import logging

import numpy as np

from envs.tasks.base import Episode
from envs.tasks.pickplace import (
    PickPlace,
    check_grip_trajectory,
    grasp_step,
    pad_rows,
    plan_after_grasp,
    run_pick_place,
    sample_new_goals,
    solve_plans,
    tip_poses,
)
from envs.tasks.registry import register

log = logging.getLogger(__name__)


@register
class PickPlaceChangingGoal(PickPlace):
    """Pick-and-place whose goal switches to a new one right after the grasp."""

    name = "pick-place-changing-goal"
    label = "changing-goal pick-and-place"
    model_task = "pick-place"
    report_rank = 22
    panels = ("tip_paths", "changing_goal")
    success_criterion = "the block placed at the new goal (as pick-and-place)"

    @property
    def horizon(self) -> int:
        return int(round(1.5 * self.max_steps))

    @property
    def switch_step(self) -> int:
        """First row after the expert's grasp has closed (for a demo of max_steps)."""
        return grasp_step(self.max_steps)

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, n, levels=(0,))
        new_goals = sample_new_goals(rng, goals)
        H, k, out = self.horizon, self.switch_step, []
        for i in range(n):
            psi = np.repeat(goals[i][None], H + 1, axis=0)
            psi[k:] = new_goals[i]
            out.append(Episode(q0=q0[i], psi=psi, horizon=H, info={
                "goal": goals[i].tolist(), "new_goal": new_goals[i].tolist(), "switch_step": k, "level": 0}))
        return out

    def expert_after_switch(self, episode: Episode, q_switch: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The expert's direct trajectory (q (n+1, 7), grip (n+1,)) from the configuration
        at the switch, block in hand, to placing at the new goal (for comparison figures)."""
        q_switch = np.asarray(q_switch, float)[None]
        tip0, rot0 = tip_poses(q_switch)
        plan = plan_after_grasp(tip0[0], rot0[0], episode.info["new_goal"])
        q, ok = solve_plans([plan], q_switch)
        if not ok[0]:
            log.warning("expert IK did not converge everywhere after the switch")
        return q[0], plan.grip

    def expert_rollout(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        """What the expert does in this episode (horizon+1 rows): pick towards the first
        goal, then at the switch go straight to the new goal, then hold."""
        k = episode.info["switch_step"]
        q1, g1 = self.expert_trajectory(episode.q0, episode.info["goal"], steps=self.max_steps)
        q2, g2 = self.expert_after_switch(episode, q1[k])
        q = pad_rows(np.concatenate([q1[: k + 1], q2[1:]]), episode.horizon + 1)
        g = pad_rows(np.concatenate([g1[: k + 1], g2[1:]]), episode.horizon + 1)
        return q, g

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        return self.expert_rollout(episode)

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q, grip = check_grip_trajectory(q, grip)
        return run_pick_place(q, grip, np.asarray(episode.info["new_goal"], float), 0, self.success)
