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
    timing: dict[str, float] = field(default_factory=dict)


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
                   phi_mode: str | None = None, timings: bool = True) -> tuple[dict[str, float], list[TaskEvaluation]]:
    """Metrics over every evaluation task plus per-task details (for figures). `timings`: also
    time one-at-a-time generation and the IK expert (the compute-time comparison)."""
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
        detail = TaskEvaluation(name, episodes, rollouts.q, results, m)
        if timings:
            detail.timing = _timing(model, task, episodes, rollouts, gen_kwargs)
        details.append(detail)
        log.info("evaluated %s: %s", name, {k: round(v, 3) for k, v in m.items() if "success_rate" in k
                                            or "final_distance" in k})
    single = [d.timing["stm_seconds_per_traj"] for d in details if d.timing]
    ik = [d.timing["ik_seconds_per_traj"] for d in details if "ik_seconds_per_traj" in d.timing]
    ik_batched = [d.timing["ik_batched_seconds_per_traj"] for d in details
                  if "ik_batched_seconds_per_traj" in d.timing]
    metrics["time/generation_batched_seconds_per_traj"] = gen_seconds / max(n_traj, 1)
    if ik:
        metrics["time/ik_seconds_per_traj"] = float(np.mean(ik))
    if ik_batched:
        metrics["time/ik_batched_seconds_per_traj"] = float(np.mean(ik_batched))
    metrics["time/rollout_seconds"] = gen_seconds
    if single:
        metrics["time/generation_seconds_per_traj"] = float(np.mean(single))
    metrics["time/physics_seconds"] = phys_seconds
    return metrics, details


TIMED_EPISODES = 3  # episodes generated / solved one at a time for the per-trajectory timings
BATCHED_IK_EPISODES = 10  # episodes in the batched IK timing (bounded: it is a side measurement)


def _timing(model, task, episodes: list, rollouts, gen_kwargs: dict[str, Any]) -> dict[str, float]:
    """Seconds per trajectory: the STM one episode at a time and batched, and the task's IK
    expert on the same episodes (one at a time, and batched where the task has a batched expert)."""
    from stm.rollout import generate

    k = min(TIMED_EPISODES, len(episodes))
    out: dict[str, float] = {"n_trajectories": float(len(episodes)), "batch_size": float(len(episodes)),
                             "horizon": float(max(ep.horizon for ep in episodes)),
                             "stm_batched_seconds_per_traj": rollouts.seconds / len(episodes)}
    out["stm_seconds_per_traj"] = float(np.mean([generate(model, task, [ep], **gen_kwargs).seconds
                                                 for ep in episodes[:k]]))
    try:
        solve_one = _expert_solver(task)
        if solve_one is not None:
            start = time.perf_counter()
            for ep in episodes[:k]:
                solve_one(ep)
            out["ik_seconds_per_traj"] = (time.perf_counter() - start) / k
        batch = episodes[:BATCHED_IK_EPISODES]
        if task.name == "reacher":  # the batched expert: several episodes in one IK solve
            q0 = np.stack([ep.q0 for ep in batch])
            goals = np.array([ep.info["goal"] for ep in batch])
            start = time.perf_counter()
            task.expert(q0, goals)
            out["ik_batched_seconds_per_traj"] = (time.perf_counter() - start) / len(batch)
        if task.name == "circle":
            start = time.perf_counter()
            task.expert([float(ep.info["radius"]) for ep in batch])
            out["ik_batched_seconds_per_traj"] = (time.perf_counter() - start) / len(batch)
    except Exception as exc:  # timing the expert is a side measurement: never fail the cell for it
        log.warning("IK timing for %s skipped: %s: %s", task.name, type(exc).__name__, exc)
    return out


def _expert_solver(task):
    """A function solving one episode with the task's IK expert, if the task has one."""
    if hasattr(task, "expert_rollout"):
        return task.expert_rollout
    if task.name == "circle":
        return lambda ep: task.expert([float(ep.info["radius"])])
    if hasattr(task, "expert_trajectory"):
        return lambda ep: task.expert_trajectory(ep.q0, np.asarray(ep.info["goal"]))
    return None


def _nan_rows(rows: list[np.ndarray | None], width: int = 3) -> np.ndarray:
    """Stack per-episode (T_i, width) arrays into (B, max T, width), NaN-padded."""
    T = max((len(r) for r in rows if r is not None), default=1)
    out = np.full((len(rows), T, width), np.nan)
    for i, r in enumerate(rows):
        if r is not None:
            out[i, : len(r)] = r
    return out


def rollout_arrays(detail: TaskEvaluation, n_expert: int = 0) -> dict[str, np.ndarray]:
    """The `rollouts/<E>.npz` arrays of the reports contract. `tip` is the forward kinematics of
    the commanded joint trajectory (the evaluation's physics does not return its measured path;
    position control tracks it closely). `expert_tip` (changing goal only) for the first
    n_expert episodes: the IK expert's direct path from the rollout's state at the switch."""
    from envs.kinematics import tip_position_np

    eps, res = detail.episodes, detail.results
    B = len(eps)

    def vec(key: str) -> np.ndarray:
        return np.array([ep.info[key] if key in ep.info else [np.nan] * 3 for ep in eps], dtype=float)

    out = {
        "tip": tip_position_np(detail.q),
        "success": np.array([r.get("success", np.nan) for r in res], dtype=float),
        "final_distance": np.array([r.get("final_distance", np.nan) for r in res], dtype=float),
        "goal": vec("goal"),
        "new_goal": vec("new_goal"),
        "switch_step": np.array([int(ep.info.get("switch_step", -1)) for ep in eps], dtype=int),
        "radius": np.array([float(ep.info.get("radius", np.nan)) for ep in eps], dtype=float),
    }
    if detail.task == "circle":
        from envs.tasks.circle import CENTRE

        out["center"] = np.repeat(np.asarray(CENTRE, float)[None], B, axis=0)
    task = None
    if n_expert and any("switch_step" in ep.info for ep in eps):
        from envs.tasks import get_task

        task = get_task(detail.task)
    if task is not None and hasattr(task, "expert_after_switch"):
        rows: list[np.ndarray | None] = [None] * B
        for i in range(min(n_expert, B)):
            try:
                k = int(eps[i].info["switch_step"])
                q = task.expert_after_switch(eps[i], detail.q[i, k])
                q = q[0] if isinstance(q, tuple) else q
                rows[i] = tip_position_np(np.asarray(q))
            except Exception as exc:  # a figure aid only
                log.warning("expert path for %s episode %d skipped: %s", detail.task, i, exc)
        out["expert_tip"] = _nan_rows(rows)
    return out


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
