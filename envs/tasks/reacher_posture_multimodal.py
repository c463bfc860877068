"""reacher-posture-multimodal: a reacher whose IK expert ends in one of two distinct arm
postures (the elbow swung to one side or the other), chosen at random per demonstration.

Why: the Sawyer has seven joints for a five-dimensional tool-down goal, so every goal has a
family of arm postures. The expert picks one of two of them by a coin flip; the tip paths
of both modes are the same straight line, so psi and phi say nothing about the mode and the
demonstrations are bimodal in joint space given the state. The average of the two modes
ends in a posture between them.

Documented choices (as the reacher's unless said: starts near NEUTRAL_Q, goals in GOAL_BOX,
tool down, a minimum-jerk straight tip line, 50-70 steps, success radius 5 cm):
- postures: POSTURE_REFS[k] is NEUTRAL_Q with the upper-arm roll right_j2 at +-SWING rad.
  `postures(goals)` solves, for each goal, the tool-down IK nearest to each reference (a
  damped least-squares step plus a null-space pull towards the reference), giving the two
  final postures of that goal (mode 0: j2 > 0, mode 1: j2 < 0).
- expert: joint guesses interpolate from the start to the chosen final posture with the
  minimum-jerk profile; each waypoint of the tip line is then solved by the same null-space
  IK pulled towards its guess, so the tip follows the line with the tool down while the
  posture swings smoothly into its mode. Modes are a random balanced permutation over the
  demos, independent of the state.
- posture coordinate c of a final configuration q (`posture_coordinate`): the projection of
  q - P0 on P1 - P0 over joints j0..j5 (the tool roll j6 does not change the posture), with
  P0, P1 the goal's two postures: c = 0 in mode 0, 1 in mode 1.
- evaluate: mode 0 if c < 1/3, mode 1 if c > 2/3, else "between"; success = final tip
  within 5 cm of the goal and a mode (not between). Labels: Demos.meta["modes"] for fresh
  demos, `demo_modes` from any demos (the dataset cache keeps arrays only).
"""

from __future__ import annotations

import logging
from typing import Any

import numpy as np
import torch

from envs.ik import DOWN
from envs.kinematics import default_kinematics, tip_position_np
from envs.robot import LIMITS, NEUTRAL_Q
from envs.tasks._bimodal import BimodalReacher
from envs.tasks.base import Demos, Episode
from envs.tasks.expert import check_trajectory, line_paths, min_jerk, physics_scene, velocity_ratio
from envs.tasks.reacher import SUCCESS_RADIUS
from envs.tasks.registry import register

log = logging.getLogger(__name__)

SWING = 0.9  # rad: right_j2 of the two posture references
POSTURE_REFS = tuple(NEUTRAL_Q + np.array([0.0, 0.0, s, 0.0, 0.0, 0.0, 0.0]) for s in (SWING, -SWING))
MODES = ("j2_pos", "j2_neg")  # right_j2 > 0 / < 0 at the end
BETWEEN = (1 / 3, 2 / 3)  # posture coordinate band counted as "between"
POSTURE_JOINTS = slice(0, 6)
TOL_POS, TOL_ROT = 1e-4, 1e-3  # m, rad: as envs.ik.solve_ik


def nullspace_ik(target: np.ndarray, q_init: np.ndarray, q_ref: np.ndarray, pull_iters: int = 60,
                 polish_iters: int = 60, damping: float = 0.03, rot_weight: float = 0.5, pull: float = 0.2
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Tool-down IK (B, 7) for tip targets (B, 3) from q_init: `pull_iters` damped least-squares
    steps each pulled in the Jacobian's null space towards q_ref (B, 7) (of the postures
    reaching the target, the one the reference selects), then plain steps until converged
    (at most `polish_iters`; the pull alone leaves a small residual). Returns (q, converged (B,))."""
    kin = default_kinematics(torch.float64)
    target = torch.as_tensor(target, dtype=torch.float64)
    q = torch.as_tensor(q_init, dtype=torch.float64).clone()
    ref = torch.as_tensor(q_ref, dtype=torch.float64)
    axis = torch.tensor(DOWN, dtype=torch.float64)
    eye6, eye7 = torch.eye(6, dtype=torch.float64), torch.eye(7, dtype=torch.float64)
    for it in range(pull_iters + polish_iters + 1):
        J, T = kin.chain.jacobian(q, ret_eef_pose=True)
        e_pos = target - T[:, :3, 3]
        e_rot = torch.cross(T[:, :3, 2], axis.expand_as(e_pos), dim=-1)
        ok = (e_pos.norm(dim=-1) < TOL_POS) & (e_rot.norm(dim=-1) < TOL_ROT)
        polishing = it >= pull_iters
        if it == pull_iters + polish_iters or (polishing and bool(ok.all())):
            break
        e = torch.cat([e_pos, rot_weight * e_rot], dim=-1)
        Jw = torch.cat([J[:, :3], rot_weight * J[:, 3:]], dim=1)
        pinv = Jw.transpose(1, 2) @ torch.linalg.inv(Jw @ Jw.transpose(1, 2) + damping**2 * eye6)
        dq = pinv @ e.unsqueeze(-1)
        if not polishing:
            dq = dq + (eye7 - pinv @ Jw) @ (pull * (ref - q)).unsqueeze(-1)
        else:
            dq = torch.where(ok[:, None, None], torch.zeros_like(dq), dq)
        q = kin.clamp(q + dq.squeeze(-1))
    return q.numpy(), ok.numpy()


def posture_coordinate(q: np.ndarray, postures: np.ndarray) -> np.ndarray:
    """c (...) of configurations q (..., 7) between the two postures (..., 2, 7): 0 at the
    first, 1 at the second (joints j0..j5)."""
    p0, p1 = postures[..., 0, POSTURE_JOINTS], postures[..., 1, POSTURE_JOINTS]
    d = p1 - p0
    return ((np.asarray(q)[..., POSTURE_JOINTS] - p0) * d).sum(-1) / (d * d).sum(-1)


def classify(c: float) -> int:
    """0 or 1: the posture taken; -1: between them."""
    return 0 if c < BETWEEN[0] else 1 if c > BETWEEN[1] else -1


@register
class ReacherPostureMultimodal(BimodalReacher):
    """Reacher ending in one of two arm postures at random (multimodal demonstrations)."""

    name = "reacher-posture-multimodal"
    model_task = "reacher-posture-multimodal"
    description = "multimodal: reacher ending in one of two arm postures (j2 swung +- 0.9 rad) at random"
    modes = MODES
    label = "reacher in two postures (multimodal)"
    report_rank = 21
    episode_options = ("min_steps", "max_steps")  # the constructor has no start range
    success_criterion = (f"tool tip within {SUCCESS_RADIUS * 100:g} cm of the goal at the end, the arm in one of "
                         "the two postures, not between them (physics)")

    def __init__(self, n_demos: int = 60, min_steps: int = 50, max_steps: int = 70):
        super().__init__(n_demos=n_demos, min_steps=min_steps, max_steps=max_steps)

    def config(self) -> dict[str, Any]:
        return {**super().config(), "task": self.name, "swing": SWING, "between": BETWEEN,
                "profile": "min-jerk line, tool down, null-space swing to one of two postures",
                "modes": "balanced random permutation"}

    def postures(self, goals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The two final postures (B, 2, 7) of each goal (B, 3) and whether both converged (B,)."""
        B = len(goals)
        refs = np.concatenate([np.repeat(r[None], B, axis=0) for r in POSTURE_REFS])
        q, ok = nullspace_ik(np.concatenate([goals, goals]), refs, refs)
        ok = ok & LIMITS.contains(q)
        return np.stack([q[:B], q[B:]], axis=1), ok[:B] & ok[B:]

    # expert ------------------------------------------------------------------
    def expert(self, q0: np.ndarray, goals: np.ndarray, modes: np.ndarray | None = None,
               steps: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Expert joint paths (B, max(steps)+1, 7) from q0 (B, 7) to goals (B, 3) ending in
        posture `modes` (B,) (default 0); also steps (B,) and ok (B,) as Reacher.expert."""
        B = len(q0)
        modes = np.zeros(B, int) if modes is None else np.asarray(modes, int)
        start = tip_position_np(q0)
        if steps is None:
            steps = self.steps_for(np.linalg.norm(goals - start, axis=-1))
        steps = np.asarray(steps, dtype=int)
        L = int(steps.max())
        final, ok_final = self.postures(goals)
        qf = final[np.arange(B), modes]
        guess = np.empty((B, L + 1, 7))
        for b in range(B):
            s = np.ones(L + 1)
            s[: steps[b] + 1] = min_jerk(int(steps[b]))
            guess[b] = q0[b] + s[:, None] * (qf[b] - q0[b])
        path = line_paths(start, goals, steps, L)
        flat = guess[:, 1:].reshape(-1, 7)
        q, ok = nullspace_ik(path[:, 1:].reshape(-1, 3), flat, flat, pull_iters=10, polish_iters=30)
        q = np.concatenate([q0[:, None], q.reshape(B, L, 7)], axis=1)
        ok = ok_final & ok.reshape(B, L).all(axis=1) & LIMITS.contains(q).all(axis=1)
        ok &= velocity_ratio(q, self.step_seconds) <= 1.0
        return q, steps, ok

    def replay(self, path: np.ndarray, goal: np.ndarray, mode: int) -> str:
        final, _ = self.postures(goal[None])
        res = self._play(path, goal, final[0])
        return "" if res["success"] and classify(res["posture_coordinate"]) == mode else "physics"

    def demo_modes(self, demos: Demos) -> np.ndarray:
        """Mode label (N,) of each demonstration from its final configuration (0, 1; -1 between)."""
        last = demos.q[np.arange(len(demos)), demos.lengths]
        final, _ = self.postures(demos.psi[:, 0])
        return np.array([classify(c) for c in posture_coordinate(last, final)])

    # evaluation --------------------------------------------------------------
    def episodes(self, n: int, seed: int) -> list[Episode]:
        eps = super().episodes(n, seed)
        final, _ = self.postures(np.array([ep.info["goal"] for ep in eps]))
        for ep, f in zip(eps, final, strict=True):
            ep.info["postures"] = f.tolist()
        return eps

    def _play(self, q: np.ndarray, goal: np.ndarray, postures: np.ndarray) -> dict[str, float]:
        measured = physics_scene().play(q, None, self.step_seconds)
        d = float(np.linalg.norm(measured.tip[-1] - goal))
        c = float(posture_coordinate(measured.q[-1], postures))
        mode = classify(c)
        return {"success": float(d < SUCCESS_RADIUS and mode >= 0), "final_distance": d,
                f"mode_{MODES[0]}": float(mode == 0), f"mode_{MODES[1]}": float(mode == 1), "between": float(mode < 0),
                "posture_coordinate": c}

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q = check_trajectory(q)
        goal = np.asarray(episode.psi[-1])
        if "postures" in episode.info:
            postures = np.asarray(episode.info["postures"])
        else:
            postures = self.postures(goal[None])[0][0]
        return self._play(q, goal, postures)
