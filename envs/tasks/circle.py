"""Circle drawing: the tool tip draws one full circle of radius r (psi = r) in a fixed
horizontal plane; phi = tip position.

Documented choices (base frame; the table top is at z = -0.15):
- centre CENTRE = (0.60, 0.16, 0.00): 15 cm above the table, in line with the neutral tip;
  plane z = 0.00 (horizontal), counter-clockwise seen from above.
- start on the circle at angle 0 (CENTRE + (r, 0, 0)) with the tool pointing down, the
  configuration solved by IK from NEUTRAL_Q; the angle follows a minimum-jerk profile
  from 0 to 2 pi over STEPS = 100 steps of STEP_SECONDS = 0.1 s (10 s per circle).
- demonstrations: 10 radii evenly spaced from 5 to 20 cm.
- metrics (`circle_metrics`, any tip path): radial error = distance from the tip to the
  circle (in-plane radius error and height error combined); radial_rmse (m),
  max_radial_error_pct (max radial error as % of r), closure (m, end to start),
  turns (unwrapped angle swept about the centre / 2 pi).
- success: max radial error < 10% of r and at least 0.95 of a turn drawn (a path that
  stays at the start point has no radial error but draws nothing).
- evaluation: episodes cycle through `eval_radii` (constructor option; a study sets it from
  its eval section's circle_radii + circle_unseen_radii, see `eval_options`). Circle
  episodes are deterministic (one start per radius): every seed gets the same ones.
"""

from __future__ import annotations

import logging
from collections.abc import Mapping
from typing import Any

import numpy as np
from tqdm import tqdm

from envs.robot import LIMITS, NEUTRAL_Q
from envs.tasks.base import Demos, Episode, StateLayout, Task
from envs.tasks.expert import check_trajectory, min_jerk, physics_scene, solve_tool_down_path, velocity_ratio
from envs.tasks.registry import register

log = logging.getLogger(__name__)

CENTRE = (0.60, 0.16, 0.00)
STEPS = 100
STEP_SECONDS = 0.1
DEMO_RADII = tuple(np.round(np.linspace(0.05, 0.20, 10), 6))
EVAL_RADII = (0.05, 0.10, 0.15, 0.075, 0.125)  # seen radii of the paper, then unseen ones
MAX_ERROR_PCT = 10.0
MIN_TURNS = 0.95
MAX_EVAL_RADIUS = 0.5  # m; larger circles leave the arm's reach
GROUP_METRICS = ("radial_rmse", "max_radial_error_pct", "closure", "success")  # reported per radius


PROFILES = ("min-jerk", "constant")  # how the angle advances along the turn


def circle_path(radius: float, steps: int = STEPS, centre=CENTRE, profile: str = "min-jerk") -> np.ndarray:
    """The demonstrated tip path (steps+1, 3): one counter-clockwise turn from angle 0, the angle
    following a minimum-jerk profile (at rest at both ends) or a constant angular speed."""
    if profile not in PROFILES:
        raise ValueError(f"unknown circle profile {profile!r}; known: {', '.join(PROFILES)}")
    s = min_jerk(steps) if profile == "min-jerk" else np.linspace(0.0, 1.0, steps + 1)
    theta = 2 * np.pi * s
    c = np.asarray(centre, dtype=float)
    return c + radius * np.stack([np.cos(theta), np.sin(theta), np.zeros_like(theta)], axis=-1)


def circle_metrics(tip: np.ndarray, radius: float, centre=CENTRE) -> dict[str, float]:
    """Metrics of a tip path (T+1, 3) against the circle of `radius` about `centre` in the
    horizontal plane through it. Pure numpy; usable on measured or predicted paths."""
    tip = np.asarray(tip, dtype=float)
    rel = tip - np.asarray(centre, dtype=float)
    rho = np.hypot(rel[:, 0], rel[:, 1])
    err = np.hypot(rho - radius, rel[:, 2])
    angle = np.unwrap(np.arctan2(rel[:, 1], rel[:, 0]))
    turns = float(abs(angle[-1] - angle[0]) / (2 * np.pi))
    max_pct = float(100.0 * err.max() / radius)
    return {
        "radial_rmse": float(np.sqrt(np.mean(err**2))),
        "max_radial_error_pct": max_pct,
        "closure": float(np.linalg.norm(tip[-1] - tip[0])),
        "turns": turns,
        "success": float(max_pct < MAX_ERROR_PCT and turns >= MIN_TURNS),
    }


@register
class Circle(Task):
    """Draw one full circle of the radius psi in a fixed horizontal plane."""

    name = "circle"
    model_task = "circle"
    step_seconds = STEP_SECONDS
    report_rank = 0
    episode_options = ("steps",)
    panels = ("circles", "tip_paths")
    primary_metric = "radial_rmse"
    success_criterion = f"max radial error < {MAX_ERROR_PCT:g}% of r and >= {MIN_TURNS:g} of a turn drawn"
    layout = StateLayout(phi_dim=3, psi_dim=1, phi_names=("tip_x", "tip_y", "tip_z"), psi_names=("radius",))

    def __init__(self, radii: tuple[float, ...] = DEMO_RADII, steps: int = STEPS, profile: str = "min-jerk",
                 eval_radii: tuple[float, ...] = EVAL_RADII):
        """radii: the demonstrated radii (m); eval_radii: the radii evaluation episodes cycle
        through (evaluation only: not in config(), so it does not touch the dataset cache)."""
        if not radii or min(radii) <= 0:
            raise ValueError(f"radii must be positive, got {radii}")
        if profile not in PROFILES:
            raise ValueError(f"profile must be one of {', '.join(PROFILES)}, got {profile!r}")
        if not eval_radii or not all(0.0 < r <= MAX_EVAL_RADIUS for r in eval_radii):
            raise ValueError(f"eval_radii must lie in 0 < r <= {MAX_EVAL_RADIUS} m, got {eval_radii}")
        self.radii = tuple(float(r) for r in radii)
        self.steps = int(steps)
        self.profile = profile
        self.eval_radii = tuple(float(r) for r in eval_radii)

    @classmethod
    def eval_options(cls, eval_cfg: Mapping[str, Any]) -> dict[str, Any]:
        """eval_radii = the eval section's circle_radii (seen in the paper) + circle_unseen_radii."""
        keys = [k for k in ("circle_radii", "circle_unseen_radii") if k in eval_cfg]
        if not keys:
            return {}
        radii = [r for k in keys for r in eval_cfg[k]]
        for r in radii:
            if not 0.0 < r <= MAX_EVAL_RADIUS:
                raise ValueError(f"eval.circle_radii: radius {r!r} m out of range; allowed: 0 < r <= {MAX_EVAL_RADIUS}")
        if not radii:
            raise ValueError("eval.circle_radii: no radius to evaluate; give at least one")
        return {"eval_radii": tuple(float(r) for r in radii)}

    def config(self) -> dict[str, Any]:
        return {"task": self.name, "radii": self.radii, "steps": self.steps, "centre": CENTRE,
                "step_seconds": self.step_seconds, "profile": f"{self.profile} angle, tool down, start at angle 0"}

    def phi(self, tip_pos, psi):
        return tip_pos

    def expert(self, radii) -> tuple[np.ndarray, np.ndarray]:
        """Expert joint paths (B, steps+1, 7) for radii (B,), and whether each is valid
        (IK converged, within joint limits, joint speeds under the URDF limits)."""
        paths = np.stack([circle_path(r, self.steps, profile=self.profile) for r in radii])
        q_start = np.repeat(NEUTRAL_Q[None], len(radii), axis=0)
        # first solve the start point from the neutral pose, then the circle from there
        q0, ok0, _ = solve_tool_down_path(paths[:, :1], q_start)
        q, ok, _ = solve_tool_down_path(paths[:, 1:], q0[:, 0])
        q = np.concatenate([q0, q], axis=1)
        ok = ok0 & ok & LIMITS.contains(q).all(axis=1) & (velocity_ratio(q, self.step_seconds) <= 1.0)
        return q, ok

    def demos(self, seed: int = 0) -> Demos:
        """One demonstration per radius; the expert is deterministic, so `seed` does not
        change it. A radius whose expert fails cannot be resampled: that raises."""
        q, ok = self.expert(self.radii)
        rejections = {"ik": int((~ok).sum()), "physics": 0}
        for i, r in enumerate(tqdm(self.radii, desc="circle demos: physics replay", disable=None, leave=False)):
            if ok[i] and not self.play_metrics(q[i], r)["success"]:
                rejections["physics"] += 1
                ok[i] = False
        if not ok.all():
            bad = [r for r, good in zip(self.radii, ok, strict=True) if not good]
            raise RuntimeError(f"circle expert fails for radii {bad}: {rejections}")
        n = len(self.radii)
        psi = np.broadcast_to(np.array(self.radii)[:, None, None], (n, self.steps + 1, 1)).copy()
        meta = {"rejections": rejections, "expert_success": 1.0, "replayed_in_physics": n}
        return Demos(q=q, grip=np.zeros((n, self.steps + 1)), psi=psi,
                     lengths=np.full(n, self.steps), meta=meta)

    def play_metrics(self, q: np.ndarray, radius: float) -> dict[str, float]:
        """Play q (T+1, 7) in physics and measure the drawn circle."""
        tip = physics_scene().play(q, None, self.step_seconds).tip
        return circle_metrics(tip, radius)

    def episodes(self, n: int, seed: int, radii: tuple[float, ...] | None = None) -> list[Episode]:
        """n episodes cycling through `radii` (default: eval_radii, i.e. 5, 10, 15 cm and the
        unseen 7.5, 12.5 cm), each starting at the expert's start configuration for its radius.
        Circle episodes are deterministic; `seed` is accepted for the common interface."""
        radii = self.eval_radii if radii is None else radii
        chosen = [float(radii[i % len(radii)]) for i in range(n)]
        starts = {r: q0 for r, q0 in zip(sorted(set(chosen)), self._starts(sorted(set(chosen))), strict=True)}
        return [Episode(q0=starts[r], psi=np.full((self.steps + 1, 1), r), horizon=self.steps,
                        info={"radius": r, "center": list(CENTRE)}) for r in chosen]

    def episode_metrics(self, results: list[dict[str, float]], episodes: list[Episode]) -> dict[str, float]:
        """Per radius r (cm): "r<r>/<metric>" means of GROUP_METRICS and "r<r>/n_rollouts"."""
        out: dict[str, float] = {}
        radii = [float(ep.info["radius"]) for ep in episodes]
        for r in sorted(set(radii)):
            group = [res for res, rr in zip(results, radii, strict=True) if rr == r]
            tag = f"r{round(r * 100, 1):g}"
            for k in GROUP_METRICS:
                vals = [g[k] for g in group if k in g and np.isfinite(g[k])]
                if vals:
                    out[f"{tag}/{k}"] = float(np.mean(vals))
            out[f"{tag}/n_rollouts"] = float(len(group))
        return out

    def expert_episode(self, episode: Episode) -> tuple[np.ndarray, None]:
        return self.expert([float(episode.info["radius"])])[0][0], None

    def expert_batch(self, episodes: list[Episode]) -> np.ndarray:
        return self.expert([float(ep.info["radius"]) for ep in episodes])[0]

    def landmarks(self) -> dict[str, tuple[float, float, float]]:
        return {"centre": CENTRE}

    def describe_paths(self, psis: list[np.ndarray]) -> str:
        radii = sorted({float(p[0, 0]) for p in psis})
        return f"radii {100 * radii[0]:g}-{100 * radii[-1]:g} cm" if radii else ""

    def _starts(self, radii) -> np.ndarray:
        paths = np.stack([circle_path(r, self.steps)[:1] for r in radii])
        q0, _, _ = solve_tool_down_path(paths, np.repeat(NEUTRAL_Q[None], len(radii), axis=0))
        return q0[:, 0]

    def kinematic_error(self, tip: np.ndarray, episode: Episode) -> float:
        """Radial RMSE plus the arc length still missing to one full turn (m): a path that
        stays put has no radial error but draws nothing."""
        r = float(episode.info["radius"])
        m = circle_metrics(tip, r)
        return m["radial_rmse"] + 2 * np.pi * r * max(0.0, 1.0 - m["turns"])

    def evaluate(self, q, grip, episode: Episode) -> dict[str, float]:
        q = check_trajectory(q)
        return self.play_metrics(q, float(episode.info["radius"]))
