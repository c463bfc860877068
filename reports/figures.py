"""Figures of the report, each saved as PNG and PDF; a figure whose data is missing comes back as a gap.

Every builder takes the study (and the output folder) and returns a `FigureResult`; none raises on missing
runs, metrics or artifacts.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never a window
import matplotlib.lines  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import matplotlib.ticker  # noqa: E402
import numpy as np  # noqa: E402
import pandas as pd  # noqa: E402

from reports import paper  # noqa: E402
from reports.stats import curve_band  # noqa: E402
from reports.store import Study  # noqa: E402

log = logging.getLogger(__name__)

plt.rcParams.update({"font.size": 10, "axes.titlesize": 11, "figure.titlesize": 12, "legend.fontsize": 8,
                     "savefig.dpi": 150, "savefig.bbox": "tight", "figure.constrained_layout.use": True})

CHANGING_GOAL_TASKS = ("reacher-changing-goal", "pick-place-changing-goal")
PATH_TASKS = ("reacher", "pick-place", "stack", "reacher-changing-goal", "pick-place-changing-goal", "circle")
EPISODES_PER_PANEL = 3


@dataclass
class FigureResult:
    name: str
    title: str
    paths: list[Path] = field(default_factory=list)
    gap: str | None = None  # why the figure (or part of it) is missing
    partial: list[str] = field(default_factory=list)  # panels drawn as gaps


def variant_color(variant: str, variants: list[str]) -> tuple:
    cmap = plt.get_cmap("tab10")
    return cmap(variants.index(variant) % 10 if variant in variants else 9)


def save(fig, folder: Path, name: str, title: str, partial: list[str] | None = None) -> FigureResult:
    folder.mkdir(parents=True, exist_ok=True)
    paths = [folder / f"{name}.png", folder / f"{name}.pdf"]
    for p in paths:
        fig.savefig(p)
    plt.close(fig)
    return FigureResult(name, title, paths, partial=partial or [])


def gap(name: str, title: str, reason: str) -> FigureResult:
    log.info("figure %s is a gap: %s", name, reason)
    return FigureResult(name, title, gap=reason)


def mark_gap(ax, text: str) -> None:
    """An empty panel that says what is missing."""
    kw = dict(ha="center", va="center", color="#900", fontsize=9, wrap=True)
    if hasattr(ax, "text2D"):  # 3D panel: no empty box around the message
        ax.set_axis_off()
        ax.text2D(0.5, 0.5, f"gap: {text}", transform=ax.transAxes, **kw)
    else:
        ax.text(0.5, 0.5, f"gap: {text}", transform=ax.transAxes, **kw)


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


# -------------------------------------------------------------------------------------- success bars
def success_bars(agg: pd.DataFrame, study: Study, folder: Path) -> FigureResult:
    name, title = "success_bars", "Success rate per task and variant"
    if agg.empty:
        return gap(name, title, "no variants in the study")
    tasks = list(dict.fromkeys(agg["eval_task"]))
    variants = list(dict.fromkeys(agg["variant"]))
    width = 0.8 / max(len(variants), 1)
    fig, ax = plt.subplots(figsize=(max(7.0, 1.9 * len(tasks)), 4.2))
    x = np.arange(len(tasks))
    partial = []
    for j, v in enumerate(variants):
        cells = agg[agg["variant"] == v].set_index("eval_task").loc[tasks]
        pos = x - 0.4 + width * (j + 0.5)
        mean = cells["mean"].to_numpy(dtype=float)
        lo = np.clip(mean - cells["ci_low"].to_numpy(dtype=float), 0, None)
        hi = np.clip(cells["ci_high"].to_numpy(dtype=float) - mean, 0, None)
        ax.bar(pos, np.nan_to_num(mean), width, yerr=np.nan_to_num(np.vstack([lo, hi])), capsize=3,
               color=variant_color(v, variants), label=f"{paper.variant_label(v)} (ours)")
        for p, t in zip(pos, tasks, strict=True):
            status = cells.loc[t, "status"]
            if status == "gap":
                ax.bar(p, 1.0, width, fill=False, hatch="//", edgecolor="#c00", linewidth=0)
                ax.text(p, 0.5, "gap", rotation=90, ha="center", va="center", color="#c00", fontsize=8)
                partial.append(f"{v}/{t}")
            elif status == "partial":
                ax.text(p, 1.02, "†", ha="center", va="bottom", fontsize=9)
        ref = [paper.paper_success(v, t) for t in tasks]
        if any(r is not None for r in ref):
            ax.scatter(pos, [np.nan if r is None else r for r in ref], marker="D", s=28, facecolor="white",
                       edgecolor="black", zorder=5, label="paper (Table I)" if j == 0 else None)
    ax.set_xticks(x, [paper.task_label(t) for t in tasks], rotation=15)
    ax.set_ylim(0, 1.1)
    ax.set_ylabel("success rate (fraction of rollouts)")
    ax.set_xlabel("task")
    ax.set_title(f"{title} — {study.name} ({study.profile}); bars: mean over seeds, "
                 "whiskers: Wilson 95%", fontsize=10)
    ax.legend(ncol=2, loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="y", alpha=0.3)
    return save(fig, folder, name, title, partial)


# -------------------------------------------------------------------------------------------- circles
def _default_circle_centre(path: np.ndarray) -> np.ndarray:
    """The circle task's fixed centre (an envs constant), else the path's mean point."""
    try:
        from envs.tasks.circle import CENTRE
        return np.asarray(CENTRE, dtype=float)
    except Exception:  # noqa: BLE001 - envs may be unavailable where only the store is
        return np.nanmean(path, axis=0)


def _ideal_circle(arrays: dict[str, np.ndarray], i: int, path: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """(centre, ideal xy points relative to it or None)."""
    ideal = _row(arrays, "ideal_tip", i)
    centre = _row(arrays, "center", i)
    radius = _row(arrays, "radius", i)
    if centre is None:
        centre = np.nanmean(ideal, axis=0) if ideal is not None else _default_circle_centre(path)
    if ideal is not None:
        return centre, (ideal - centre)[:, :2]
    if radius is not None:
        t = np.linspace(0, 2 * np.pi, 200)
        return centre, float(radius) * np.stack([np.cos(t), np.sin(t)], axis=1)
    return centre, None


def circles(study: Study, folder: Path) -> FigureResult:
    name, title = "circles", "Generated vs ideal circles"
    variants = study.variants
    reps = {v: representative_run(study, v, "circle") for v in variants}
    reps = {v: r for v, r in reps.items() if r is not None}
    if not reps:
        return gap(name, title, "no run logged rollouts/circle.npz")
    radii = sorted({round(float(r), 4) for _, a in reps.values() for r in np.atleast_1d(a.get("radius", []))
                    if not math.isnan(float(r))})
    if not radii:  # no radius array: one panel per episode index
        radii = [None]
    fig, axes = plt.subplots(1, len(radii), figsize=(3.6 * len(radii), 3.8), squeeze=False)
    for ax, r in zip(axes[0], radii, strict=True):
        drew_ideal = False
        for v, (_, arrays) in reps.items():
            rad = arrays.get("radius")
            idx = [int(np.argmin(np.abs(rad - r)))] if (r is not None and rad is not None) else [0]
            if r is not None and rad is not None and abs(float(rad[idx[0]]) - r) > 1e-6:
                continue
            i = idx[0]
            path = np.asarray(arrays["tip"][i], dtype=float)
            centre, ideal = _ideal_circle(arrays, i, path)
            if ideal is not None and not drew_ideal:
                ax.plot(ideal[:, 0] * 100, ideal[:, 1] * 100, "k--", lw=1.2, label="ideal")
                drew_ideal = True
            rel = (path - centre)[:, :2] * 100
            ax.plot(rel[:, 0], rel[:, 1], color=variant_color(v, variants), lw=1.2, label=paper.variant_label(v))
        ax.set_aspect("equal", adjustable="datalim")
        ax.set_xlabel("x − centre (cm)")
        ax.set_ylabel("y − centre (cm)")
        ax.set_title(f"r = {r * 100:g} cm" if r is not None else "episode 0")
        ax.grid(alpha=0.3)
        ax.legend(loc="upper right")
    missing = [v for v in variants if v not in reps]
    fig.suptitle(f"{title} (measured tool tip, first seed) — {study.name}"
                 + (f"; gap: {', '.join(missing)}" if missing else ""))
    return save(fig, folder, name, title, missing)


# --------------------------------------------------------------------------------------- compute time
TIMING_KEYS = {  # json key -> (method, mode)
    "stm_seconds_per_traj": ("STM generation", "one trajectory"),
    "stm_batched_seconds_per_traj": ("STM generation", "batched (per traj.)"),
    "ik_seconds_per_traj": ("IK solver", "one trajectory"),
    "ik_batched_seconds_per_traj": ("IK solver", "batched (per traj.)"),
}
TIMING_METRICS = {
    "metrics.time/generation_seconds_per_traj": "stm_seconds_per_traj",
    "metrics.time/generation_batched_seconds_per_traj": "stm_batched_seconds_per_traj",
    "metrics.time/ik_seconds_per_traj": "ik_seconds_per_traj",
    "metrics.time/ik_batched_seconds_per_traj": "ik_batched_seconds_per_traj",
}


def timing_frame(study: Study) -> pd.DataFrame:
    """Long frame (run_id, variant, eval_task, key, seconds) from rollouts/ik_timing.json, else the metrics."""
    rows = []
    for run in study.ok.to_dict("records"):
        timing = study.ik_timing(run["run_id"])
        if timing:
            for task, entry in timing.items():
                for key in TIMING_KEYS:
                    if isinstance(entry, dict) and entry.get(key) is not None:
                        rows.append((run["run_id"], run["variant"], task, key, float(entry[key])))
            continue
        for col, key in TIMING_METRICS.items():
            val = run.get(col)
            if val is not None and not pd.isna(val):
                rows.append((run["run_id"], run["variant"], run["task"], key, float(val)))
    return pd.DataFrame(rows, columns=["run_id", "variant", "eval_task", "key", "seconds"])


def compute_time(study: Study, folder: Path) -> FigureResult:
    name, title = "compute_time", "Trajectory generation time: STM vs IK solver"
    df = timing_frame(study)
    df = df[df["seconds"] > 0]
    if df.empty:
        return gap(name, title, "no run logged rollouts/ik_timing.json or time/*_seconds_per_traj")
    tasks = [t for t in ("circle", "reacher") if t in set(df["eval_task"])] + \
        sorted(set(df["eval_task"]) - {"circle", "reacher"})
    keys = list(TIMING_KEYS)
    fig, ax = plt.subplots(figsize=(max(6.5, 2.4 * len(tasks)), 4.2))
    width = 0.8 / len(keys)
    colors = {"stm_seconds_per_traj": "#1f77b4", "stm_batched_seconds_per_traj": "#9ecae1",
              "ik_seconds_per_traj": "#d62728", "ik_batched_seconds_per_traj": "#fc9272"}
    stats = df.groupby(["eval_task", "key"])["seconds"].agg(["mean", "std", "count"])
    for j, key in enumerate(keys):
        pos = np.arange(len(tasks)) - 0.4 + width * (j + 0.5)
        mean = [stats["mean"].get((t, key), np.nan) for t in tasks]
        std = [stats["std"].get((t, key), np.nan) for t in tasks]
        method, mode = TIMING_KEYS[key]
        ax.bar(pos, mean, width, yerr=np.nan_to_num(std), capsize=3, color=colors[key], label=f"{method}, {mode}")
        for p, m in zip(pos, mean, strict=True):
            if np.isnan(m):
                ax.text(p, 0.5, "gap", transform=ax.get_xaxis_transform(), rotation=90, ha="center",
                        color="#c00", fontsize=8)
    notes = []
    for t in tasks:
        stm, ik = stats["mean"].get((t, "stm_seconds_per_traj")), stats["mean"].get((t, "ik_seconds_per_traj"))
        if stm and ik and not (np.isnan(stm) or np.isnan(ik)):
            notes.append(f"{t}: IK/STM = {ik / stm:.2f}x")
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(tasks)), tasks)
    ax.set_xlabel("task")
    ax.set_ylabel("wall time per trajectory (s, log scale)")
    ax.set_title(f"{title} (mean ± std over runs of all variants)\n{'; '.join(notes) or 'no paired STM/IK numbers'} "
                 f"(paper: STM ≈ {paper.STM_SPEEDUP_OVER_IK:g}x faster on circles)", fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="y", which="both", alpha=0.3)
    return save(fig, folder, name, title)


def train_time(summary: pd.DataFrame, study: Study, folder: Path) -> FigureResult:
    name, title = "train_time", "Training time per variant and task"
    if summary.empty:
        return gap(name, title, "no finished run logged time/train_seconds")
    tasks = sorted(summary["task"].dropna().unique())
    variants = study.variants
    width = 0.8 / max(len(variants), 1)
    fig, ax = plt.subplots(figsize=(max(6.0, 2.2 * len(tasks)), 4.0))
    for j, v in enumerate(variants):
        pos = np.arange(len(tasks)) - 0.4 + width * (j + 0.5)
        hit = summary[summary["variant"] == v].set_index("task")
        mean = [float(hit["mean"].get(t, np.nan)) for t in tasks]
        std = [float(hit["std"].get(t, np.nan)) for t in tasks]
        ax.bar(pos, mean, width, yerr=np.nan_to_num(std), capsize=3, color=variant_color(v, variants),
               label=paper.variant_label(v))
    ax.set_xticks(np.arange(len(tasks)), tasks)
    ax.set_yscale("log")
    ax.set_xlabel("training task")
    ax.set_ylabel("training wall time per run (s, log scale)")
    ax.set_title(f"{title} (mean ± std over seeds) — {study.name}", fontsize=10)
    ax.legend(loc="upper left", bbox_to_anchor=(1.0, 1.0))
    ax.grid(axis="y", which="both", alpha=0.3)
    return save(fig, folder, name, title)


# ------------------------------------------------------------------------------------ training curves
def training_curves(study: Study, folder: Path, metric: str = "train/loss") -> FigureResult:
    name, title = "training_curves", f"Training curves ({metric})"
    tasks = sorted(study.children["task"].dropna().unique())
    variants = study.variants
    if not tasks or not variants:
        return gap(name, title, "no child runs")
    fig, axes = plt.subplots(len(tasks), len(variants), figsize=(3.3 * len(variants), 2.8 * len(tasks)),
                             squeeze=False)
    missing = []
    for r, task in enumerate(tasks):
        for c, v in enumerate(variants):
            ax = axes[r][c]
            runs = study.ok[(study.ok["task"] == task) & (study.ok["variant"] == v)]
            band = curve_band([study.metric_history(rid, metric) for rid in runs["run_id"]])
            ax.set_title(f"{task} / {paper.variant_label(v)}", fontsize=9)
            ax.set_xlabel("iteration")
            ax.set_ylabel("loss (NLL)" if "mdn" in v else "loss (MSE)")
            if band.empty:
                mark_gap(ax, "no finished run" if runs.empty else f"no {metric} history")
                missing.append(f"{task}/{v}")
                continue
            color = variant_color(v, variants)
            n = int(band["n"].max())
            ax.plot(band["step"], band["mean"], color=color, lw=1.3, label=f"mean over {n} seed(s)")
            ax.fill_between(band["step"], band["mean"] - band["std"], band["mean"] + band["std"], color=color,
                            alpha=0.25, label="± std")
            ax.plot(band["step"], band["min"], color=color, lw=0.5, ls=":", label="min / max")
            ax.plot(band["step"], band["max"], color=color, lw=0.5, ls=":")
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right")
    fig.suptitle(f"{title} per task and variant, finished runs — {study.name}")
    if len(missing) == len(tasks) * len(variants):
        plt.close(fig)
        return gap(name, title, f"no run logged {metric}")
    return save(fig, folder, name, title, missing)


# ---------------------------------------------------------------------------------------- tip paths
def _set_3d_labels(ax) -> None:
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")


def tip_paths(study: Study, folder: Path) -> FigureResult:
    name, title = "tip_paths", "Rollout tool-tip paths in 3D"
    variants = study.variants
    tasks = [t for t in PATH_TASKS if t in _eval_tasks(study)] or list(PATH_TASKS[:3])
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
    return found | ({"circle"} if not study.circle_metrics().empty else set())


def changing_goal(study: Study, folder: Path) -> FigureResult:
    name, title = "changing_goal", "Changing goal: adapted path vs the expert's direct path"
    variants = study.variants
    reps = {(t, v): representative_run(study, v, t) for t in CHANGING_GOAL_TASKS for v in variants}
    if all(r is None for r in reps.values()):
        return gap(name, title, "no run logged rollouts/<changing-goal task>.npz")
    fig = plt.figure(figsize=(3.9 * len(variants), 3.9 * len(CHANGING_GOAL_TASKS)))
    missing = []
    for r, t in enumerate(CHANGING_GOAL_TASKS):
        for c, v in enumerate(variants):
            ax = fig.add_subplot(len(CHANGING_GOAL_TASKS), len(variants), r * len(variants) + c + 1,
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


# -------------------------------------------------------------------------------------------- sweeps
def _objective(study: Study) -> tuple[str, pd.Series] | None:
    for col in ("metrics.objective", "metrics.val/metric"):
        if col in study.children.columns and study.children[col].notna().any():
            return col.removeprefix("metrics."), study.children[col]
    return None


def _sweep_frame(study: Study) -> pd.DataFrame:
    ch = study.children.copy()
    found = _objective(study)
    ch["objective"] = found[1] if found else np.nan
    if "metrics.val/metric" in ch:  # pruned trials have no objective: show their last intermediate value
        ch["objective"] = ch["objective"].fillna(ch["metrics.val/metric"])
    ch["trial_no"] = ch["trial"].fillna(pd.Series(range(len(ch)), index=ch.index, dtype="Int64"))
    state = ch["trial_state"].fillna(ch["status"])  # MLflow status when the trial tag is missing
    ch["trial_state"] = state.replace({"FINISHED": "COMPLETE", "FAILED": "FAIL", "KILLED": "PRUNED"})
    return ch.sort_values("trial_no")


OBJECTIVE_LABELS = {"val": "validation metric", "final_distance": "final distance to goal (m)"}


def _objective_label(study: Study, metric: str) -> str:
    """What the objective measures, from the sweep parent's param sweep.objective where logged."""
    kind = study.parent.get("params.sweep.objective")
    return f"objective: {OBJECTIVE_LABELS.get(kind, kind)}" if kind else metric


def _direction(study: Study) -> str:
    d = study.parent.get("tags.direction") or study.parent.get("params.direction") or "minimize"
    return "maximize" if str(d).lower().startswith("max") else "minimize"


def sweep_history(study: Study, folder: Path) -> FigureResult:
    name, title = "sweep_history", "Sweep: objective per trial"
    found = _objective(study)
    if found is None:
        return gap(name, title, "no trial logged 'objective' or 'val/metric'")
    df = _sweep_frame(study)
    fig, ax = plt.subplots(figsize=(7, 4))
    for state, marker, color in (("COMPLETE", "o", "tab:blue"), ("PRUNED", "s", "tab:gray"), ("FAIL", "x", "tab:red")):
        part = df[df["trial_state"] == state]
        if len(part):
            ax.scatter(part["trial_no"], part["objective"], marker=marker, color=color,
                       label="pruned (last intermediate value)" if state == "PRUNED" else state.lower())
    done = df[df["trial_state"] == "COMPLETE"].dropna(subset=["objective"])
    if len(done):
        best = done["objective"].cummin() if _direction(study) == "minimize" else done["objective"].cummax()
        ax.step(done["trial_no"], best, where="post", color="black", lw=1.2, label="best so far")
    ax.set_xlabel("trial number")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_ylabel(f"{_objective_label(study, found[0])} ({_direction(study)}d)")
    ax.set_title(f"{title} — {study.name}")
    ax.grid(alpha=0.3)
    ax.legend()
    return save(fig, folder, name, title)


def sweep_params(study: Study, folder: Path) -> FigureResult:
    name, title = "sweep_params", "Sweep: objective vs each hyperparameter"
    found = _objective(study)
    df = _sweep_frame(study)
    # the sampled values (params trial.<name>); without them every param that varies between trials
    params = [c for c in df.columns if c.startswith("params.trial.") and df[c].nunique(dropna=True) > 1] or \
        [c for c in df.columns if c.startswith("params.") and df[c].nunique(dropna=True) > 1]
    if found is None or not params:
        return gap(name, title, "no objective or no varied params among the trials")
    cols = min(3, len(params))
    rows = math.ceil(len(params) / cols)
    fig, axes = plt.subplots(rows, cols, figsize=(3.6 * cols, 3.3 * rows), squeeze=False)
    for ax in axes.flat[len(params):]:
        ax.set_axis_off()
    for ax, p in zip(axes.flat, params, strict=False):
        vals = pd.to_numeric(df[p], errors="coerce")
        if vals.isna().any():  # categorical: positions by sorted category
            cats = sorted(df[p].dropna().astype(str).unique())
            vals = df[p].astype(str).map({c: i for i, c in enumerate(cats)})
            ax.set_xticks(range(len(cats)), cats, rotation=30)
        colors = df["trial_state"].map({"COMPLETE": "tab:blue", "PRUNED": "tab:gray"}).fillna("tab:red")
        ax.scatter(vals, df["objective"], c=list(colors))
        ax.set_xlabel(p.removeprefix("params.").removeprefix("trial."))
        ax.set_ylabel(_objective_label(study, found[0]))
        ax.grid(alpha=0.3)
    axes[0][0].scatter([], [], c="tab:blue", label="complete")
    axes[0][0].scatter([], [], c="tab:gray", label="pruned")
    axes[0][0].legend()
    fig.suptitle(f"{title} — {study.name}")
    return save(fig, folder, name, title)


def sweep_intermediate(study: Study, folder: Path, metric: str = "val/metric") -> FigureResult:
    name, title = "sweep_intermediate", f"Sweep: intermediate {metric} per trial (pruning)"
    df = _sweep_frame(study)
    fig, ax = plt.subplots(figsize=(7, 4))
    drew = False
    for row in df.itertuples():
        h = study.metric_history(row.run_id, metric)
        if h.empty:
            continue
        pruned = row.trial_state == "PRUNED"
        ax.plot(h["step"], h["value"], color="tab:gray" if pruned else "tab:blue", lw=0.8,
                alpha=0.6 if pruned else 0.9, marker=".", ms=3)
        drew = True
    if not drew:
        plt.close(fig)
        return gap(name, title, f"no trial logged {metric} history")
    ax.plot([], [], color="tab:blue", label="complete")
    ax.plot([], [], color="tab:gray", label="pruned")
    ax.set_xlabel("iteration")
    ax.set_ylabel(f"{metric} (lower is better)")
    ax.set_title(f"{title} — {study.name}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    return save(fig, folder, name, title)


Builder = Callable[[Study, Path], FigureResult]
