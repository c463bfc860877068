"""Pieces shared by the IK experts: smooth time profiles, tool-down Cartesian
paths solved with envs.ik, joint-velocity checks, and a per-process physics scene.

Every expert in this package moves the tool tip along a Cartesian path with the
tool axis pointing down (at the table), solved waypoint by waypoint and
warm-started from the previous waypoint (envs.ik.solve_path).
"""

from __future__ import annotations

import os

import numpy as np
import torch

from envs.ik import DOWN, solve_ik, solve_path
from envs.kinematics import default_kinematics
from envs.robot import LIMITS
from envs.sim import Scene


def min_jerk(n: int) -> np.ndarray:
    """Minimum-jerk progress s(t) in [0, 1] at n+1 evenly spaced times (zero
    velocity and acceleration at both ends)."""
    tau = np.linspace(0.0, 1.0, n + 1)
    return 10 * tau**3 - 15 * tau**4 + 6 * tau**5


def line_paths(start: np.ndarray, goal: np.ndarray, steps: np.ndarray, length: int) -> np.ndarray:
    """Straight tip paths (B, length+1, 3) from start (B, 3) to goal (B, 3), each
    with a minimum-jerk profile over its own number of steps, then held at its goal."""
    B = len(start)
    out = np.empty((B, length + 1, 3))
    for b in range(B):
        s = np.ones(length + 1)
        s[: steps[b] + 1] = min_jerk(int(steps[b]))
        out[b] = start[b] + s[:, None] * (goal[b] - start[b])
    return out


def solve_tool_down_path(path: np.ndarray, q_start: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Joint paths (B, T, 7) for tip paths (B, T, 3) with the tool pointing down,
    warm-started from q_start (B, 7). Returns (q, converged (B,), worst position error (B,))."""
    kin = default_kinematics(torch.float64)
    res = solve_path(torch.as_tensor(path, dtype=torch.float64), torch.as_tensor(q_start, dtype=torch.float64),
                     tool_axis=DOWN, kin=kin)
    return res.q.numpy(), res.converged.numpy(), res.pos_err.numpy()


def tool_down_at(tip: np.ndarray, q_near: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Configurations (B, 7) near q_near (B, 7) with the tip at `tip` (B, 3) and the
    tool pointing down; also whether each converged."""
    kin = default_kinematics(torch.float64)
    res = solve_ik(torch.as_tensor(tip, dtype=torch.float64), torch.as_tensor(q_near, dtype=torch.float64),
                   tool_axis=DOWN, kin=kin, iters=300)
    return res.q.numpy(), res.converged.numpy()


def velocity_ratio(q: np.ndarray, step_seconds: float) -> np.ndarray:
    """Peak joint speed as a fraction of the URDF velocity limit, per path: q (..., T+1, 7) -> (...)."""
    dq = np.abs(np.diff(q, axis=-2)) / step_seconds
    return (dq / LIMITS.velocity).max(axis=(-2, -1))


def check_trajectory(q: np.ndarray, length: int | None = None) -> np.ndarray:
    """Validate a joint trajectory (T+1, 7) given to a task's evaluate; returns it as float64."""
    q = np.asarray(q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 7 or len(q) < 2:
        raise ValueError(f"expected a joint trajectory of shape (T+1, 7) with T >= 1, got {q.shape}")
    if not np.isfinite(q).all():
        raise ValueError("joint trajectory contains NaN or inf")
    if length is not None and len(q) != length:
        raise ValueError(f"expected {length} rows (horizon + 1), got {len(q)}")
    return q


_SCENE: tuple[int, Scene] | None = None


def physics_scene() -> Scene:
    """A table scene reused within this process (a forked worker gets its own:
    pybullet clients do not survive a fork)."""
    global _SCENE
    if _SCENE is None or _SCENE[0] != os.getpid():
        _SCENE = (os.getpid(), Scene(table=True))
    return _SCENE[1]
