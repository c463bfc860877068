"""reacher-obstacle-multimodal: a reacher whose straight path is blocked by a pillar; the
expert passes it on the left or on the right, chosen at random per demonstration.

Why: the paper argues for the MDN head with multimodal demonstrations. Here the two modes
are the expert's coin flip, not a function of the state: psi (the goal) and the scene are
the same for both, so the data are genuinely bimodal given the state, and the average of
the two modes runs into the pillar.

Documented choices (base frame; the table top is at z = -0.15):
- obstacle: a static box pillar, centre (x, y) = OBSTACLE_XY, half widths OBSTACLE_HALF
  (6 cm x 6 cm), from the table top up to z = OBSTACLE_TOP_Z (above every tip path and
  the gripper around it, so it can only be passed at the side). It is in the pybullet scene
  of `evaluate`; any contact of the robot with it fails the episode ("collided").
- start tip uniform in START_REGION (before the pillar in y), goal uniform in GOAL_REGION
  (behind it); a pair is kept only if the straight tip segment passes within BLOCKED m of
  the pillar's axis, so the direct line always hits the pillar. Starts: tool-down IK near
  NEUTRAL_Q (as the reacher's).
- expert: the straight line plus a horizontal bump of DETOUR m * sin(pi s) perpendicular to
  it (s: minimum-jerk progress), on the left (mode 0) or right (mode 1) of the direction of
  travel; modes are a random balanced permutation over the demos, independent of the state.
  Tool down, warm-started IK; steps = 60 + 20 * min(distance / 0.6 m, 1).
- mode of a tip path (`classify`): the side of the pillar's centre on which the path
  crosses the line through the centre perpendicular to start -> goal. Labels are in
  Demos.meta["modes"] for fresh demos; `demo_modes` recomputes them from any demos (the
  dataset cache keeps arrays only).
- evaluate: success = final tip within 5 cm of the goal and no contact with the pillar;
  one-hot mode_left / mode_right / between, where between = the path touched the pillar
  (what an average of the two modes does) or never crossed it.
"""

from __future__ import annotations

import logging
import os
from typing import Any

import numpy as np
import pybullet as p

from envs.kinematics import tip_position_np
from envs.robot import LIMITS, NEUTRAL_Q
from envs.sim import TABLE_TOP_Z, Scene
from envs.tasks._bimodal import BimodalReacher
from envs.tasks.base import Demos, Episode
from envs.tasks.expert import check_trajectory, min_jerk, tool_down_at
from envs.tasks.reacher import SUCCESS_RADIUS
from envs.tasks.registry import register

log = logging.getLogger(__name__)

OBSTACLE_XY = (0.62, 0.15)
OBSTACLE_HALF = (0.03, 0.03)  # m, half widths in x and y
OBSTACLE_TOP_Z = 0.17
START_REGION = ((0.56, 0.68), (-0.10, 0.00), (0.00, 0.10))  # (x, y, z) ranges of the start tip (m)
GOAL_REGION = ((0.56, 0.68), (0.30, 0.40), (0.00, 0.10))
BLOCKED = 0.02  # m: the straight segment passes at most this far from the pillar's axis
DETOUR = 0.17  # m: peak sideways offset of the expert's path
MODES = ("left", "right")  # seen from above, facing the direction of travel


def _horizontal_frame(start: np.ndarray, goal: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit direction of travel (..., 2) and its left normal (..., 2) in the x-y plane."""
    d = goal[..., :2] - start[..., :2]
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    return d, np.stack([-d[..., 1], d[..., 0]], axis=-1)


def classify(tip: np.ndarray, start: np.ndarray, goal: np.ndarray) -> tuple[int, float]:
    """(mode, lateral offset m) of a tip path (T+1, 3): mode 0 left / 1 right of the pillar,
    -1 if the path never crosses the pillar's line; the offset is signed (+ = left)."""
    d, n = _horizontal_frame(np.asarray(start, float), np.asarray(goal, float))
    rel = np.asarray(tip, float)[:, :2] - np.asarray(OBSTACLE_XY)
    along, lateral = rel @ d, rel @ n
    crossing = np.nonzero((along[:-1] < 0) & (along[1:] >= 0))[0]
    if not len(crossing):
        return -1, float("nan")
    i = int(crossing[0])
    w = -along[i] / (along[i + 1] - along[i])
    offset = float(lateral[i] + w * (lateral[i + 1] - lateral[i]))
    return (0 if offset > 0 else 1), offset


def _segment_distance(a: np.ndarray, b: np.ndarray, c: np.ndarray) -> np.ndarray:
    """Horizontal distance of point c (2,) to segments a-b (B, 2)."""
    ab, ac = b - a, c - a
    s = np.clip((ac * ab).sum(-1) / (ab * ab).sum(-1), 0.0, 1.0)
    return np.linalg.norm(a + s[:, None] * ab - c, axis=-1)


class ObstacleScene:
    """The table scene plus the pillar; playback reports contacts with it."""

    def __init__(self):
        self.scene = Scene(table=True)
        hz = (OBSTACLE_TOP_Z - TABLE_TOP_Z) / 2
        self.obstacle = self.scene.add_box((*OBSTACLE_HALF, hz), (*OBSTACLE_XY, TABLE_TOP_Z + hz),
                                           rgba=(0.8, 0.2, 0.2, 1))

    def play(self, q: np.ndarray, step_seconds: float) -> tuple[np.ndarray, bool]:
        """Measured tip path (T+1, 3) and whether the robot touched the pillar."""
        s, touched = self.scene, []

        def contact(_t: int) -> None:
            touched.append(bool(p.getContactPoints(bodyA=s.robot.body, bodyB=self.obstacle,
                                                   physicsClientId=s.client)))

        tip = s.play(q, None, step_seconds, on_step=contact).tip
        return tip, any(touched)


_SCENE: tuple[int, ObstacleScene] | None = None


def obstacle_scene() -> ObstacleScene:
    """One scene per process (pybullet clients do not survive a fork)."""
    global _SCENE
    if _SCENE is None or _SCENE[0] != os.getpid():
        _SCENE = (os.getpid(), ObstacleScene())
    return _SCENE[1]


def _sample(rng: np.random.Generator, box, n: int) -> np.ndarray:
    lo, hi = np.array([b[0] for b in box]), np.array([b[1] for b in box])
    return rng.uniform(lo, hi, size=(n, 3))


@register
class ReacherObstacleMultimodal(BimodalReacher):
    """Reacher around a pillar, passed left or right at random (multimodal demonstrations)."""

    name = "reacher-obstacle-multimodal"
    model_task = "reacher-obstacle-multimodal"
    description = "multimodal: reacher around a pillar, expert passes left or right at random"
    modes = MODES
    label = "reacher around a pillar (multimodal)"
    report_rank = 20
    episode_options = ("min_steps", "max_steps")  # the constructor has no start range
    success_criterion = (f"tool tip within {SUCCESS_RADIUS * 100:g} cm of the goal at the end without touching "
                         "the pillar (physics)")

    def __init__(self, n_demos: int = 60, min_steps: int = 60, max_steps: int = 80):
        super().__init__(n_demos=n_demos, min_steps=min_steps, max_steps=max_steps)

    def config(self) -> dict[str, Any]:
        return {"task": self.name, "n_demos": self.n_demos, "min_steps": self.min_steps,
                "max_steps": self.max_steps, "start_region": START_REGION, "goal_region": GOAL_REGION,
                "obstacle_xy": OBSTACLE_XY, "obstacle_half": OBSTACLE_HALF, "obstacle_top_z": OBSTACLE_TOP_Z,
                "blocked": BLOCKED, "detour": DETOUR, "step_seconds": self.step_seconds,
                "success_radius": SUCCESS_RADIUS, "profile": "min-jerk line + sin bump, tool down",
                "modes": "balanced random permutation"}

    # sampling ----------------------------------------------------------------
    def sample_pairs(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """n tool-down starts (n, 7) and goals (n, 3) whose straight segment hits the pillar."""
        qs: list[np.ndarray] = []
        goals: list[np.ndarray] = []
        while len(qs) < n:
            tips, g = _sample(rng, START_REGION, n), _sample(rng, GOAL_REGION, n)
            blocked = _segment_distance(tips[:, :2], g[:, :2], np.asarray(OBSTACLE_XY)) < BLOCKED
            raw = NEUTRAL_Q + rng.uniform(-0.1, 0.1, size=(n, 7))
            q, ok = tool_down_at(tips, raw)
            ok &= blocked & LIMITS.contains(q)
            qs.extend(q[ok])
            goals.extend(g[ok])
        return np.array(qs[:n]), np.array(goals[:n])

    # expert ------------------------------------------------------------------
    def detour_paths(self, start: np.ndarray, goals: np.ndarray, modes: np.ndarray, steps: np.ndarray,
                     length: int) -> np.ndarray:
        """Tip paths (B, length+1, 3): line + sideways bump (left for mode 0, right for mode 1)."""
        _, n = _horizontal_frame(start, goals)
        sign = np.where(np.asarray(modes) == 0, 1.0, -1.0)
        out = np.empty((len(start), length + 1, 3))
        for b in range(len(start)):
            s = np.ones(length + 1)
            s[: steps[b] + 1] = min_jerk(int(steps[b]))
            bump = DETOUR * np.sin(np.pi * s)
            out[b] = start[b] + s[:, None] * (goals[b] - start[b])
            out[b, :, :2] += sign[b] * bump[:, None] * n[b]
        return out

    def expert(self, q0: np.ndarray, goals: np.ndarray, modes: np.ndarray | None = None,
               steps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Expert joint paths (B, max(steps)+1, 7) from q0 (B, 7) to goals (B, 3) passing on
        the side `modes` (B,) (default: left); also steps (B,) and ok (B,) as Reacher.expert."""
        start = tip_position_np(q0)
        modes = np.zeros(len(q0), int) if modes is None else np.asarray(modes, int)
        if steps is None:
            steps = self.steps_for(np.linalg.norm(goals - start, axis=-1))
        steps = np.asarray(steps, dtype=int)
        return self.solve_tip_paths(q0, self.detour_paths(start, goals, modes, steps, int(steps.max())), steps)

    def replay(self, path: np.ndarray, goal: np.ndarray, mode: int) -> str:
        tip, touched = obstacle_scene().play(path, self.step_seconds)
        if touched:
            return "collision"
        missed = np.linalg.norm(tip[-1] - goal) >= SUCCESS_RADIUS
        return "physics" if missed or classify(tip, tip[0], goal)[0] != mode else ""

    def demo_modes(self, demos: Demos) -> np.ndarray:
        """Mode label (N,) of each demonstration from its kinematic tip path (0 left, 1 right, -1 none)."""
        out = []
        for i, n in enumerate(demos.lengths):
            tip = tip_position_np(demos.q[i, : n + 1])
            out.append(classify(tip, tip[0], demos.psi[i, 0])[0])
        return np.array(out)

    # evaluation --------------------------------------------------------------
    def episodes(self, n: int, seed: int) -> list[Episode]:
        rng = np.random.default_rng(seed)
        q0, goals = self.sample_pairs(rng, n)
        starts = tip_position_np(q0)
        horizon = self.max_steps
        return [Episode(q0=q0[i], psi=np.repeat(goals[i][None], horizon + 1, axis=0), horizon=horizon,
                        info={"goal": goals[i].tolist(), "start_tip": starts[i].tolist(),
                              "obstacle": list(OBSTACLE_XY)}) for i in range(n)]

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q = check_trajectory(q)
        goal = np.asarray(episode.psi[-1])
        tip, touched = obstacle_scene().play(q, self.step_seconds)
        d = float(np.linalg.norm(tip[-1] - goal))
        mode, offset = classify(tip, tip[0], goal)
        between = touched or mode < 0
        return {"success": float(d < SUCCESS_RADIUS and not touched), "final_distance": d,
                "collided": float(touched), "mode_left": float(not between and mode == 0),
                "mode_right": float(not between and mode == 1), "between": float(between),
                "lateral_offset": offset}
