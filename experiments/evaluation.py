"""Evaluate one trained model on every task it serves: closed-loop generation with
`stm.rollout.generate`, execution in pybullet with `stm.rollout.evaluate`, and the
metrics of the MLflow schema (success with its Wilson interval, final distance, circle
radius errors per radius, timings). Each call builds its own tasks and pybullet scenes,
so it is safe in parallel worker processes."""

from __future__ import annotations

import inspect
import logging
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from experiments.stats import success_summary

log = logging.getLogger(__name__)


@dataclass
class TaskEvaluation:
    task: str
    episodes: list
    q: np.ndarray  # (B, H+1, 7) generated joint trajectories
    results: list[dict[str, float]]
    metrics: dict[str, float] = field(default_factory=dict)


def circle_episodes(task, n: int, seed: int, radii: list[float]) -> list:
    """n circle episodes spread evenly over the given radii (m).

    Adapter over the circle task's signature: `episodes(n, seed, radii=...)`, else one call
    per radius with `radius=`, else the task's own default radii."""
    params = inspect.signature(task.episodes).parameters
    if "radii" in params:
        return task.episodes(n, seed, radii=list(radii))
    if "radius" in params:
        per = [n // len(radii) + (i < n % len(radii)) for i in range(len(radii))]
        eps = []
        for i, (r, k) in enumerate(zip(radii, per, strict=True)):
            if k:
                eps += task.episodes(k, seed + 1000 * i, radius=r)
        return eps
    return task.episodes(n, seed)


def _mean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else math.nan


def task_metrics(name: str, results: list[dict[str, float]], episodes: list) -> dict[str, float]:
    out: dict[str, float] = {f"{name}/n_rollouts": float(len(results))}
    if results and "success" in results[0]:
        for k, v in success_summary([r["success"] for r in results]).items():
            out[f"{name}/{k}"] = v
    keys = sorted({k for r in results for k in r} - {"success"})
    for k in keys:  # every task metric's mean, e.g. final_distance_mean
        out[f"{name}/{k}_mean"] = _mean([r.get(k, math.nan) for r in results])
    radii = [ep.info.get("radius") for ep in episodes]
    if any(r is not None for r in radii):
        for r in sorted({r for r in radii if r is not None}):
            group = [res for res, rr in zip(results, radii, strict=True) if rr == r]
            tag = f"{name}/r{round(r * 100, 1):g}"
            for k in ("radial_rmse", "max_radial_error_pct", "closure", "success"):
                if group and k in group[0]:
                    out[f"{tag}/{k}"] = _mean([g[k] for g in group])
            out[f"{tag}/n_rollouts"] = float(len(group))
    return out


def evaluate_model(model, eval_tasks: list[str], eval_cfg: dict[str, Any], *, seed: int = 0,
                   phi_mode: str | None = None) -> tuple[dict[str, float], list[TaskEvaluation]]:
    """Metrics over every evaluation task plus per-task details (for figures)."""
    from envs.tasks import get_task
    from stm.rollout import evaluate, generate

    metrics: dict[str, float] = {}
    details = []
    gen_seconds = phys_seconds = 0.0
    n_traj = 0
    gen_kwargs: dict[str, Any] = {"feedback": eval_cfg["feedback"], "seed": seed}
    if phi_mode is not None and "phi_mode" in inspect.signature(generate).parameters:
        gen_kwargs["phi_mode"] = phi_mode
    for name in eval_tasks:
        task = get_task(name)
        n = int(eval_cfg["rollouts"])
        if name == "circle":
            radii = [*eval_cfg["circle_radii"], *eval_cfg["circle_unseen_radii"]]
            episodes = circle_episodes(task, n, int(eval_cfg["seed"]), radii)
        else:
            episodes = task.episodes(n, int(eval_cfg["seed"]))
        rollouts = generate(model, task, episodes, **gen_kwargs)
        start = time.perf_counter()
        results = evaluate(task, rollouts, episodes)
        phys = time.perf_counter() - start
        gen_seconds += rollouts.seconds
        phys_seconds += phys
        n_traj += len(episodes)
        m = task_metrics(name, results, episodes)
        metrics.update(m)
        details.append(TaskEvaluation(name, episodes, rollouts.q, results, m))
        log.info("evaluated %s: %s", name, {k: round(v, 3) for k, v in m.items() if "success_rate" in k
                                            or "final_distance" in k})
    metrics["time/rollout_seconds"] = gen_seconds
    metrics["time/generation_seconds_per_traj"] = gen_seconds / max(n_traj, 1)
    metrics["time/physics_seconds"] = phys_seconds
    return metrics, details


def rollout_figure(detail: TaskEvaluation, path: Path, n: int) -> Path:
    """Top view (x-y) and side view (x-z) of the tool tip of the first n rollouts, with goals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from envs.kinematics import tip_position_np

    fig, axes = plt.subplots(1, 2, figsize=(9, 4))
    for i in range(min(n, len(detail.episodes))):
        ep, res = detail.episodes[i], detail.results[i]
        tip = tip_position_np(detail.q[i, : ep.horizon + 1])
        ok = res.get("success")
        style = "-" if ok is None or ok >= 0.5 else "--"
        for ax, (a, b) in zip(axes, ((0, 1), (0, 2)), strict=True):
            line, = ax.plot(tip[:, a], tip[:, b], style, lw=1.2)
            ax.plot(tip[0, a], tip[0, b], "o", color=line.get_color(), ms=4)
            for key in ("goal", "new_goal", "place", "center"):
                g = ep.info.get(key)
                if g is not None and np.size(g) == 3:
                    ax.plot(g[a], g[b], "x", color=line.get_color(), ms=7)
    for ax, (xl, yl) in zip(axes, (("x (m)", "y (m)"), ("x (m)", "z (m)")), strict=True):
        ax.set_xlabel(xl)
        ax.set_ylabel(yl)
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    rate = detail.metrics.get(f"{detail.task}/success_rate")
    title = f"{detail.task}: tool-tip paths (dashed: failed)"
    if rate is not None and not math.isnan(rate):
        title += f", success {rate:.0%}"
    fig.suptitle(title)
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
