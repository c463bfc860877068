"""The pick-and-place expert: Cartesian min-jerk segments with the tool pointing down at a
fixed yaw (the fingers close along the base x axis on the block's faces), solved by
full-frame IK waypoint by waypoint. Shared by pick-place, stacking and changing goals.

Segments of a demo of T steps: approach (T - 124 steps, to HOVER above the block; the
orientation slerps from the start's), descend 20 (tip 3 cm above the block bottom),
close 8, lift 20 (to HOVER), carry 36 (to HOVER above the goal), place 20 (tip at goal
+ 3 cm), release 8, retreat 12 (10 cm up). The grip channel is 1 from the first close row
to the last place row.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
from scipy.spatial.transform import Rotation, Slerp

from envs.blocks import PICK_XY, level_z
from envs.ik import solve_ik
from envs.kinematics import default_kinematics
from envs.robot import LIMITS
from envs.sim import TABLE_TOP_Z
from envs.tasks.expert import min_jerk, velocity_ratio

STEP_SECONDS = 0.1
GRASP_HEIGHT = 0.03  # tip above the block's bottom when grasping/placing (pads end 5 mm above it)
HOVER_Z = TABLE_TOP_Z + 0.20  # tip height when approaching and carrying
RETREAT = 0.10  # m straight up after releasing
SEGMENTS = {"descend": 20, "close": 8, "lift": 20, "carry": 36, "place": 20, "release": 8, "retreat": 12}
FIXED_STEPS = sum(SEGMENTS.values())  # 124: the approach takes the rest of a demo
# the grasp frame: tool z down, tool x along base y, tool y (the fingers' axis) along base x
GRASP_ROT = np.array([[0.0, 1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, -1.0]])


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
