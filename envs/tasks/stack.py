"""Stacking: three pick-and-place sub-episodes at one xy, evaluated with the pick-place model.

Three consecutive pick-place sub-episodes of SUB_HORIZON = 170 steps each (horizon 510)
at one random xy with levels 0, 1, 2: psi rows k*170 .. (k+1)*170 - 1 ask for level k
(the last row too for level 2); the model starts afresh at each sub-episode
(info["restart_steps"]: LSTM state reset, an episode start from the current q). A new
block appears at the pick position right after steps 170 and 340 (unless an unpicked
block still occupies it); placed blocks stay. Success: after 1 s of settling, three
upright blocks stand as a tower, each within 2 cm (xy) of the tower axis and 1 cm (z) of
its level, untouched by the gripper.
"""

from __future__ import annotations

import numpy as np

from envs.blocks import PICK_XY, level_z, rests_at
from envs.tasks.base import Episode
from envs.tasks.pickplace import (
    LEVELS,
    MAX_STEPS,
    MAX_TILT,
    SETTLE_SECONDS,
    STEP_SECONDS,
    XY_TOL,
    Z_TOL,
    PickPlace,
    check_grip_trajectory,
    fresh_world,
    pad_rows,
    sample_goal_xy,
)
from envs.tasks.registry import register

SUB_HORIZON = MAX_STEPS  # steps per stacking sub-episode


@register
class Stack(PickPlace):
    """Three pick-place sub-episodes of SUB_HORIZON steps at one xy, levels 0, 1, 2."""

    name = "stack"
    label = "stacking"
    model_task = "pick-place"
    report_rank = 21
    success_criterion = "three upright blocks stand as a tower at the goal, untouched by the gripper"

    @property
    def horizon(self) -> int:
        return 3 * SUB_HORIZON

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        xy = sample_goal_xy(rng, n)
        H, out = self.horizon, []
        for i in range(n):
            goals = np.array([[*xy[i], level_z(lv)] for lv in LEVELS])
            psi = np.repeat(goals, SUB_HORIZON, axis=0)
            psi = np.concatenate([psi, goals[-1:]])  # the last row keeps level 2
            out.append(Episode(q0=q0[i], psi=psi, horizon=H, info={
                "tower_xy": xy[i].tolist(), "goals": goals.tolist(),
                "switch_steps": [SUB_HORIZON, 2 * SUB_HORIZON], "sub_horizon": SUB_HORIZON,
                # each block is its own pick-and-place: the model restarts from where the last one ended
                "restart_steps": [SUB_HORIZON, 2 * SUB_HORIZON]}))
        return out

    def expert_rollout(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        """The expert builds the tower: three pick-place plans, each padded to SUB_HORIZON."""
        qs, grips, q = [episode.q0[None]], [np.zeros(1)], np.asarray(episode.q0, float)
        for goal in episode.info["goals"]:
            qk, gk = self.expert_trajectory(q, goal)
            qk, gk = pad_rows(qk, SUB_HORIZON + 1), pad_rows(gk, SUB_HORIZON + 1)
            qs.append(qk[1:])
            grips.append(gk[1:])
            q = qk[-1]
        return np.concatenate(qs), np.concatenate(grips)

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        return self.expert_rollout(episode)

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        """Metrics: success, blocks_in_tower (levels built from the bottom up), n_blocks
        (blocks that appeared), final_distance (mean over levels of the distance from the
        level's goal to the nearest block bottom, m)."""
        q, grip = check_grip_trajectory(q, grip)
        if len(q) != episode.horizon + 1:
            raise ValueError(f"a stacking rollout needs horizon + 1 = {episode.horizon + 1} rows, got {len(q)}")
        goals = np.asarray(episode.info["goals"], float)
        switches = set(episode.info["switch_steps"])
        with fresh_world() as world:
            blocks = [world.spawn(PICK_XY, 0)]

            def spawn(t: int) -> None:
                if t in switches:
                    body = world.spawn_pick_block()
                    if body is not None:
                        blocks.append(body)

            world.scene.play(q, grip, STEP_SECONDS, on_step=spawn)
            world.hold(q[-1], float(grip[-1]), SETTLE_SECONDS)
            states = [world.state(b) for b in blocks]
            touched = any(world.robot_touches(b) for b in blocks)
        # level k is built when some block rests there (bottom at level k, within XY_TOL of the axis)
        placed = [any(rests_at(s, g, XY_TOL, Z_TOL, MAX_TILT) for s in states) for g in goals]
        nearest = [min(float(np.linalg.norm(s.bottom - g)) for s in states) for g in goals]
        built = int(np.argmin(placed)) if not all(placed) else len(goals)
        return {"success": float(all(placed) and len(states) == 3 and not touched and grip[-1] < 0.5),
                "blocks_in_tower": float(built), "n_blocks": float(len(states)),
                "final_distance": float(np.mean(nearest))}
