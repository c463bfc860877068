"""Pick-and-place, stacking and changing-goal pick-and-place on one dataset.

One model serves all three: it is trained on the "pick-place" demonstrations.
Positions are in the base frame (m); the table top is at z = TABLE_TOP_Z = -0.15.

Scene (envs.blocks): 4 cm cubes of 50 g appear one at a time at PICK_XY = (0.55, -0.20),
resting on the table. The goal psi = (x, y, z) is where the placed block's BOTTOM face
must end: z = TABLE_TOP_Z + level * 0.04 (level 0 on the table, 1 and 2 on a tower).
phi = tip - goal (the grasped block's bottom is 3 cm below the tip).

Distributions (documented choices):
- start: q0 = NEUTRAL_Q + U(-0.1, 0.1) rad per joint, clipped to the limits, kept when
  the tip lies in START_BOX (at least 12 cm above the table, clear of the blocks).
- goal xy uniform in GOAL_REGION (x 0.50..0.75, y -0.05..0.25; at least 15 cm from
  PICK_XY); level uniform in {0, 1, 2}. A level-L pick-place episode (and its demo
  replay) starts with L support blocks already stacked at the goal xy.
- demo length T uniform in 166..170 steps of 0.1 s.

Expert (Cartesian min-jerk segments, tool pointing down with a fixed yaw so that the
fingers close along the base x axis on the block's faces; full-frame IK per waypoint):
  approach (T - 124 steps, to HOVER above the block; the orientation slerps from the
  start's), descend 20 (tip 3 cm above the block bottom), close 8, lift 20 (to HOVER),
  carry 36 (to HOVER above the goal), place 20 (tip at goal + 3 cm), release 8,
  retreat 12 (10 cm up). The grip channel is 1 from the first close row to the last
  place row. Every demo is replayed in physics and kept only if it succeeds;
  failures (IK or physics) are resampled and counted in meta["rejections"].

Success (physics, after the trajectory and 1 s of settling with the last command held):
pick-place: the block's bottom is within 2 cm (xy) and 1 cm (z) of the goal, upright
(tilt < 0.2 rad), the last grip command is open, no finger touches it and the tip is at
least 6 cm from its centre. final_distance = |block bottom - goal| (m).

stack: three consecutive pick-place sub-episodes of SUB_HORIZON = 170 steps each
(horizon 510) at one random xy with levels 0, 1, 2: psi rows k*170 .. (k+1)*170 - 1
ask for level k (the last row too for level 2); the model starts afresh at each sub-episode
(info["restart_steps"]: LSTM state reset, an episode start from the current q). A new block appears at the pick position
right after steps 170 and 340 (unless an unpicked block still occupies it); placed blocks
stay. Success: after 1 s of settling, three upright blocks stand as a tower, each within
2 cm (xy) of the tower axis and 1 cm (z) of its level, untouched by the gripper.

pick-place-changing-goal: level-0 goal, then at switch_step (the first step after the
expert's grasp closes: approach + descend + close = 74 for T = 170) psi switches to
new_goal (level 0, at least 10 cm from goal); horizon 255 (1.5x the longest demo);
success is judged at new_goal. `expert_after_switch` gives the expert's direct
trajectory to the new goal from any configuration at the switch (block in hand).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp
from tqdm import tqdm

from envs.blocks import BLOCK_FRICTION, BLOCK_MASS, BLOCK_SIZE, FINGER_FRICTION, PICK_XY, BlockWorld, level_z, rests_at
from envs.ik import solve_ik
from envs.kinematics import default_kinematics
from envs.robot import LIMITS, NEUTRAL_Q
from envs.sim import GRIPPER_FORCE, TABLE_TOP_Z
from envs.tasks.base import Demos, Episode, StateLayout, Task, register
from envs.tasks.expert import check_trajectory, min_jerk, velocity_ratio

log = logging.getLogger(__name__)

STEP_SECONDS = 0.1
START_JOINT_RANGE = 0.1  # rad, half-width of the start range around NEUTRAL_Q (why 0.1: see envs/tasks/reacher.py)
RETREAT_STARTS = 0.0  # fraction of starts poised where a previous place ended (see sample_starts)
START_BOX = ((0.30, 0.80), (-0.15, 0.45), (TABLE_TOP_Z + 0.12, 0.35))  # tip at the start (m)
GOAL_REGION = ((0.50, 0.75), (-0.05, 0.25))  # goal xy ranges (m)
LEVELS = (0, 1, 2)
MIN_GOAL_SWITCH = 0.10  # m between goal and new_goal (changing goal)
GRASP_HEIGHT = 0.03  # tip above the block's bottom when grasping/placing (pads end 5 mm above it)
HOVER_Z = TABLE_TOP_Z + 0.20  # tip height when approaching and carrying
RETREAT = 0.10  # m straight up after releasing
SEGMENTS = {"descend": 20, "close": 8, "lift": 20, "carry": 36, "place": 20, "release": 8, "retreat": 12}
FIXED_STEPS = sum(SEGMENTS.values())  # 124: the approach takes the rest of a demo
MIN_STEPS, MAX_STEPS = 166, 170
SUB_HORIZON = MAX_STEPS  # steps per stacking sub-episode
SETTLE_SECONDS = 1.0
XY_TOL, Z_TOL, MAX_TILT, AWAY = 0.02, 0.01, 0.2, 0.06
# the grasp frame: tool z down, tool x along base y, tool y (the fingers' axis) along base x
GRASP_ROT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


def _box_lo_hi(box) -> tuple[np.ndarray, np.ndarray]:
    return np.array([b[0] for b in box]), np.array([b[1] for b in box])


# expert -------------------------------------------------------------------------
@dataclass
class Plan:
    """A tip path and gripper commands, one row per step (T+1 rows)."""

    tip: np.ndarray  # (T+1, 3)
    rot: np.ndarray  # (T+1, 3, 3) tool frame
    grip: np.ndarray  # (T+1,)
    marks: dict[str, int]  # row at which each segment ends

    @property
    def steps(self) -> int:
        return len(self.tip) - 1


def compose(tip0: np.ndarray, rot0: np.ndarray, segments: list[tuple[str, np.ndarray, int, float]]) -> Plan:
    """Chain straight min-jerk segments (name, target tip, steps, grip) from tip0; the
    orientation slerps from rot0 to GRASP_ROT during the first segment, then stays."""
    tips, grips, marks = [np.asarray(tip0, float)], [segments[0][3]], {}
    for name, target, n, grip in segments:
        s = min_jerk(n)[1:, None]
        tips.extend(tips[-1] + s * (np.asarray(target, float) - tips[-1]))
        grips.extend([grip] * n)
        marks[name] = len(tips) - 1
    n0 = segments[0][2]
    slerp = Slerp([0.0, 1.0], Rotation.from_matrix(np.stack([rot0, GRASP_ROT])))
    rot = np.repeat(GRASP_ROT[None], len(tips), axis=0)
    rot[: n0 + 1] = slerp(min_jerk(n0)).as_matrix()
    return Plan(tip=np.array(tips), rot=rot, grip=np.array(grips, float), marks=marks)


def plan_pick_place(tip0, rot0, goal, steps: int) -> Plan:
    """The expert's plan from a start tip pose to placing the pick block's bottom at goal."""
    goal = np.asarray(goal, float)
    pick = np.array([PICK_XY[0], PICK_XY[1], level_z(0) + GRASP_HEIGHT])
    place = goal + [0.0, 0.0, GRASP_HEIGHT]
    up = [0.0, 0.0, HOVER_Z]
    g = SEGMENTS
    return compose(tip0, rot0, [
        ("approach", np.r_[pick[:2], up[2]], steps - FIXED_STEPS, 0.0),
        ("descend", pick, g["descend"], 0.0),
        ("close", pick, g["close"], 1.0),
        ("lift", np.r_[pick[:2], up[2]], g["lift"], 1.0),
        ("carry", np.r_[place[:2], up[2]], g["carry"], 1.0),
        ("place", place, g["place"], 1.0),
        ("release", place, g["release"], 0.0),
        ("retreat", place + [0.0, 0.0, RETREAT], g["retreat"], 0.0),
    ])


def plan_after_grasp(tip0, rot0, goal) -> Plan:
    """The expert's plan from a configuration holding the block: lift, carry, place at goal."""
    goal = np.asarray(goal, float)
    place = goal + [0.0, 0.0, GRASP_HEIGHT]
    tip0 = np.asarray(tip0, float)
    g = SEGMENTS
    return compose(tip0, rot0, [
        ("lift", np.r_[tip0[:2], max(HOVER_Z, tip0[2])], g["lift"], 1.0),
        ("carry", np.r_[place[:2], max(HOVER_Z, tip0[2])], g["carry"], 1.0),
        ("place", place, g["place"], 1.0),
        ("release", place, g["release"], 0.0),
        ("retreat", place + [0.0, 0.0, RETREAT], g["retreat"], 0.0),
    ])


def tip_poses(q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    kin = default_kinematics(torch.float64)
    with torch.no_grad():
        poses = kin.forward(torch.as_tensor(q, dtype=torch.float64))
    return poses.tip_pos.numpy(), poses.tip_rot.numpy()


def solve_plans(plans: list[Plan], q0: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Joint paths (B, T_max+1, 7) for plans starting at q0 (B, 7), solved waypoint by
    waypoint with full-frame IK warm-started from the previous row (rows past a plan's
    end repeat its last row). ok (B,): every waypoint converged and joint speeds stay
    under the URDF velocity limits."""
    kin = default_kinematics(torch.float64)
    B, T = len(plans), max(pl.steps for pl in plans)
    tips = np.stack([np.concatenate([pl.tip, np.repeat(pl.tip[-1:], T - pl.steps, 0)]) for pl in plans])
    rots = np.stack([np.concatenate([pl.rot, np.repeat(pl.rot[-1:], T - pl.steps, 0)]) for pl in plans])
    q = torch.as_tensor(np.asarray(q0, float).reshape(B, 7), dtype=torch.float64)
    rows, ok = [q], torch.ones(B, dtype=torch.bool)
    for t in range(1, T + 1):
        res = solve_ik(torch.as_tensor(tips[:, t]), q, target_rot=torch.as_tensor(rots[:, t]), kin=kin)
        q = res.q
        rows.append(q)
        ok &= res.converged
    qs = torch.stack(rows, dim=1).numpy()
    for b, pl in enumerate(plans):
        qs[b, pl.steps + 1:] = qs[b, pl.steps]
    ok_np = ok.numpy() & LIMITS.contains(qs).all(axis=1) & (velocity_ratio(qs, STEP_SECONDS) <= 1.0)
    return qs, ok_np


def pad_rows(x: np.ndarray, rows: int) -> np.ndarray:
    """Repeat the last row of x until it has `rows` rows."""
    return np.concatenate([x, np.repeat(x[-1:], rows - len(x), axis=0)]) if len(x) < rows else x[:rows]


# physics ------------------------------------------------------------------------
@contextmanager
def fresh_world() -> Iterator[BlockWorld]:
    """A new block scene for one episode (about 30 ms to build). Results then do not
    depend on what ran before: a reused pybullet world keeps solver state that shifts
    final positions by ~1e-6 m from one run to the next."""
    world = BlockWorld()
    try:
        yield world
    finally:
        world.close()


def placed_ok(world: BlockWorld, block: int, goal: np.ndarray) -> tuple[bool, dict[str, float]]:
    st = world.state(block)
    err = st.bottom - goal
    tip_away = float(np.linalg.norm(world.tip_position() - st.centre))
    ok = rests_at(st, goal, XY_TOL, Z_TOL, MAX_TILT) and not world.robot_touches(block) and tip_away >= AWAY
    return ok, {"final_distance": float(np.linalg.norm(err)), "xy_error": float(np.hypot(*err[:2])),
                "z_error": float(err[2]), "tip_to_block": tip_away}


def run_pick_place(q: np.ndarray, grip: np.ndarray, goal: np.ndarray, level: int) -> dict[str, float]:
    """Play a pick-place trajectory in physics: L support blocks at the goal xy, one block
    at the pick position; then settle and check the placed block."""
    with fresh_world() as world:
        for lv in range(level):
            world.spawn(goal[:2], lv)
        block = world.spawn(PICK_XY, 0)
        world.scene.play(q, grip, STEP_SECONDS)
        world.hold(q[-1], float(grip[-1]), SETTLE_SECONDS)
        ok, metrics = placed_ok(world, block, goal)
    return {"success": float(ok and grip[-1] < 0.5), **metrics}


def retreat_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Configurations (n, 7) as after a place: the tip RETREAT above a random goal of a random
    level, in the grasp frame (full-frame IK from NEUTRAL_Q); unconverged draws are redrawn."""
    kin = default_kinematics(torch.float64)
    out: list[np.ndarray] = []
    while len(out) < n:
        goals = _sample_goals(rng, n)
        tip = goals + [0.0, 0.0, GRASP_HEIGHT + RETREAT]
        res = solve_ik(torch.as_tensor(tip), torch.as_tensor(np.repeat(NEUTRAL_Q[None], n, 0)),
                       target_rot=torch.as_tensor(np.repeat(GRASP_ROT[None], n, 0)), kin=kin, iters=300)
        q = res.q.numpy()
        out.extend(q[res.converged.numpy() & LIMITS.contains(q)])
    return np.array(out[:n])


def _sample_goals(rng: np.random.Generator, n: int, levels=LEVELS) -> np.ndarray:
    xy = _sample_goal_xy(rng, n)
    lv = rng.choice(np.asarray(levels), size=n)
    return np.column_stack([xy, [level_z(v) for v in lv]])


def _sample_goal_xy(rng: np.random.Generator, n: int) -> np.ndarray:
    lo, hi = _box_lo_hi(GOAL_REGION)
    return rng.uniform(lo, hi, size=(n, 2))


@register
class PickPlace(Task):
    name = "pick-place"
    model_task = "pick-place"
    step_seconds = STEP_SECONDS
    layout = StateLayout(
        phi_dim=3, psi_dim=3, gripper=True,
        phi_names=("tip_minus_goal_x", "tip_minus_goal_y", "tip_minus_goal_z"),
        psi_names=("goal_x", "goal_y", "goal_z"),
    )

    def __init__(self, n_demos: int = 150, min_steps: int = MIN_STEPS, max_steps: int = MAX_STEPS,
                 retreat_starts: float = RETREAT_STARTS):
        if n_demos < 1:
            raise ValueError(f"n_demos must be >= 1, got {n_demos}")
        if not FIXED_STEPS + 10 <= min_steps <= max_steps:
            raise ValueError(f"need {FIXED_STEPS + 10} <= min_steps <= max_steps, got {min_steps}, {max_steps}")
        if not 0.0 <= retreat_starts <= 1.0:
            raise ValueError(f"retreat_starts must be a fraction in [0, 1], got {retreat_starts}")
        self.n_demos, self.min_steps, self.max_steps = n_demos, min_steps, max_steps
        self.retreat_starts = float(retreat_starts)

    def config(self) -> dict[str, Any]:
        return {
            "task": "pick-place", "n_demos": self.n_demos, "min_steps": self.min_steps,
            "max_steps": self.max_steps, "step_seconds": STEP_SECONDS, "start_joint_range": START_JOINT_RANGE,
            "start_box": START_BOX, "goal_region": GOAL_REGION, "levels": LEVELS, "pick_xy": PICK_XY,
            "block_size": BLOCK_SIZE, "block_mass": BLOCK_MASS, "block_friction": BLOCK_FRICTION,
            "finger_friction": FINGER_FRICTION, "gripper_force": GRIPPER_FORCE, "grasp_height": GRASP_HEIGHT,
            "hover_z": HOVER_Z, "retreat": RETREAT, "segments": SEGMENTS, "settle_seconds": SETTLE_SECONDS,
            **({"retreat_starts": self.retreat_starts} if self.retreat_starts else {}),
            "tolerances": {"xy": XY_TOL, "z": Z_TOL, "tilt": MAX_TILT, "away": AWAY},
            "expert": "min-jerk Cartesian segments, full-frame IK, replayed in physics",
        }

    def phi(self, tip_pos, psi):
        return tip_pos - psi

    # sampling ----------------------------------------------------------------
    def sample_starts(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n start configurations (n, 7): around NEUTRAL_Q with the tip in START_BOX, or, for a
        `retreat_starts` fraction of them, poised where a place ends (tool down in the grasp frame,
        RETREAT above a random goal of a random level) -- where each next block of a stack starts."""
        if not self.retreat_starts:
            return self._neutral_starts(rng, n)
        retreat = rng.random(n) < self.retreat_starts
        out = self._neutral_starts(rng, n)
        out[retreat] = retreat_poses(rng, int(retreat.sum()))
        return out

    def _neutral_starts(self, rng: np.random.Generator, n: int) -> np.ndarray:
        lo, hi = _box_lo_hi(START_BOX)
        out: list[np.ndarray] = []
        while len(out) < n:
            q = LIMITS.clip(NEUTRAL_Q + rng.uniform(-START_JOINT_RANGE, START_JOINT_RANGE, size=(n, 7)))
            tip, _ = tip_poses(q)
            out.extend(q[np.all((tip >= lo) & (tip <= hi), axis=1)])
        return np.array(out[:n])

    def sample_goals(self, rng: np.random.Generator, n: int, levels=LEVELS) -> np.ndarray:
        """Goals (n, 3): xy uniform in GOAL_REGION, z of a level drawn from `levels`."""
        return _sample_goals(rng, n, levels)

    # expert ------------------------------------------------------------------
    def expert(self, q0: np.ndarray, goals: np.ndarray, steps: np.ndarray) -> tuple[np.ndarray, np.ndarray, list[Plan]]:
        """Expert joint paths (B, max(steps)+1, 7) from q0 (B, 7) to goals (B, 3), whether
        IK succeeded (B,), and the plans (gripper commands in plan.grip)."""
        tip0, rot0 = tip_poses(q0)
        plans = [plan_pick_place(tip0[b], rot0[b], goals[b], int(steps[b])) for b in range(len(q0))]
        q, ok = solve_plans(plans, q0)
        return q, ok, plans

    def expert_trajectory(self, q_start: np.ndarray, goal: np.ndarray, steps: int | None = None
                          ) -> tuple[np.ndarray, np.ndarray]:
        """The expert's q (T+1, 7) and grip (T+1,) from q_start to placing at goal."""
        q, ok, plans = self.expert(np.asarray(q_start, float)[None], np.asarray(goal, float)[None],
                                   np.array([steps or self.max_steps]))
        if not ok[0]:
            log.warning("expert IK did not converge everywhere from %s to %s", np.round(q_start, 3), goal)
        return q[0], plans[0].grip

    # demonstrations ------------------------------------------------------------
    def demos(self, seed: int = 0) -> Demos:
        """IK demonstrations, each replayed in physics; failures are resampled and counted.
        meta: expert_success (1.0: every kept demo succeeded in physics), rejections
        ({"ik": n, "physics": n}), first_try_success, ik_seconds, physics_seconds."""
        rng = np.random.default_rng(seed)
        accepted: list[tuple[np.ndarray, np.ndarray, np.ndarray, int]] = []
        rejections = {"ik": 0, "physics": 0}
        seconds = {"ik": 0.0, "physics": 0.0}
        while len(accepted) < self.n_demos:
            need = self.n_demos - len(accepted)
            q0 = self.sample_starts(rng, need)
            goals = self.sample_goals(rng, need)
            steps = rng.integers(self.min_steps, self.max_steps + 1, size=need)
            t0 = time.perf_counter()
            q, ok, plans = self.expert(q0, goals, steps)
            t1 = time.perf_counter()
            for b in tqdm(range(need), desc=f"{self.name} demos: physics replay", disable=None, leave=False):
                if not ok[b]:
                    rejections["ik"] += 1
                    continue
                path = q[b, : steps[b] + 1]
                if run_pick_place(path, plans[b].grip, goals[b], _level_of(goals[b]))["success"] < 1.0:
                    rejections["physics"] += 1
                    continue
                accepted.append((path, plans[b].grip, goals[b], int(steps[b])))
            seconds["ik"] += t1 - t0
            seconds["physics"] += time.perf_counter() - t1
        if sum(rejections.values()):
            log.info("%s demos: resampled %s", self.name, rejections)
        lengths = np.array([a[3] for a in accepted])
        T = int(lengths.max())
        qs = np.stack([pad_rows(a[0], T + 1) for a in accepted])
        grips = np.stack([pad_rows(a[1], T + 1) for a in accepted])
        psi = np.repeat(np.stack([a[2] for a in accepted])[:, None], T + 1, axis=1)
        meta = {"rejections": rejections, "expert_success": 1.0, "replayed_in_physics": len(accepted),
                "first_try_success": len(accepted) / (len(accepted) + sum(rejections.values())),
                "ik_seconds": seconds["ik"], "physics_seconds": seconds["physics"]}
        return Demos(q=qs, grip=grips, psi=psi, lengths=lengths, meta=meta)

    # evaluation --------------------------------------------------------------
    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, n)
        H = self.max_steps
        return [Episode(q0=q0[i], psi=np.repeat(goals[i][None], H + 1, axis=0), horizon=H,
                        info={"goal": goals[i].tolist(), "level": _level_of(goals[i])}) for i in range(n)]

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float:
        """Closest approach of the tip to where it must release the block at the (last) goal."""
        place = np.asarray(episode.psi[-1], float) + [0.0, 0.0, GRASP_HEIGHT]
        return float(np.linalg.norm(tip - place, axis=-1).min())

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        """Metrics: success, final_distance (|block bottom - goal|, m), xy_error, z_error (m),
        tip_to_block (m). The goal is info["goal"], else the episode's last psi row."""
        q, grip = _check(q, grip)
        goal = np.asarray(episode.info.get("goal", episode.psi[-1]), float)
        return run_pick_place(q, grip, goal, int(episode.info.get("level", _level_of(goal))))


def _level_of(goal: np.ndarray) -> int:
    return int(round((float(goal[2]) - TABLE_TOP_Z) / BLOCK_SIZE))


def _check(q, grip) -> tuple[np.ndarray, np.ndarray]:
    q = check_trajectory(q)
    if grip is None:
        raise ValueError("pick-and-place needs a gripper command per row, got None")
    grip = np.asarray(grip, dtype=float).reshape(-1)
    if grip.shape != (len(q),) or not np.isfinite(grip).all():
        raise ValueError(f"expected a finite gripper command of shape ({len(q)},), got {grip.shape}")
    return q, grip


@register
class Stack(PickPlace):
    """Three pick-place sub-episodes of SUB_HORIZON steps at one xy, levels 0, 1, 2."""

    name = "stack"
    model_task = "pick-place"

    @property
    def horizon(self) -> int:
        return 3 * SUB_HORIZON

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        xy = _sample_goal_xy(rng, n)
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

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        """Metrics: success, blocks_in_tower (levels built from the bottom up), n_blocks
        (blocks that appeared), final_distance (mean over levels of the distance from the
        level's goal to the nearest block bottom, m)."""
        q, grip = _check(q, grip)
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


@register
class PickPlaceChangingGoal(PickPlace):
    """Pick-and-place whose goal switches to a new one right after the grasp."""

    name = "pick-place-changing-goal"
    model_task = "pick-place"

    @property
    def horizon(self) -> int:
        return int(round(1.5 * self.max_steps))

    @property
    def switch_step(self) -> int:
        """First row after the expert's grasp has closed (for a demo of max_steps)."""
        return self.max_steps - FIXED_STEPS + SEGMENTS["descend"] + SEGMENTS["close"]

    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, n, levels=(0,))
        new_goals = self.sample_goals(rng, n, levels=(0,))
        while (near := np.hypot(*(new_goals - goals)[:, :2].T) < MIN_GOAL_SWITCH).any():
            new_goals[near] = self.sample_goals(rng, int(near.sum()), levels=(0,))
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

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q, grip = _check(q, grip)
        return run_pick_place(q, grip, np.asarray(episode.info["new_goal"], float), 0)
