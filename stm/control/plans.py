"""Stand-in joint plans for the post-processing studies: the reacher's IK expert
(straight tool-down tip paths, minimum-jerk timing) from the neutral pose to four
goals. The smoothing and IDM studies take any plan (B, T+1, 7); these are used when
no trained STM is at hand.
"""

from __future__ import annotations

import numpy as np

from envs.robot import NEUTRAL_Q
from envs.tasks.registry import get_task

# Four reacher goals in the base frame (m), spread over the reacher task's goal box
# (envs.tasks.reacher.GOAL_BOX): left/right, near/far, low/high.
FOUR_GOALS = np.array([
    [0.70, 0.35, 0.00],
    [0.70, -0.05, 0.00],
    [0.55, 0.35, 0.15],
    [0.75, 0.05, 0.15],
])


def straight_line_plans(goals: np.ndarray = FOUR_GOALS, steps: int = 60, q_start: np.ndarray = NEUTRAL_Q) -> np.ndarray:
    """The reacher expert's joint plans (B, steps+1, 7) from q_start to each goal:
    the tip moves on a straight line with a minimum-jerk profile, tool down."""
    if steps < 1:
        raise ValueError(f"steps must be >= 1, got {steps}")
    goals = np.asarray(goals, dtype=float).reshape(-1, 3)
    q0 = np.repeat(np.asarray(q_start, dtype=float).reshape(1, 7), len(goals), axis=0)
    q, _, ok = get_task("reacher").expert(q0, goals, np.full(len(goals), steps))
    if not ok.all():
        raise ValueError(f"the IK expert found no valid plan to goals {goals[~ok].tolist()}")
    return q


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


def stm_plans(model, goals: np.ndarray = FOUR_GOALS, horizon: int = 60, q_start: np.ndarray = NEUTRAL_Q,
              task_name: str = "reacher", **generate_kwargs) -> np.ndarray:
    """Skeletons (B, horizon+1, 7) unrolled by a trained reacher STM from q_start to
    each goal (stm.rollout.generate; extra keyword arguments go to it)."""
    from envs.tasks.base import Episode
    from stm.rollout import generate

    goals = np.asarray(goals, dtype=float).reshape(-1, 3)
    q0 = np.asarray(q_start, dtype=float)
    episodes = [Episode(q0=q0, psi=np.repeat(g[None], horizon + 1, axis=0), horizon=horizon, info={"goal": g.tolist()})
                for g in goals]
    return generate(model, get_task(task_name), episodes, **generate_kwargs).q.astype(float)
