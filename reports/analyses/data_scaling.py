"""Success vs number of demonstrations, across studies that differ only in it:
{{ data_scaling("TASK", "STUDY", "STUDY", ...) }} in a RESULTS template. Each study contributes its finished
runs of training task TASK, at the number of demonstrations they trained on (their `data.n_demos` param, else
the task's default; studies of different variants may share a number); the table gives, per evaluated task,
variant and number of demonstrations, the statistics of every success table (experiments.stats), the figure
the mean over seeds with the seed-level 95 % interval."""

from __future__ import annotations

from pathlib import Path

import pandas as pd

from experiments.stats import success_table
from reports import paper
from reports.analyses.levers import task_success_rows
from reports.data.store import Study
from reports.plotting import FigureResult, gap, panel_grid, plt, save, variant_color

NAME, TITLE = "data_scaling", "Success vs number of demonstrations"
N_DEMOS = "params.data.n_demos"


class DataScalingError(ValueError):
    """The named studies cannot make one curve (two with one variant at the same number of demonstrations)."""


def demos_of(study: Study, task: str) -> int | None:
    """The number of demonstrations the study's finished runs of `task` trained on; None without such runs."""
    runs = study.ok[study.ok["task"] == task]
    if runs.empty:
        return None
    logged = runs[N_DEMOS].dropna().astype(int).unique() if N_DEMOS in runs else []
    if len(logged) > 1:
        raise DataScalingError(f"study {study.name!r}: runs of {task} trained on {sorted(logged)} demonstrations")
    if len(logged):
        return int(logged[0])
    from envs.tasks import task_class  # the task's default (imported only here: it pulls in torch and pybullet)

    return int(task_class(task)().n_demos)


def scaling_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (number of demonstrations, variant, evaluated task): success_rows' columns plus `n_demos`
    and `study`; studies without finished runs of `task` are left out."""
    frames, seen = [], {}
    for study in studies:
        n = demos_of(study, task)
        if n is None:
            continue
        agg = task_success_rows(study, task)
        for variant in dict.fromkeys(agg["variant"]):  # two studies may share a count if not a variant
            if (n, variant) in seen:
                raise DataScalingError(f"studies {seen[n, variant]!r} and {study.name!r} both trained {task} on {n} "
                                       f"demonstrations (variant {variant})")
            seen[n, variant] = study.name
        frames.append(agg.assign(n_demos=n, study=study.name))
    agg = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if agg.empty:
        return agg
    order = {v: i for i, v in enumerate(dict.fromkeys(v for s in studies for v in s.variants))}
    agg = agg.assign(_v=agg["variant"].map(order))
    return agg.sort_values(["eval_task", "_v", "n_demos"], kind="stable").drop(columns="_v").reset_index(drop=True)


def scaling_table(agg: pd.DataFrame) -> pd.DataFrame:
    """THE success table (experiments.stats.success_table: per seed, seed-level and Wilson intervals) with the
    number of demonstrations after the variant: one row per (evaluated task, variant, demonstrations)."""
    if agg.empty:
        return pd.DataFrame()
    table = success_table(agg, paper.variant_label, paper.task_label)
    table.insert(2, "demos", [str(n) for n in agg["n_demos"]])
    return table


def scaling_figure(agg: pd.DataFrame, task: str, folder: Path) -> FigureResult:
    """One panel per evaluated task: success vs demonstrations (log axis), one line per variant, the seed-level
    95 % interval as a band."""
    if agg.empty:
        return gap(NAME, TITLE, f"no finished runs of {task} in the named studies")
    tasks = list(dict.fromkeys(agg["eval_task"]))
    variants = list(dict.fromkeys(agg["variant"]))
    counts = sorted(agg["n_demos"].unique())
    fig, axes = panel_grid(len(tasks), 4.2, 3.2)
    for ax, eval_task in zip(axes.flat, tasks, strict=False):
        for variant in variants:
            got = agg[(agg["eval_task"] == eval_task) & (agg["variant"] == variant)]
            if got.empty:
                continue
            color = variant_color(variant, variants)
            ax.plot(got["n_demos"], 100 * got["mean"], "o-", color=color, ms=3, label=paper.variant_label(variant))
            ax.fill_between(got["n_demos"], 100 * got["seed_low"], 100 * got["seed_high"], color=color, alpha=0.15)
        ax.set_xscale("log")
        ax.set_xticks(counts, [str(n) for n in counts])
        ax.minorticks_off()
        ax.set_title(paper.task_label(eval_task))
        ax.set_xlabel("demonstrations")
        ax.set_ylabel("success (%)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    axes.flat[0].legend(loc="best", fontsize=8)
    fig.suptitle(f"{TITLE} ({task} models; mean over seeds, band: seed-level 95 %)")
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
