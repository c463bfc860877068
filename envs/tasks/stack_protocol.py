"""The stacking evaluation's protocol pieces (envs/tasks/stack.py): what happens between two blocks, and which
check a failed tower fails.

Between the blocks (`Stack(restart=...)`, the study's eval.stack_restart):
- "place_pose": the model restarts where the last place ended (the arm poised over the tower), a pose no
  demonstration starts from.
- "start": the arm is moved by script first, position-controlled with the last grip command held: straight up
  (LIFT_STEPS steps, the tip's orientation kept, to LIFT_CLEARANCE above where it was and at least HOVER_Z),
  then a minimum-jerk joint move (RETURN_STEPS steps) to a start configuration drawn from the task's start
  distribution (the episode's info["restart_q"]), where the model restarts. The rollout's rows stay the model's:
  the row of a restart step holds where the last sub-episode ended, the next row continues from the start
  configuration, and the physics plays the scripted rows in between (`physics_path`). The next block appears
  when the move has ended (under "place_pose": when the sub-episode ends).

A failed tower is put down to its lowest level that does not stand at the end (its block: the k-th, which
sub-episode k places there) and the first of FAILED_CHECKS that block fails (`failed_check`)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from envs.blocks import BlockState, rests_at
from envs.tasks.expert import min_jerk
from envs.tasks.pickplace_expert import HOVER_Z, Plan, solve_plans, tip_poses

RESTARTS = ("place_pose", "start")
LIFT_STEPS = 15  # 1.5 s straight up
RETURN_STEPS = 25  # 2.5 s to the start configuration (a joint move of ~1 rad peaks at ~0.75 rad/s)
LIFT_CLEARANCE = 0.05  # m the tip rises at least
CAME_FOR = 0.02  # m: the tool tip within this of a block's grasp point came for it (reports.analyses.stacking.REACH)
# why a failed tower failed, in the order they are checked; a (B,) 0/1 array "failed_<check>" per episode each.
# never_came: the tool tip (measured) never within CAME_FOR of the block's grasp point during its sub-episode;
# no_block: the block never appeared (the pick position still occupied); not_released: when its sub-episode ended,
# the grip command closed and a finger on it; off_target, height_off, tilted: when its sub-episode ended, its bottom
# more than XY_TOL from the tower axis, more than Z_TOL off its level, or tilted more than MAX_TILT;
# knocked_by_move: at its level when its sub-episode ended, not after the scripted move ("start");
# knocked_down: at its level when its sub-episode ended (and after the move), not at the end;
# touched, grip_closed: every level stands, yet a finger on a block at the end, or the last grip command closed.
FAILED_CHECKS = ("never_came", "no_block", "not_released", "off_target", "height_off", "tilted", "knocked_by_move",
                 "knocked_down", "touched", "grip_closed")


@dataclass
class PhysicsPath:
    """What the physics plays for one stacking episode: rows q (N, 7) and grip (N,), the physics row at which each
    sub-episode starts and ends (`spans`, (start, end) inclusive), and the rows at which each scripted move ends
    (`moved`, one per restart; empty under "place_pose")."""

    q: np.ndarray
    grip: np.ndarray
    spans: list[tuple[int, int]]
    moved: list[int]


def lift_and_return(q_end: np.ndarray, grip: float, q_start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The scripted move after a sub-episode (module docstring): rows (LIFT_STEPS + RETURN_STEPS, 7) from the
    configuration after q_end to q_start (its last row), and the grip command held (same length)."""
    tip, rot = tip_poses(np.asarray(q_end, float)[None])
    top = np.r_[tip[0, :2], max(tip[0, 2] + LIFT_CLEARANCE, HOVER_Z)]
    s = min_jerk(LIFT_STEPS)[:, None]
    plan = Plan(tip=tip[0] + s * (top - tip[0]), rot=np.repeat(rot, LIFT_STEPS + 1, axis=0),
                grip=np.full(LIFT_STEPS + 1, grip), marks={"lift": LIFT_STEPS})
    lift, _ = solve_plans([plan], np.asarray(q_end, float)[None])  # position-controlled: the rows as solved
    q_lift = lift[0, -1]
    ramp = min_jerk(RETURN_STEPS)[1:, None]
    back = q_lift + ramp * (np.asarray(q_start, float) - q_lift)
    rows = np.concatenate([lift[0, 1:], back])
    return rows, np.full(len(rows), grip)


def physics_path(q: np.ndarray, grip: np.ndarray, sub_horizon: int, restart_q: list | None) -> PhysicsPath:
    """The rows the physics plays for a rollout of len(q) rows in sub-episodes of sub_horizon steps; with
    `restart_q` (one start configuration per restart) the scripted moves inserted after each restart step's row."""
    ends = list(range(sub_horizon, len(q) - 1, sub_horizon))  # the restart steps
    if not restart_q:
        spans = [(t - sub_horizon, t) for t in [*ends, len(q) - 1]]
        return PhysicsPath(q, grip, spans, [])
    if len(restart_q) != len(ends):
        raise ValueError(f"{len(restart_q)} restart configurations for {len(ends)} restarts")
    qs, gs, spans, moved, start = [q[: ends[0] + 1]], [grip[: ends[0] + 1]], [(0, ends[0])], [], 0
    for k, (t, q_start) in enumerate(zip(ends, restart_q, strict=True)):
        rows, held = lift_and_return(q[t], float(grip[t]), q_start)
        qs.append(rows)
        gs.append(held)
        start = sum(len(x) for x in qs) - 1  # the move's last row: the start configuration
        moved.append(start)
        stop = ends[k + 1] if k + 1 < len(ends) else len(q) - 1
        qs.append(q[t + 1: stop + 1])
        gs.append(grip[t + 1: stop + 1])
        spans.append((start, start + stop - t))
    return PhysicsPath(np.concatenate(qs), np.concatenate(gs), spans, moved)


def tower_height(states: list[BlockState], goals: np.ndarray, xy_tol: float, z_tol: float, max_tilt: float) -> int:
    """Levels that stand from the bottom up: some block rests at level 0, 1, ... (as the success check reads them)."""
    height = 0
    for goal in goals:
        if not any(rests_at(s, goal, xy_tol, z_tol, max_tilt) for s in states):
            break
        height += 1
    return height


@dataclass
class BlockAtEnd:
    """One block when its sub-episode ended: its state, whether a finger was on it, the grip command then, and
    (for "start") its state after the scripted move that followed (None when there was none)."""

    state: BlockState
    touched: bool
    grip: float
    after_move: BlockState | None = None


def failed_check(level: int | None, came: bool, block: BlockAtEnd | None, goal: np.ndarray, touched_at_end: bool,
                 last_grip: float, tol: tuple[float, float, float]) -> str:
    """Which of FAILED_CHECKS a failed tower fails. level: its lowest level that does not stand at the end (None when
    all stand); came: the tip came for that level's block; block: that block when its sub-episode ended (None: it
    never appeared); goal: the level's goal (bottom centre); tol: (xy, z, tilt) tolerances."""
    xy_tol, z_tol, max_tilt = tol
    if level is None:
        return "touched" if touched_at_end else "grip_closed" if last_grip >= 0.5 else "knocked_down"
    if not came:
        return "never_came"
    if block is None:
        return "no_block"
    if rests_at(block.state, goal, xy_tol, z_tol, max_tilt):
        moved_off = block.after_move is not None and not rests_at(block.after_move, goal, xy_tol, z_tol, max_tilt)
        return "knocked_by_move" if moved_off else "knocked_down"
    if block.grip >= 0.5 and block.touched:
        return "not_released"
    bottom = block.state.bottom
    if np.hypot(*(bottom[:2] - goal[:2])) > xy_tol:
        return "off_target"
    if abs(bottom[2] - goal[2]) > z_tol:
        return "height_off"
    return "tilted"
