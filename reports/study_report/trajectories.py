"""Figures drawn from the rollouts the runs logged (artifacts rollouts/<task>.npz, see reports.data.store):
generated vs ideal circles, tool-tip paths in 3D per task, the changing-goal figure."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.lines
import numpy as np

from reports import paper
from reports.data.store import Study
from reports.plotting import FigureResult, gap, mark_gap, panel_grid, plt, save, variant_color

EPISODES_PER_PANEL = 3


def panel_tasks(panel: str) -> list[str]:
    """The tasks a panel shows: their own choice (Task.panels), in report order."""
    from envs.tasks import tasks_with_panel  # here, not at import: it loads torch and pybullet

    return tasks_with_panel(panel)


def representative_run(study: Study, variant: str, eval_task: str) -> tuple[str, dict[str, np.ndarray]] | None:
    """The lowest-seed finished run of `variant` that logged rollouts/<eval_task>.npz, with its arrays."""
    runs = study.ok[(study.ok["variant"] == variant) & (study.ok["task"] == study.model_task_of(eval_task))]
    for run_id in runs.sort_values("seed")["run_id"]:
        arrays = study.rollouts(run_id, eval_task)
        if arrays is not None:
            return run_id, arrays
    return None


def _row(arrays: dict[str, np.ndarray], key: str, i: int) -> np.ndarray | None:
    a = arrays.get(key)
    if a is None or len(a) <= i:
        return None
    row = np.asarray(a[i], dtype=float)
    return None if np.all(np.isnan(row)) else row


# -------------------------------------------------------------------------------------------- circles
def _default_circle_centre(task: str, path: np.ndarray) -> np.ndarray:
    """The task's "centre" landmark (Task.landmarks), else the path's mean point."""
    from envs.tasks import task_class

    centre = task_class(task)().landmarks().get("centre")
    return np.asarray(centre, dtype=float) if centre is not None else np.nanmean(path, axis=0)


def _ideal_circle(task: str, arrays: dict[str, np.ndarray], i: int, path: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray | None]:
    """(centre, ideal xy points relative to it or None)."""
    ideal = _row(arrays, "ideal_tip", i)
    centre = _row(arrays, "center", i)
    radius = _row(arrays, "radius", i)
    if centre is None:
        centre = np.nanmean(ideal, axis=0) if ideal is not None else _default_circle_centre(task, path)
    if ideal is not None:
        return centre, (ideal - centre)[:, :2]
    if radius is not None:
        t = np.linspace(0, 2 * np.pi, 200)
        return centre, float(radius) * np.stack([np.cos(t), np.sin(t)], axis=1)
    return centre, None


def circles(study: Study, folder: Path) -> FigureResult:
    name, title = "circles", "Generated vs ideal circles"
    variants = study.variants
    circle_tasks = panel_tasks("circles")
    task = circle_tasks[0] if circle_tasks else ""
    reps = {v: representative_run(study, v, task) for v in variants} if task else {}
    reps = {v: r for v, r in reps.items() if r is not None}
    if not reps:
        return gap(name, title, f"no run logged rollouts/{task or '<circle task>'}.npz")
    radii = sorted({round(float(r), 4) for _, a in reps.values() for r in np.atleast_1d(a.get("radius", []))
                    if not math.isnan(float(r))})
    if not radii:  # no radius array: one panel per episode index
        radii = [None]
    fig, axes = panel_grid(len(radii), 4.2, 4.0)
    for ax, r in zip(axes.flat, radii, strict=False):
        drew_ideal = False
        for v, (_, arrays) in reps.items():
            rad = arrays.get("radius")
            idx = [int(np.argmin(np.abs(rad - r)))] if (r is not None and rad is not None) else [0]
            if r is not None and rad is not None and abs(float(rad[idx[0]]) - r) > 1e-6:
                continue
            i = idx[0]
            path = np.asarray(arrays["tip"][i], dtype=float)
            centre, ideal = _ideal_circle(task, arrays, i, path)
            if ideal is not None and not drew_ideal:
                ax.plot(ideal[:, 0] * 100, ideal[:, 1] * 100, "k--", lw=1.2)
                drew_ideal = True
            rel = (path - centre)[:, :2] * 100
            ax.plot(rel[:, 0], rel[:, 1], color=variant_color(v, variants), lw=1.2)
            ax.plot(rel[0, 0], rel[0, 1], "o", color=variant_color(v, variants), ms=3)
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x − centre (cm)")
        ax.set_ylabel("y − centre (cm)")
        ax.set_title(f"r = {r * 100:g} cm" if r is not None else "episode 0")
        ax.grid(alpha=0.3)
    handles = [matplotlib.lines.Line2D([], [], color="black", ls="--", label="ideal circle")]
    handles += [matplotlib.lines.Line2D([], [], color=variant_color(v, variants), label=paper.variant_label(v))
                for v in reps]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles))
    missing = [v for v in variants if v not in reps]
    fig.suptitle(f"{title} (tool tip, first seed) — {study.name}"
                 + (f"; gap: {', '.join(missing)}" if missing else ""))
    return save(fig, folder, name, title, missing)


# ---------------------------------------------------------------------------------------- tip paths
def _set_3d_labels(ax) -> None:
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")


def tip_paths(study: Study, folder: Path) -> FigureResult:
    name, title = "tip_paths", "Rollout tool-tip paths in 3D"
    variants = study.variants
    path_tasks = panel_tasks("tip_paths")
    tasks = [t for t in path_tasks if t in _eval_tasks(study)] or path_tasks[:3]
    reps = {(t, v): representative_run(study, v, t) for t in tasks for v in variants}
    if all(r is None for r in reps.values()):
        return gap(name, title, "no run logged rollouts/<task>.npz")
    cols = min(3, len(tasks))
    rows = math.ceil(len(tasks) / cols)
    fig = plt.figure(figsize=(4.6 * cols, 4.2 * rows))
    missing = []
    for k, t in enumerate(tasks):
        ax = fig.add_subplot(rows, cols, k + 1, projection="3d")
        ax.set_title(paper.task_label(t))
        _set_3d_labels(ax)
        for v in variants:
            rep = reps[(t, v)]
            if rep is None:
                missing.append(f"{t}/{v}")
                continue
            arrays = rep[1]
            color = variant_color(v, variants)
            for i in range(min(EPISODES_PER_PANEL, len(arrays["tip"]))):
                p = np.asarray(arrays["tip"][i], dtype=float)
                ax.plot(p[:, 0], p[:, 1], p[:, 2], color=color, lw=1.0,
                        label=paper.variant_label(v) if i == 0 else None)
                ax.scatter(*p[0], color=color, marker="o", s=10)
                goal = _row(arrays, "goal", i)
                if goal is not None:
                    ax.scatter(*goal, color=color, marker="*", s=60, edgecolor="black", linewidth=0.4)
        if all(reps[(t, v)] is None for v in variants):
            mark_gap(ax, "no rollouts logged")
    # one legend for the figure: a line per variant that has any rollouts, plus the markers
    drawn = [v for v in variants if any(reps[(t, v)] is not None for t in tasks)]
    handles = [matplotlib.lines.Line2D([], [], color=variant_color(v, variants), label=paper.variant_label(v))
               for v in drawn]
    handles += [matplotlib.lines.Line2D([], [], ls="", marker="o", color="gray", label="start"),
                matplotlib.lines.Line2D([], [], ls="", marker="*", ms=10, color="gray", markeredgecolor="black",
                                        label="goal (same colour as its path)")]
    fig.legend(handles=handles, loc="outside lower center", ncol=len(handles))
    fig.suptitle(f"{title}: first {EPISODES_PER_PANEL} episodes of the first seed (o start, * goal) — {study.name}")
    return save(fig, folder, name, title, missing)


def _eval_tasks(study: Study) -> set[str]:
    em = study.eval_metrics()
    found = set(em["eval_task"]) if not em.empty else set()
    return found | (set(panel_tasks("circles")) if not study.circle_metrics().empty else set())


def changing_goal(study: Study, folder: Path) -> FigureResult:
    name, title = "changing_goal", "Changing goal: adapted path vs the expert's direct path"
    variants = study.variants
    tasks = panel_tasks("changing_goal")
    reps = {(t, v): representative_run(study, v, t) for t in tasks for v in variants}
    if all(r is None for r in reps.values()):
        return gap(name, title, "no run logged rollouts/<changing-goal task>.npz")
    fig = plt.figure(figsize=(3.9 * len(variants), 3.9 * len(tasks)))
    missing = []
    for r, t in enumerate(tasks):
        for c, v in enumerate(variants):
            ax = fig.add_subplot(len(tasks), len(variants), r * len(variants) + c + 1,
                                 projection="3d")
            ax.set_title(f"{paper.task_label(t)}\n{paper.variant_label(v)}", fontsize=9)
            _set_3d_labels(ax)
            rep = reps[(t, v)]
            if rep is None:
                mark_gap(ax, "no rollouts logged")
                missing.append(f"{t}/{v}")
                continue
            arrays = rep[1]
            p = np.asarray(arrays["tip"][0], dtype=float)
            ax.plot(p[:, 0], p[:, 1], p[:, 2], color=variant_color(v, variants), lw=1.4, label="adapted path")
            switch = _row(arrays, "switch_step", 0)
            if switch is not None and 0 <= int(switch) < len(p):
                ax.scatter(*p[int(switch)], color="black", marker="x", s=30, label="goal switch")
            expert = _row(arrays, "expert_tip", 0)
            if expert is not None:
                e = expert[~np.isnan(expert).any(axis=1)]
                ax.plot(e[:, 0], e[:, 1], e[:, 2], "k--", lw=1.0, label="expert direct path")
            for key, marker, label in (("goal", "o", "old goal"), ("new_goal", "*", "new goal")):
                g = _row(arrays, key, 0)
                if g is not None:
                    ax.scatter(*g, marker=marker, s=60, color="tab:red" if key == "new_goal" else "tab:gray",
                               edgecolor="black", linewidth=0.4, label=label)
            ax.legend(loc="upper left", fontsize=7)
    fig.suptitle(f"{title} (episode 0 of the first seed) — {study.name}")
    return save(fig, folder, name, title, missing)
