"""Evaluate one trained model on every task it serves: closed-loop generation with
`stm.rollout.generate`, execution in pybullet with `stm.rollout.evaluate`, and the
metrics of the MLflow schema (success with its Wilson interval, every per-rollout metric's
mean, the task's own breakdowns, timings). Each call builds its own tasks and pybullet
scenes, so it is safe in parallel worker processes; its physics spreads over the study's idle worker
slots (experiments/runtime/spread.py), every per-episode result as played alone.

Protocol: each training seed is evaluated on its own episodes (`episode_seed`), and a model
trained to feed back samples of its mixture is evaluated sampling (`rollout_feedback`). The eval
section's split picks the episodes: "test" (the headline's) or "validation" (disjoint ones, on which
protocol choices are made; `split_seed`). Everything task-specific (episodes, metrics, the expert)
comes from the task object."""

from __future__ import annotations

import logging
import math
import numbers
import time
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from envs.figure_files import save_figure
from experiments.eval_sweep_config import SPLITS, VALIDATION_SEED_OFFSET
from experiments.mode_repeats import mode_metrics, repeat_rollouts, task_modes
from experiments.runtime.spread import physics_spread
from experiments.stats import run_success_metrics

log = logging.getLogger(__name__)


@dataclass
class TaskEvaluation:
    task: str
    episodes: list
    q: np.ndarray  # (B, H+1, 7) generated joint trajectories
    results: list[dict[str, float]]
    metrics: dict[str, float] = field(default_factory=dict)
    timing: dict[str, float] = field(default_factory=dict)
    seed: int = 0  # the training seed of the evaluated model
    episode_seed: int = 0  # the seed the episodes were drawn with (episode_seed(eval seed, seed))
    feedback: str = ""  # what the rollouts fed back
    modes: dict[str, Any] | None = None  # eval.mode_repeats > 0 on a task with modes: mode_repeats.mode_table


def episode_seed(eval_seed: int, train_seed: int) -> int:
    """The episodes' seed for a model trained with `train_seed`: every training seed gets its
    own episodes (independent draws), and seed 0 keeps the eval seed's. The demonstrations are
    drawn with the dataset seed (0), far below the eval seed (10,000 by default), so no
    evaluation episode repeats a training demonstration."""
    return int(eval_seed) + int(train_seed)


def split_seed(eval_cfg: Mapping[str, Any]) -> int:
    """The eval seed of the episodes the eval section's split asks for: eval.seed for "test" (the headline's
    episodes), eval.seed + VALIDATION_SEED_OFFSET for "validation" (those protocol choices are made on). Every
    training seed adds itself (episode_seed), so with fewer than VALIDATION_SEED_OFFSET training seeds no
    validation episode seed is a test one: validation 20,000 + s against test 10,000 + s by default."""
    split = eval_cfg.get("split", "test")
    if split not in SPLITS:
        raise ValueError(f"eval.split: {split!r} is not allowed; allowed: {', '.join(SPLITS)}")
    return int(eval_cfg["seed"]) + (VALIDATION_SEED_OFFSET if split == "validation" else 0)


def rollout_feedback(eval_feedback: str, train_feedback: str | None) -> str:
    """What the rollouts feed back: a model trained on samples of its mixture is evaluated
    sampling too; otherwise the eval section's choice (deterministic heads ignore it)."""
    return "sample" if train_feedback == "sample" else eval_feedback


def _mean(values: list[float]) -> float:
    vals = [v for v in values if v is not None and not math.isnan(v)]
    return float(np.mean(vals)) if vals else math.nan


def task_metrics(task, results: list[dict[str, float]], episodes: list) -> dict[str, float]:
    """"<task>/..." metrics of one evaluation: n_rollouts, the success summary, every per-rollout
    metric's mean and the task's own breakdowns (Task.episode_metrics)."""
    name = task.name
    out: dict[str, float] = {f"{name}/n_rollouts": float(len(results))}
    if results and "success" in results[0]:
        for k, v in run_success_metrics([r["success"] for r in results]).items():
            out[f"{name}/{k}"] = v
    keys = sorted({k for r in results for k, v in r.items() if _is_number(v)} - {"success"})
    for k in keys:  # every numeric task metric's mean, e.g. final_distance_mean (a per-episode list has none)
        out[f"{name}/{k}_mean"] = _mean([r.get(k, math.nan) for r in results])
    for k, v in task.episode_metrics(results, episodes).items():
        out[f"{name}/{k}"] = v
    return out


def evaluate_model(model, eval_tasks: list[str], eval_cfg: Mapping[str, Any], *, seed: int = 0,
                   phi_mode: str | None = None, timings: bool = True, data: Mapping[str, Any] | None = None,
                   train_feedback: str | None = None, temperature: float = 1.0
                   ) -> tuple[dict[str, float], list[TaskEvaluation]]:
    """Metrics over every evaluation task plus per-task details (for figures).

    seed: the model's training seed (picks its episodes and seeds sampling); data: the training
    task's dataset options (evaluation tasks take those they accept, so episodes come from the
    trained distribution); train_feedback, temperature: the training config's (see
    rollout_feedback); timings: also time one-at-a-time generation and the IK expert."""
    from envs.tasks import task_class
    from stm.rollout import generate

    metrics: dict[str, float] = {}
    details = []
    gen_seconds = phys_seconds = 0.0
    n_traj = 0
    feedback = rollout_feedback(eval_cfg["feedback"], train_feedback)
    gen_kwargs: dict[str, Any] = {"feedback": feedback, "seed": seed, "phi_mode": phi_mode}
    if feedback == "sample":
        gen_kwargs["temperature"] = temperature
    ep_seed = episode_seed(split_seed(eval_cfg), seed)
    repeats = int(eval_cfg.get("mode_repeats", 0) or 0)
    with physics_spread() as spread:  # the physics here and on the study's idle worker slots (runtime.spread)
        for name in eval_tasks:
            task = task_class(name).for_evaluation(data, eval_cfg)
            episodes = task.episodes(int(eval_cfg["rollouts"]), ep_seed)
            rollouts = generate(model, task, episodes, **gen_kwargs)
            start = time.perf_counter()
            results = spread.evaluate(task, rollouts, episodes)  # as stm.rollout.evaluate, on idle slots too
            phys = time.perf_counter() - start
            gen_seconds += rollouts.seconds
            phys_seconds += phys
            n_traj += len(episodes)
            m = task_metrics(task, results, episodes)
            m[f"{name}/episode_seed"] = float(ep_seed)
            detail = TaskEvaluation(name, episodes, rollouts.q, results, m, seed=seed, episode_seed=ep_seed,
                                    feedback=feedback)
            if repeats and task_modes(task):  # after the ordinary evaluation: its rollout is repeat 0, unchanged
                detail.modes = repeat_rollouts(model, task, episodes, results, gen_kwargs, repeats)
                m.update(mode_metrics(name, task_modes(task), np.asarray(detail.modes["mode"])))
            metrics.update(m)
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


# The timings are a side measurement: at most TIMED_EPISODES episodes generated / solved one at a time and
# BATCHED_IK_EPISODES in the batched IK solve, and no more than a tenth / a third of the evaluation's episodes
# (from 30 episodes on, the bounds; a smoke evaluation of 4 episodes times 1 and 2)
TIMED_EPISODES = 3
BATCHED_IK_EPISODES = 10


def _timed_counts(n_episodes: int) -> tuple[int, int]:
    """(episodes timed one at a time, episodes in the batched IK timing) for an evaluation of n_episodes."""
    return min(TIMED_EPISODES, -(-n_episodes // 10)), min(BATCHED_IK_EPISODES, -(-n_episodes // 3))


def _timing(model, task, episodes: list, rollouts, gen_kwargs: dict[str, Any]) -> dict[str, float]:
    """Seconds per trajectory: the STM one episode at a time and batched, and the task's IK
    expert on the same episodes (one at a time, and batched where the task has a batched expert)."""
    from stm.rollout import generate

    k, k_batched = _timed_counts(len(episodes))
    out: dict[str, float] = {"n_trajectories": float(len(episodes)), "batch_size": float(len(episodes)),
                             "horizon": float(max(ep.horizon for ep in episodes)),
                             "stm_batched_seconds_per_traj": rollouts.seconds / len(episodes)}
    out["stm_seconds_per_traj"] = float(np.mean([generate(model, task, [ep], **gen_kwargs).seconds
                                                 for ep in episodes[:k]]))
    try:
        start = time.perf_counter()
        for ep in episodes[:k]:
            task.expert_episode(ep)
        out["ik_seconds_per_traj"] = (time.perf_counter() - start) / k
        batch = episodes[:k_batched]
        start = time.perf_counter()
        if task.expert_batch(batch) is not None:  # several episodes in one IK solve
            out["ik_batched_seconds_per_traj"] = (time.perf_counter() - start) / len(batch)
    except NotImplementedError:
        log.info("task %s has no expert for its episodes: IK not timed", task.name)
    except Exception as exc:  # timing the expert is a side measurement: never fail the cell for it
        log.warning("IK timing for %s skipped: %s: %s", task.name, type(exc).__name__, exc)
    return out


def _nan_rows(rows: list[np.ndarray | None], width: int = 3) -> np.ndarray:
    """Stack per-episode (T_i, width) arrays into (B, max T, width), NaN-padded."""
    T = max((len(r) for r in rows if r is not None), default=1)
    out = np.full((len(rows), T, width), np.nan)
    for i, r in enumerate(rows):
        if r is not None:
            out[i, : len(r)] = r
    return out


def _is_number(v: Any) -> bool:
    return isinstance(v, numbers.Real | np.bool_)


def _is_steps(v: Any) -> bool:
    return isinstance(v, tuple | list) and all(isinstance(x, numbers.Integral) for x in v)


def result_arrays(results: list[dict[str, Any]]) -> dict[str, np.ndarray]:
    """Every per-episode numeric key of the task's evaluate (success, final_distance and the
    task's own, e.g. mode_left, collided) as a (B,) float array, NaN where an episode lacks it;
    success and final_distance always (NaN when the task has none). A key whose values are tuples
    of integers (e.g. grip_close_steps, the rows the grip command closed at) as a (B, L) int array,
    each row its episode's tuple padded with -1 (L: the longest tuple; L = 0 when all are empty)."""
    keys = {"success", "final_distance"} | {k for r in results for k, v in r.items() if _is_number(v)}
    out = {k: np.array([float(r[k]) if _is_number(r.get(k)) else np.nan for r in results], dtype=float)
           for k in sorted(keys)}
    for k in sorted({k for r in results for k, v in r.items() if _is_steps(v)} - keys):
        rows = [tuple(r.get(k, ())) for r in results]
        padded = np.full((len(rows), max(map(len, rows), default=0)), -1, dtype=int)
        for i, row in enumerate(rows):
            padded[i, : len(row)] = row
        out[k] = padded
    return out


def rollout_arrays(detail: TaskEvaluation, n_expert: int = 0) -> dict[str, np.ndarray]:
    """The `rollouts/<E>.npz` arrays of the reports contract, one row per rollout. `tip` is the
    forward kinematics of the commanded joint trajectory (the evaluation's physics does not return
    its measured path; position control tracks it closely). `seed` (the training seed),
    `episode_seed` and `episode` (index within the seed's episodes) identify each rollout, so a
    report can resample seeds and episodes. Every per-episode numeric result of the task's
    evaluate is a (B,) array of its own name (`result_arrays`); the fixed arrays above win a
    clash of names. `expert_tip` (tasks with a goal switch) for the first
    n_expert episodes: the IK expert's direct path from the rollout's state at the switch."""
    from envs.kinematics import tip_position_np
    from envs.tasks import task_class

    eps, res = detail.episodes, detail.results
    B = len(eps)

    def vec(key: str) -> np.ndarray:
        return np.array([ep.info[key] if key in ep.info else [np.nan] * 3 for ep in eps], dtype=float)

    out = result_arrays(res)
    out.update({
        "tip": tip_position_np(detail.q),
        "goal": vec("goal"),
        "new_goal": vec("new_goal"),
        "switch_step": np.array([int(ep.info.get("switch_step", -1)) for ep in eps], dtype=int),
        "radius": np.array([float(ep.info.get("radius", np.nan)) for ep in eps], dtype=float),
        "seed": np.full(B, detail.seed, dtype=int),
        "episode_seed": np.full(B, detail.episode_seed, dtype=int),
        "episode": np.arange(B, dtype=int),
    })
    if any("center" in ep.info for ep in eps):
        out["center"] = vec("center")
    if n_expert and any("switch_step" in ep.info for ep in eps):
        task = task_class(detail.task)()
        rows: list[np.ndarray | None] = [None] * B
        for i in range(min(n_expert, B)):
            try:
                q = task.expert_after_switch(eps[i], detail.q[i, int(eps[i].info["switch_step"])])
                if q is None:
                    break
                q = q[0] if isinstance(q, tuple) else q
                rows[i] = tip_position_np(np.asarray(q))
            except Exception as exc:  # a figure aid only
                log.warning("expert path for %s episode %d skipped: %s", detail.task, i, exc)
        if any(r is not None for r in rows):
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
    save_figure(fig, path.with_suffix(""), dpi=110)  # PNG and PDF
    return path
