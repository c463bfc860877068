"""What the multimodal reacher tasks share: an expert that takes a mode per demonstration, and
demonstrations whose modes are a balanced random permutation drawn before the states (so the
mode is independent of start and goal: the data are bimodal given the state), each replayed in
physics and redrawn with its mode when it fails. Not a task itself (the registry skips modules
whose name starts with "_")."""

from __future__ import annotations

import logging

import numpy as np
from tqdm import tqdm

from envs.kinematics import tip_position_np
from envs.tasks.base import Demos
from envs.tasks.reacher import Reacher

log = logging.getLogger(__name__)


class BimodalReacher(Reacher):
    """A Reacher subclass whose `expert(q0, goals, modes, steps)` follows mode 0 or 1 per row.
    Subclasses set `modes` (the two names) and implement `replay` (physics check of one demo)."""

    modes: tuple[str, str] = ("", "")

    def sample_pairs(self, rng: np.random.Generator, n: int) -> tuple[np.ndarray, np.ndarray]:
        """Start configurations (n, 7) and goals (n, 3) of demonstrations."""
        q0 = self.sample_starts(rng, n)
        return q0, self.sample_goals(rng, tip_position_np(q0))

    def replay(self, path: np.ndarray, goal: np.ndarray, mode: int) -> str:
        """Replay one expert path in physics: "" when it succeeds in `mode`, else the reason."""
        raise NotImplementedError

    def expert_trajectory(self, q_start: np.ndarray, goal: np.ndarray, max_steps: int | None = None,
                          mode: int = 0) -> np.ndarray:
        q_start = np.asarray(q_start, dtype=float).reshape(1, 7)
        goal = np.asarray(goal, dtype=float).reshape(1, 3)
        steps = self.steps_for(np.linalg.norm(goal - tip_position_np(q_start), axis=-1))
        if max_steps is not None:
            steps = np.minimum(steps, max_steps)
        q, steps, _ = self.expert(q_start, goal, np.array([mode]), steps)
        return q[0, : steps[0] + 1]

    def demos(self, seed: int = 0) -> Demos:
        rng = np.random.default_rng(seed)
        todo = rng.permutation(np.arange(self.n_demos) % 2)  # balanced, drawn before (so independent of) the states
        accepted: list[tuple[np.ndarray, np.ndarray, int, int]] = []
        rejections: dict[str, int] = {"ik": 0}
        while len(todo):
            need, modes = len(todo), todo
            kept = np.zeros(need, dtype=bool)
            q0, goals = self.sample_pairs(rng, need)
            q, steps, ok = self.expert(q0, goals, modes)
            for b in tqdm(range(need), desc=f"{self.name} demos: physics replay", disable=None, leave=False):
                path = q[b, : steps[b] + 1]
                reason = "ik" if not ok[b] else self.replay(path, goals[b], int(modes[b]))
                if reason:
                    rejections[reason] = rejections.get(reason, 0) + 1
                    continue
                accepted.append((path, goals[b], int(steps[b]), int(modes[b])))
                kept[b] = True
            todo = modes[~kept]  # a rejected demo is redrawn with its mode, so the split stays balanced
        if sum(rejections.values()):
            log.info("%s demos: resampled %s", self.name, rejections)
        lengths = np.array([a[2] for a in accepted])
        T = int(lengths.max())
        qs = np.stack([np.concatenate([a[0], np.repeat(a[0][-1:], T - a[2], axis=0)]) for a in accepted])
        psi = np.repeat(np.stack([a[1] for a in accepted])[:, None], T + 1, axis=1)
        meta = {"rejections": rejections, "expert_success": 1.0, "replayed_in_physics": len(accepted),
                "modes": [a[3] for a in accepted], "mode_names": list(self.modes)}
        return Demos(q=qs, grip=np.zeros(qs.shape[:2]), psi=psi, lengths=lengths, meta=meta)
