"""Pick-and-place; stacking (envs/tasks/stack.py) and changing-goal pick-and-place
(envs/tasks/pickplace_changing_goal.py) are evaluated with the model trained on its
demonstrations. The expert's plans and IK: envs/tasks/pickplace_expert.py.
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
- demo length T uniform in 166..170 steps of 0.1 s. Every demo is replayed in physics
  and kept only if it succeeds; failures (IK or physics) are resampled and counted in
  meta["rejections"].

Training-data levers (not the paper's protocol; off by default, so the headline's datasets stay as
they are): retreat_starts (see sample_starts) and goal_switches: that fraction of the demonstrations
switches goal as the changing-goal episodes do (envs/tasks/pickplace_changing_goal.py), at a step
drawn from the first row after the grasp has closed (where the evaluation switches) to SWITCH_LATE
steps into the lift: both goals on the table, the new one at least MIN_GOAL_SWITCH from the first,
psi the new goal from the switch on, and the expert's plan from the arm at the switch, block in
hand, to placing at the new goal (judged there in the physics replay).

Success (physics, after the trajectory and 1 s of settling with the last command held):
the block's bottom is within 2 cm (xy) and 1 cm (z) of the goal, upright (tilt < 0.2
rad), the last grip command is open, no finger touches it and the tip is at least 6 cm
from its centre. final_distance = |block bottom - goal| (m). Each episode records `placed` (the
block judged alone, whatever the last grip command) and `success_strict` (all of the above);
`success` holds the one eval.success names (SUCCESS_CRITERIA; "strict" by default, as before).
"""

from __future__ import annotations

import logging
import time
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from typing import Any

import numpy as np
import torch
from tqdm import tqdm

from envs.blocks import BLOCK_FRICTION, BLOCK_MASS, BLOCK_SIZE, FINGER_FRICTION, PICK_XY, BlockWorld, level_z, rests_at
from envs.ik import solve_ik
from envs.kinematics import default_kinematics
from envs.robot import LIMITS, NEUTRAL_Q
from envs.sim import GRIPPER_FORCE, TABLE_TOP_Z
from envs.tasks.base import Demos, Episode, StateLayout, Task
from envs.tasks.expert import check_trajectory
from envs.tasks.pickplace_expert import (  # noqa: F401  (GRASP_ROT, pad_rows, ...: the pick-place API)
    FIXED_STEPS,
    GRASP_HEIGHT,
    GRASP_ROT,
    HOVER_Z,
    RETREAT,
    SEGMENTS,
    STEP_SECONDS,
    Plan,
    pad_rows,
    plan_after_grasp,
    plan_pick_place,
    solve_plans,
    tip_poses,
)
from envs.tasks.registry import register

log = logging.getLogger(__name__)

START_JOINT_RANGE = 0.1  # rad, half-width of the start range around NEUTRAL_Q (why 0.1: see envs/tasks/reacher.py)
RETREAT_STARTS = 0.0  # fraction of starts poised where a previous place ended (see sample_starts)
SWITCH_LATE = 10  # steps into the lift at which a goal-switch demonstration may still switch
MIN_GOAL_SWITCH = 0.10  # m between a goal and the goal it switches to
START_BOX = ((0.30, 0.80), (-0.15, 0.45), (TABLE_TOP_Z + 0.12, 0.35))  # tip at the start (m)
GOAL_REGION = ((0.50, 0.75), (-0.05, 0.25))  # goal xy ranges (m)
LEVELS = (0, 1, 2)
MIN_STEPS, MAX_STEPS = 166, 170
SETTLE_SECONDS = 1.0
XY_TOL, Z_TOL, MAX_TILT, AWAY = 0.02, 0.01, 0.2, 0.06
SUCCESS_CRITERIA = ("strict", "placed")  # what `success` holds: success_strict or placed (run_pick_place)


def _box_lo_hi(box) -> tuple[np.ndarray, np.ndarray]:
    return np.array([b[0] for b in box]), np.array([b[1] for b in box])


# physics ------------------------------------------------------------------------
@contextmanager
def fresh_world() -> Iterator[BlockWorld]:
    """A new block scene for one episode (about 10 ms to build, 1-3 % of its physics). Results then do not
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
    touching = world.robot_touches(block)
    ok = rests_at(st, goal, XY_TOL, Z_TOL, MAX_TILT) and not touching and tip_away >= AWAY
    return ok, {"final_distance": float(np.linalg.norm(err)), "xy_error": float(np.hypot(*err[:2])),
                "z_error": float(err[2]), "tip_to_block": tip_away, "tilt": st.tilt, "touching": float(touching)}


def run_pick_place(q: np.ndarray, grip: np.ndarray, goal: np.ndarray, level: int,
                   success: str = "strict") -> dict[str, Any]:
    """Play a pick-place trajectory in physics: L support blocks at the goal xy, one block
    at the pick position; then settle and check the placed block. `placed`: the block at the
    goal within the tolerances, upright, untouched and the tip away (placed_ok, after the
    settling); `success_strict`: placed and the last grip command open; `success`: the one of
    them the criterion `success` (SUCCESS_CRITERIA) names."""
    with fresh_world() as world:
        for lv in range(level):
            world.spawn(goal[:2], lv)
        block = world.spawn(PICK_XY, 0)
        world.scene.play(q, grip, STEP_SECONDS)
        world.hold(q[-1], float(grip[-1]), SETTLE_SECONDS)
        ok, metrics = placed_ok(world, block, goal)
    closed = np.asarray(grip) >= 0.5
    grip_closed = float(closed[-1])  # the last grip command: a place ends with the gripper open
    strict = float(ok and not grip_closed)
    # the rows the command closed at; a demonstration closes once (the grasp): more mean it shut again after opening
    steps = tuple(int(t) for t in np.flatnonzero(np.r_[closed[0], closed[1:] & ~closed[:-1]]))
    return {"success": strict if success == "strict" else float(ok), "success_strict": strict, "placed": float(ok),
            **metrics, "grip_closed": grip_closed, "grip_closes": float(len(steps)), "grip_close_steps": steps}



def retreat_poses(rng: np.random.Generator, n: int) -> np.ndarray:
    """Configurations (n, 7) as after a place: the tip RETREAT above a random goal of a random
    level, in the grasp frame (full-frame IK from NEUTRAL_Q); unconverged draws are redrawn."""
    kin = default_kinematics(torch.float64)
    out: list[np.ndarray] = []
    while len(out) < n:
        goals = sample_goals_xyz(rng, n)
        tip = goals + [0.0, 0.0, GRASP_HEIGHT + RETREAT]
        res = solve_ik(torch.as_tensor(tip), torch.as_tensor(np.repeat(NEUTRAL_Q[None], n, 0)),
                       target_rot=torch.as_tensor(np.repeat(GRASP_ROT[None], n, 0)), kin=kin, iters=300)
        q = res.q.numpy()
        out.extend(q[res.converged.numpy() & LIMITS.contains(q)])
    return np.array(out[:n])


def sample_goals_xyz(rng: np.random.Generator, n: int, levels=LEVELS) -> np.ndarray:
    xy = sample_goal_xy(rng, n)
    lv = rng.choice(np.asarray(levels), size=n)
    return np.column_stack([xy, [level_z(v) for v in lv]])


def sample_goal_xy(rng: np.random.Generator, n: int) -> np.ndarray:
    lo, hi = _box_lo_hi(GOAL_REGION)
    return rng.uniform(lo, hi, size=(n, 2))


@register
class PickPlace(Task):
    """Pick the block at the pick position and place it at a goal (on the table or a tower)."""

    name = "pick-place"
    label = "pick-and-place"
    model_task = "pick-place"
    step_seconds = STEP_SECONDS
    report_rank = 20
    # the start range shapes the evaluation's episodes too; retreat_starts is a training-data lever only
    episode_options = ("start_joint_range", "min_steps", "max_steps")
    block_size = BLOCK_SIZE
    success_criterion = (f"block upright within {XY_TOL * 100:g} cm (xy) and {Z_TOL * 100:g} cm (z) of the goal, "
                         f"released, gripper clear")
    layout = StateLayout(
        phi_dim=3, psi_dim=3, gripper=True,
        phi_names=("tip_minus_goal_x", "tip_minus_goal_y", "tip_minus_goal_z"),
        psi_names=("goal_x", "goal_y", "goal_z"),
    )

    def __init__(self, n_demos: int = 150, min_steps: int = MIN_STEPS, max_steps: int = MAX_STEPS,
                 retreat_starts: float = RETREAT_STARTS, goal_switches: float = 0.0,
                 start_joint_range: float = START_JOINT_RANGE, success: str = "strict"):
        """start_joint_range: half-width (rad) of the uniform start range around NEUTRAL_Q (the
        start-range lever; the tip must still start in START_BOX, so wide ranges are filtered).
        success: what an episode's `success` holds (SUCCESS_CRITERIA; evaluation only, out of config())."""
        if n_demos < 1:
            raise ValueError(f"n_demos must be >= 1, got {n_demos}")
        if not FIXED_STEPS + 10 <= min_steps <= max_steps:
            raise ValueError(f"need {FIXED_STEPS + 10} <= min_steps <= max_steps, got {min_steps}, {max_steps}")
        for name, value in (("retreat_starts", retreat_starts), ("goal_switches", goal_switches)):
            if not 0.0 <= value <= 1.0:
                raise ValueError(f"{name} must be a fraction in [0, 1], got {value}")
        if not 0.0 <= start_joint_range <= np.pi:
            raise ValueError(f"start_joint_range must be in [0, pi] rad, got {start_joint_range}")
        if success not in SUCCESS_CRITERIA:
            raise ValueError(f"success must be one of {', '.join(SUCCESS_CRITERIA)}, got {success!r}")
        self.success = success
        self.start_joint_range = float(start_joint_range)
        self.n_demos, self.min_steps, self.max_steps = n_demos, min_steps, max_steps
        self.retreat_starts, self.goal_switches = float(retreat_starts), float(goal_switches)

    @classmethod
    def eval_options(cls, eval_cfg: Mapping[str, Any]) -> dict[str, Any]:
        """success = the eval section's success criterion (absent: "strict"; the constructor checks it)."""
        return {"success": eval_cfg.get("success", "strict")}

    def config(self) -> dict[str, Any]:
        return {
            "task": "pick-place", "n_demos": self.n_demos, "min_steps": self.min_steps,
            "max_steps": self.max_steps, "step_seconds": STEP_SECONDS, "start_joint_range": self.start_joint_range,
            "start_box": START_BOX, "goal_region": GOAL_REGION, "levels": LEVELS, "pick_xy": PICK_XY,
            "block_size": BLOCK_SIZE, "block_mass": BLOCK_MASS, "block_friction": BLOCK_FRICTION,
            "finger_friction": FINGER_FRICTION, "gripper_force": GRIPPER_FORCE, "grasp_height": GRASP_HEIGHT,
            "hover_z": HOVER_Z, "retreat": RETREAT, "segments": SEGMENTS, "settle_seconds": SETTLE_SECONDS,
            **({"retreat_starts": self.retreat_starts} if self.retreat_starts else {}),
            **({"goal_switches": self.goal_switches, "switch_late": SWITCH_LATE, "min_goal_switch": MIN_GOAL_SWITCH}
               if self.goal_switches else {}),
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
            r = self.start_joint_range
            q = LIMITS.clip(NEUTRAL_Q + rng.uniform(-r, r, size=(n, 7)))
            tip, _ = tip_poses(q)
            out.extend(q[np.all((tip >= lo) & (tip <= hi), axis=1)])
        return np.array(out[:n])

    def sample_goals(self, rng: np.random.Generator, n: int, levels=LEVELS) -> np.ndarray:
        """Goals (n, 3): xy uniform in GOAL_REGION, z of a level drawn from `levels`."""
        return sample_goals_xyz(rng, n, levels)

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
        accepted: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []  # q, grip, psi: one row per step
        rejections = {"ik": 0, "physics": 0}
        seconds = {"ik": 0.0, "physics": 0.0}
        while len(accepted) < self.n_demos:
            need = self.n_demos - len(accepted)
            q0 = self.sample_starts(rng, need)
            goals = self.sample_goals(rng, need)
            steps = rng.integers(self.min_steps, self.max_steps + 1, size=need)
            t0 = time.perf_counter()
            q, ok, plans = self.expert(q0, goals, steps)
            candidates = [(q[b, : steps[b] + 1], plans[b].grip, np.repeat(goals[b][None], steps[b] + 1, axis=0),
                           bool(ok[b])) for b in range(need)]
            if self.goal_switches:  # drawn only then, so that the paper's datasets stay as they were
                candidates = self._switch_some(rng, candidates, steps)
            t1 = time.perf_counter()
            for path, grip, psi, ok_b in tqdm(candidates, desc=f"{self.name} demos: physics replay", disable=None,
                                              leave=False):
                if not ok_b:
                    rejections["ik"] += 1
                    continue
                if run_pick_place(path, grip, psi[-1], level_of(psi[-1]))["success_strict"] < 1.0:
                    rejections["physics"] += 1
                    continue
                accepted.append((path, grip, psi))
            seconds["ik"] += t1 - t0
            seconds["physics"] += time.perf_counter() - t1
        if sum(rejections.values()):
            log.info("%s demos: resampled %s", self.name, rejections)
        lengths = np.array([len(a[0]) - 1 for a in accepted])
        T = int(lengths.max())
        qs, grips, psi = (np.stack([pad_rows(a[i], T + 1) for a in accepted]) for i in range(3))
        meta = {"rejections": rejections, "expert_success": 1.0, "replayed_in_physics": len(accepted),
                "first_try_success": len(accepted) / (len(accepted) + sum(rejections.values())),
                "ik_seconds": seconds["ik"], "physics_seconds": seconds["physics"]}
        if self.goal_switches:
            meta["goal_switches"] = int(sum(bool((a[2] != a[2][:1]).any()) for a in accepted))
        return Demos(q=qs, grip=grips, psi=psi, lengths=lengths, meta=meta)

    def _switch_some(self, rng: np.random.Generator, candidates: list, steps: np.ndarray) -> list:
        """A `goal_switches` fraction of the candidate demonstrations (q, grip, psi, ok) with a goal switch
        (module docstring); the others as they are."""
        chosen = np.flatnonzero(rng.random(len(candidates)) < self.goal_switches)
        if not len(chosen):
            return candidates
        first = np.stack([candidates[b][2][0] for b in chosen])
        first[:, 2] = level_z(0)  # the switch comes before the place: only the goal's xy has been acted on
        new = sample_new_goals(rng, first)
        out = list(candidates)
        for b, goal, new_goal in zip(chosen, first, new, strict=True):
            q, grip, _, ok = candidates[b]
            k = grasp_step(int(steps[b])) + int(rng.integers(0, SWITCH_LATE + 1))
            tip0, rot0 = tip_poses(q[k][None])
            plan = plan_after_grasp(tip0[0], rot0[0], new_goal)
            after, after_ok = solve_plans([plan], q[k][None])
            path = np.concatenate([q[: k + 1], after[0][1:]])
            psi = np.concatenate([np.repeat(goal[None], k, axis=0), np.repeat(new_goal[None], len(path) - k, axis=0)])
            out[b] = (path, np.concatenate([grip[: k + 1], plan.grip[1:]]), psi, ok and bool(after_ok[0]))
        return out

    # evaluation --------------------------------------------------------------
    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0 = self.sample_starts(rng, n)
        goals = self.sample_goals(rng, n)
        H = self.max_steps
        return [Episode(q0=q0[i], psi=np.repeat(goals[i][None], H + 1, axis=0), horizon=H,
                        info={"goal": goals[i].tolist(), "level": level_of(goals[i])}) for i in range(n)]

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, np.ndarray]:
        return self.expert_trajectory(episode.q0, np.asarray(episode.info["goal"]))

    def scene_blocks(self) -> list[tuple[float, float, float]]:
        return [(*PICK_XY, TABLE_TOP_Z)]

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float:
        """Closest approach of the tip to where it must release the block at the (last) goal."""
        place = np.asarray(episode.psi[-1], float) + [0.0, 0.0, GRASP_HEIGHT]
        return float(np.linalg.norm(tip - place, axis=-1).min())

    def evaluate(self, q, grip, episode: Episode) -> dict[str, Any]:
        """Metrics: success (success_strict or placed, as self.success names), success_strict (placed and the
        last grip command open), placed (the block judged alone: at the goal, upright, untouched, the tip away,
        after settling), final_distance (|block bottom - goal|, m), xy_error, z_error (m), tip_to_block (m), tilt
        (rad), touching, grip_closed (the last grip command; 0 or 1), grip_closes (how often the command went from
        open to closed; a demonstration's once) and grip_close_steps (the rows it closed at, a tuple). The goal is
        info["goal"], else the episode's last psi row."""
        q, grip = check_grip_trajectory(q, grip)
        goal = np.asarray(episode.info.get("goal", episode.psi[-1]), float)
        return run_pick_place(q, grip, goal, int(episode.info.get("level", level_of(goal))), self.success)


def grasp_step(steps: int) -> int:
    """The first row after the grasp has closed, in a demonstration of `steps` steps."""
    return steps - FIXED_STEPS + SEGMENTS["descend"] + SEGMENTS["close"]


def sample_new_goals(rng: np.random.Generator, goals: np.ndarray) -> np.ndarray:
    """A table-level goal (n, 3) for each of `goals`, at least MIN_GOAL_SWITCH (xy) from it."""
    new = sample_goals_xyz(rng, len(goals), levels=(0,))
    while (near := np.hypot(*(new - goals)[:, :2].T) < MIN_GOAL_SWITCH).any():
        new[near] = sample_goals_xyz(rng, int(near.sum()), levels=(0,))
    return new


def level_of(goal: np.ndarray) -> int:
    return int(round((float(goal[2]) - TABLE_TOP_Z) / BLOCK_SIZE))


def check_grip_trajectory(q, grip) -> tuple[np.ndarray, np.ndarray]:
    q = check_trajectory(q)
    if grip is None:
        raise ValueError("pick-and-place needs a gripper command per row, got None")
    grip = np.asarray(grip, dtype=float).reshape(-1)
    if grip.shape != (len(q),) or not np.isfinite(grip).all():
        raise ValueError(f"expected a finite gripper command of shape ({len(q)},), got {grip.shape}")
    return q, grip


