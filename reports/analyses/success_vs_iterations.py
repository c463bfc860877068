"""Success vs training iterations from a milestones study (experiments/milestones.py: the checkpoints an
ablation kept, evaluated like its final models): one panel per evaluated task, one line per variant, the mean
over seeds with its seed-level 95 % interval (experiments.stats.success_rows) as a band."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from experiments.stats import success_rows
from reports.data.store import Study
from reports.plotting import FigureResult, gap, panel_grid, plt, save, variant_color

NAME, TITLE = "success_vs_iterations", "Success vs training iterations (kept checkpoints)"


def milestone_rows(study: Study) -> pd.DataFrame:
    """One row per (iteration, variant, evaluated task): success_rows' columns plus `iteration`."""
    evals = study.eval_metrics()
    if evals.empty or "tags.iteration" not in study.children:
        return pd.DataFrame()
    iteration = dict(zip(study.children["run_id"], study.children["tags.iteration"], strict=True))
    evals = evals[evals["status"] == "FINISHED"].assign(iteration=lambda d: d["run_id"].map(iteration))
    evals = evals[evals["iteration"].notna()].astype({"iteration": int})
    frames = [success_rows(group, study.variants).assign(iteration=it) for it, group in evals.groupby("iteration")]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def success_vs_iterations(study: Study, folder: Path) -> FigureResult:
    agg = milestone_rows(study)
    if agg.empty:
        return gap(NAME, TITLE, "no finished milestone runs with success metrics")
    tasks = list(dict.fromkeys(agg["eval_task"]))
    fig, axes = panel_grid(len(tasks), 4.2, 3.2)
    variants = study.variants
    for ax, task in zip(axes.flat, tasks, strict=False):
        for variant in variants:
            got = agg[(agg["eval_task"] == task) & (agg["variant"] == variant)].sort_values("iteration")
            if got.empty:
                continue
            color = variant_color(variant, variants)
            ax.plot(got["iteration"], 100 * got["mean"], "o-", color=color, label=variant, ms=3)
            ax.fill_between(got["iteration"], 100 * got["seed_low"], 100 * got["seed_high"], color=color, alpha=0.15)
        ax.set_title(task)
        ax.set_xlabel("training iterations")
        ax.set_ylabel("success (%)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axes.flat[0].legend(loc="best")
    fig.suptitle(f"{TITLE}: {study.name} (mean over seeds; band: seed-level 95 %)")
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
