"""Stacking: three pick-and-place sub-episodes at one xy, evaluated with the pick-place model.

Three consecutive pick-place sub-episodes of SUB_HORIZON = 170 steps each (horizon 510)
at one random xy with levels 0, 1, 2: psi rows k*170 .. (k+1)*170 - 1 ask for level k
(the last row too for level 2); the model starts afresh at each sub-episode
(info["restart_steps"]: LSTM state reset, an episode start). Where it starts is the protocol's
choice between the blocks (`restart`, the study's eval.stack_restart; envs/tasks/stack_protocol.py):
"place_pose" (the default) from where the last place ended, "start" from a start configuration drawn
from the task's start distribution (info["restart_q"], seeded by the episode) after a scripted lift
and joint move. A new block appears at the pick position right after steps 170 and 340 (after the
scripted move, under "start"; unless an unpicked block still occupies it); placed blocks stay.
Success: after 1 s of settling, three upright blocks stand as a tower, each within 2 cm (xy) of the
tower axis and 1 cm (z) of its level, untouched by the gripper, the last grip command open. A failed
tower records its lowest level that does not stand and the check its block fails there
(stack_protocol.FAILED_CHECKS).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

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
from envs.tasks.pickplace_expert import GRASP_HEIGHT
from envs.tasks.registry import register
from envs.tasks.stack_protocol import (
    CAME_FOR,
    FAILED_CHECKS,
    RESTARTS,
    BlockAtEnd,
    failed_check,
    physics_path,
    tower_height,
)

SUB_HORIZON = MAX_STEPS  # steps per stacking sub-episode
TOLERANCES = (XY_TOL, Z_TOL, MAX_TILT)


@register
class Stack(PickPlace):
    """Three pick-place sub-episodes of SUB_HORIZON steps at one xy, levels 0, 1, 2."""

    name = "stack"
    label = "stacking"
    model_task = "pick-place"
    report_rank = 21
    success_criterion = "three upright blocks stand as a tower at the goal, untouched by the gripper"

    def __init__(self, *args, restart: str = "place_pose", **kwargs):
        """restart: where the model restarts between the blocks (RESTARTS; module docstring). Evaluation only: it
        stays out of config(), the dataset's cache key."""
        super().__init__(*args, **kwargs)
        if restart not in RESTARTS:
            raise ValueError(f"restart must be one of {', '.join(RESTARTS)}, got {restart!r}")
        self.restart = restart

    @classmethod
    def eval_options(cls, eval_cfg: Mapping[str, Any]) -> dict[str, Any]:
        """restart = the eval section's stack_restart (absent: "place_pose"); a tower has its own success, so
        eval.success does not apply."""
        restart = eval_cfg.get("stack_restart", "place_pose")
        if restart not in RESTARTS:
            raise ValueError(f"eval.stack_restart: {restart!r} is not allowed; allowed: {', '.join(RESTARTS)}")
        return {"restart": restart}

    @property
    def horizon(self) -> int:
        return 3 * SUB_HORIZON

    def episodes(self, n: int, seed: int) -> list[Episode]:
        """Under restart "start", info["restart_q"]: two start configurations per episode, drawn from the task's
        start distribution with a generator of its own seeded by (seed, episode index), so that the episodes' other
        draws are those of "place_pose"."""
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        xy = sample_goal_xy(rng, n)
        H, out = self.horizon, []
        for i in range(n):
            goals = np.array([[*xy[i], level_z(lv)] for lv in LEVELS])
            psi = np.repeat(goals, SUB_HORIZON, axis=0)
            psi = np.concatenate([psi, goals[-1:]])  # the last row keeps level 2
            info = {"tower_xy": xy[i].tolist(), "goals": goals.tolist(),
                    "switch_steps": [SUB_HORIZON, 2 * SUB_HORIZON], "sub_horizon": SUB_HORIZON,
                    # each block is its own pick-and-place: the model restarts at each next block
                    "restart_steps": [SUB_HORIZON, 2 * SUB_HORIZON]}
            if self.restart == "start":
                info["restart_q"] = self.sample_starts(np.random.default_rng([seed, i]), 2).tolist()
            out.append(Episode(q0=q0[i], psi=psi, horizon=H, info=info))
        return out

    def expert_rollout(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        """The expert builds the tower: three pick-place plans, each padded to SUB_HORIZON, each next one from where
        the last ended or, under "start", from the episode's restart configuration."""
        qs, grips, q = [episode.q0[None]], [np.zeros(1)], np.asarray(episode.q0, float)
        starts = episode.info.get("restart_q") or []
        for k, goal in enumerate(episode.info["goals"]):
            if k and starts:
                q = np.asarray(starts[k - 1], float)
            qk, gk = self.expert_trajectory(q, goal)
            qk, gk = pad_rows(qk, SUB_HORIZON + 1), pad_rows(gk, SUB_HORIZON + 1)
            qs.append(qk[1:])
            grips.append(gk[1:])
            q = qk[-1]
        return np.concatenate(qs), np.concatenate(grips)

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        return self.expert_rollout(episode)

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        """Metrics: success, blocks_in_tower (levels built from the bottom up), n_blocks (blocks that appeared),
        final_distance (mean over levels of the distance from the level's goal to the nearest block bottom, m);
        failed_block (the block, 1-3, at the tower's lowest level that does not stand; 0 when stacked) and
        failed_<check> (1 for the check of stack_protocol.FAILED_CHECKS it fails, 0 for the others); under "start"
        only, tower_stood_move_1 / _2 (1 when the tower stands as high after the scripted move after block 1 / 2 as
        when that block's sub-episode ended)."""
        q, grip = check_grip_trajectory(q, grip)
        if len(q) != episode.horizon + 1:
            raise ValueError(f"a stacking rollout needs horizon + 1 = {episode.horizon + 1} rows, got {len(q)}")
        goals = np.asarray(episode.info["goals"], float)
        path = physics_path(q, grip, int(episode.info.get("sub_horizon", SUB_HORIZON)), episode.info.get("restart_q"))
        ends = {end: k for k, (_, end) in enumerate(path.spans)}
        spawn_at = set(path.moved) if path.moved else {end for _, end in path.spans[:-1]}
        ended: dict[int, BlockAtEnd] = {}  # block k when its sub-episode ended
        height_at_end: dict[int, int] = {}  # the tower's height then
        stood: list[float] = []  # per scripted move: the tower as high after it as before
        with fresh_world() as world:
            blocks = [world.spawn(PICK_XY, 0)]

            def height() -> int:
                return tower_height([world.state(b) for b in blocks], goals, *TOLERANCES)

            def on_step(t: int) -> None:  # reads the scene only: the physics steps as without it
                if t in ends:
                    k = ends[t]
                    height_at_end[k] = height()
                    if k < len(blocks):
                        b = blocks[k]
                        ended[k] = BlockAtEnd(world.state(b), world.robot_touches(b), float(path.grip[t]))
                if t in path.moved:
                    k = path.moved.index(t)
                    if k in ended:
                        ended[k].after_move = world.state(blocks[k])
                    stood.append(float(height() >= height_at_end[k]))
                if t in spawn_at:
                    body = world.spawn_pick_block()
                    if body is not None:
                        blocks.append(body)

            playback = world.scene.play(path.q, path.grip, STEP_SECONDS, on_step=on_step)
            world.hold(path.q[-1], float(path.grip[-1]), SETTLE_SECONDS)
            states = [world.state(b) for b in blocks]
            touched = any(world.robot_touches(b) for b in blocks)
        # level k is built when some block rests there (bottom at level k, within XY_TOL of the axis)
        placed = [any(rests_at(s, g, XY_TOL, Z_TOL, MAX_TILT) for s in states) for g in goals]
        nearest = [min(float(np.linalg.norm(s.bottom - g)) for s in states) for g in goals]
        built = int(np.argmin(placed)) if not all(placed) else len(goals)
        success = all(placed) and len(states) == 3 and not touched and grip[-1] < 0.5
        out = {"success": float(success), "blocks_in_tower": float(built), "n_blocks": float(len(states)),
               "final_distance": float(np.mean(nearest))}
        check, out["failed_block"] = "", 0.0
        if not success:
            level = built if built < len(goals) else None  # None: every level stands, the release failed
            k = len(goals) - 1 if level is None else level
            start, end = path.spans[k]
            grasp = np.array([*PICK_XY, level_z(0) + GRASP_HEIGHT])
            came = bool((np.linalg.norm(playback.tip[start: end + 1] - grasp, axis=-1) < CAME_FOR).any())
            check = failed_check(level, came, ended.get(k), goals[k], touched, float(grip[-1]), TOLERANCES)
            out["failed_block"] = float(k + 1)
        out.update({f"failed_{c}": float(c == check) for c in FAILED_CHECKS})
        for m, value in enumerate(stood):  # under "start" only: "place_pose" moves nothing
            out[f"tower_stood_move_{m + 1}"] = value
        return out
