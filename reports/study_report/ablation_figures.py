"""Summary figures of an ablation: success bars, compute time (STM vs IK), training time, training curves.

Every builder takes the study (and the output folder) and returns a `FigureResult`; missing runs, metrics or
artifacts make a gap, never an exception.
"""

from __future__ import annotations

import textwrap
from pathlib import Path

import numpy as np
import pandas as pd

from reports import paper
from reports.data.seed_aggregates import curve_band
from reports.data.store import Study
from reports.plotting import FigureResult, gap, mark_gap, plt, save, variant_color


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
        of_variant = agg[agg["variant"] == v].set_index("eval_task").loc[tasks]
        pos = x - 0.4 + width * (j + 0.5)
        mean = of_variant["mean"].to_numpy(dtype=float)
        lo = np.clip(mean - of_variant["ci_low"].to_numpy(dtype=float), 0, None)
        hi = np.clip(of_variant["ci_high"].to_numpy(dtype=float) - mean, 0, None)
        ax.bar(pos, np.nan_to_num(mean), width, yerr=np.nan_to_num(np.vstack([lo, hi])), capsize=3,
               color=variant_color(v, variants), label=f"{paper.variant_label(v)} (ours)")
        for p, t in zip(pos, tasks, strict=True):
            status = of_variant.loc[t, "status"]
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
    from envs.tasks import task_names  # here: it loads torch and pybullet

    order = task_names()  # the tasks' report order (Task.report_rank)
    tasks = [t for t in order if t in set(df["eval_task"])] + sorted(set(df["eval_task"]) - set(order))
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
            notes.append(f"{t} {ik / stm:.2f}x")
    ax.set_yscale("log")
    ax.set_xticks(np.arange(len(tasks)), tasks)
    ax.set_xlabel("task")
    ax.set_ylabel("wall time per trajectory (s, log scale)")
    speedup = f"STM speed-up over IK, one trajectory: {', '.join(notes)}" if notes else "no paired STM/IK numbers"
    speedup = textwrap.fill(f"{speedup} (paper: {paper.STM_SPEEDUP_OVER_IK:g}x on circles)", width=100)
    ax.set_title(f"{title} (mean ± std over runs of all variants)\n{speedup}", fontsize=10)
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
    ax.set_ylabel("training wall time (s, log scale)")
    ax.set_title(f"{title} (a pack's wall time, else mean ± std over runs) — {study.name}", fontsize=10)
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
            ax.set_ylabel("loss (NLL)" if "mdn" in v else "loss (MSE)")  # axis scale set below
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
            if (band["min"] > 0).all():  # positive losses (MSE) span decades: log axis
                ax.set_yscale("log")
            ax.grid(alpha=0.3)
            ax.legend(loc="upper right")
    fig.suptitle(f"{title} per task and variant, finished runs — {study.name}")
    if len(missing) == len(tasks) * len(variants):
        plt.close(fig)
        return gap(name, title, f"no run logged {metric}")
    return save(fig, folder, name, title, missing)
