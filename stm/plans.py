"""Stand-in joint plans for the post-processing studies: straight tip paths to four
reacher goals, solved with the IK expert (envs.ik). The smoothing and IDM studies
take any plan (B, T+1, 7); these are used when no trained STM is at hand.
"""

from __future__ import annotations

import numpy as np
import torch

from envs.ik import solve_path
from envs.kinematics import default_kinematics
from envs.robot import NEUTRAL_Q

# Four reacher goals in the base frame (m): left/right, near/far, low/high, all
# above the table (top at z = -0.15) and reachable with the tool pointing down.
FOUR_GOALS = np.array([
    [0.70, 0.35, 0.00],
    [0.70, -0.20, 0.00],
    [0.45, 0.45, 0.20],
    [0.55, -0.25, 0.25],
])


def straight_line_plans(goals: np.ndarray = FOUR_GOALS, steps: int = 60, q_start: np.ndarray = NEUTRAL_Q) -> np.ndarray:
    """Joint plans (B, steps+1, 7) whose tip moves on a straight line at constant speed
    from the tip of `q_start` to each goal (row 0 is q_start)."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    kin = default_kinematics(torch.float64)
    goals = torch.as_tensor(np.asarray(goals, dtype=float).reshape(-1, 3))
    q0 = torch.as_tensor(np.asarray(q_start, dtype=float)).expand(len(goals), 7).clone()
    with torch.no_grad():
        start = kin.tip_position(q0)
        s = torch.linspace(0.0, 1.0, steps + 1, dtype=torch.float64)[1:]
        path = start[:, None] + s[None, :, None] * (goals - start)[:, None]
        q = solve_path(path, q0, kin=kin).q
    return torch.cat([q0[:, None], q], dim=1).numpy()


def jittery_skeletons(plans: np.ndarray, seed: int = 0, jitter: float = 0.02, drift: float = 0.05) -> np.ndarray:
    """Plans with STM-like imperfections, for studies run without a trained STM:
    white jitter (std `jitter` rad per joint and step) and a slow random drift
    (std `drift` rad at the end) that also moves the final tip off the goal.
    Row 0 (the measured start) is kept."""
    rng = np.random.default_rng(seed)
    plans = np.asarray(plans, dtype=float)
    B, T1, J = plans.shape
    ramp = np.linspace(0.0, 1.0, T1)[None, :, None]
    noise = jitter * rng.standard_normal((B, T1, J)) + drift * ramp * rng.standard_normal((B, 1, J))
    noise[:, 0] = 0.0
    return plans + noise
