"""A lever's studies side by side (the "deviations that help"): {{ lever("TASK", "STUDY", "STUDY", ...) }}
in a RESULTS template; STUDY@ITERATION names the checkpoints a milestones study kept at that iteration. Each
study contributes its finished runs of training task TASK; what sets the studies apart is read from the store,
not written by hand: the settings (params data.*, model.*, train.*, eval.*) whose values differ between the
named studies, e.g. "n_demos=45, goal_switches=0.5". A setting a study did not log (it ran on the default: a
data option of the task, a later field of stm.config) reads as that default. The table gives, per evaluated
task, variant and setting, the statistics of every success table (experiments.stats); the figure, grouped bars
with the seed-level 95 % interval."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.runtime.tracking import MILESTONE_ITERATION
from experiments.stats import success_rows, success_table
from reports import paper
from reports.data.store import Study, order_variants
from reports.plotting import FigureResult, gap, legend_below, panel_grid, plt, save, variant_color

NAME, TITLE = "lever", "Success by setting"
SETTING_PREFIXES = ("data.", "model.", "train.", "eval.")
# params that differ between runs of one study or only say how it was logged, never a lever
NOT_SETTINGS = {"train.seed", "train.checkpoint_every", "train.log_every", "train.val_every", "train.max_seconds",
                "eval.figures"}
ITERATION = f"params.{MILESTONE_ITERATION}"  # a milestones study's runs: the checkpoint's iteration


class LeverError(ValueError):
    """The named studies cannot be told apart, or a study's runs of the task disagree on a setting."""


def task_success_rows(study: Study, task: str) -> pd.DataFrame:
    """success_rows of the study's finished runs of training task `task` (every task they were evaluated on)."""
    evals = study.eval_metrics()
    evals = evals[(evals["status"] == "FINISHED") & (evals["task"] == task)]
    return success_rows(evals, study.variants)


def study_settings(study: Study, task: str, variant: str) -> dict[str, str] | None:
    """The settings (param name without "params." -> value) of the study's finished runs of `task` with
    `variant`; None without such runs. A setting two of those runs disagree on is an error (they are not one
    cell group), and so are runs at several iterations (a milestones study's checkpoints along training: name one
    stage as STUDY@ITERATION). A milestone's train.iters reads as its checkpoint's iteration: what it trained."""
    runs = study.ok[(study.ok["task"] == task) & (study.ok["variant"] == variant)]
    if runs.empty:
        return None
    iterations = runs[ITERATION].dropna().unique() if ITERATION in runs else []
    if len(iterations) > 1:
        listed = ", ".join(sorted(iterations, key=int))
        raise LeverError(f"study {study.name!r}: runs of {task}/{variant} at several iterations ({listed}); "
                         f"name one as {study.name}@ITERATION")
    out = {}
    for col in runs.columns:
        key = col.removeprefix("params.")
        if key == col or not key.startswith(SETTING_PREFIXES) or key in NOT_SETTINGS:
            continue
        values = runs[col].dropna().astype(str).unique()
        if len(values) > 1:
            raise LeverError(f"study {study.name!r}: runs of {task}/{variant} differ in {key} "
                             f"({', '.join(sorted(values))})")
        if len(values):
            out[key] = values[0]
    if len(iterations):
        out["train.iters"] = str(iterations[0])
    return out


def _default(task: str, key: str) -> str | None:
    """What a setting a study did not log was, as its param would read: a data option's default (the task
    constructor's), a model or train field's (stm.config: fields a cell leaves out at their default); else None."""
    from envs.tasks import task_class  # imported only here: it pulls in torch and pybullet
    from stm.config import ModelConfig, TrainConfig

    section, _, name = key.partition(".")
    owner = {"data": lambda: task_class(task)(), "model": ModelConfig, "train": TrainConfig}.get(section)
    value = getattr(owner(), name, None) if owner else None
    return None if value is None else str(value)


def _short(key: str, value: str | None) -> str:
    name = key.removeprefix("data.")
    if value is None:
        return f"{name} not logged"
    try:
        return f"{name}={float(value):g}"
    except ValueError:
        return f"{name}={value}"


def setting_labels(studies: list[Study], task: str) -> dict[tuple[str, str], str]:
    """(study name, variant) -> the settings that tell the study's runs of `task` apart from the other named
    studies' runs of that variant: the keys whose values differ between the studies for some variant, in a
    fixed order (a lever changes one thing in every variant it trains, so the label is the study's)."""
    names = [s.name for s in studies]
    if twice := next((n for n in names if names.count(n) > 1), None):
        raise LeverError(f"names study {twice!r} twice")
    variants = list(dict.fromkeys(v for s in studies for v in s.variants))
    found = {(s.name, v): got for v in variants for s in studies if (got := study_settings(s, task, v)) is not None}
    keys = sorted({k for got in found.values() for k in got})
    defaults = {k: _default(task, k) for k in keys if any(k not in got for got in found.values())}
    full = {at: {k: got[k] if k in got else defaults[k] for k in keys} for at, got in found.items()}
    differ = [k for k in keys if any(len({f[k] for (_, v), f in full.items() if v == variant}) > 1
                                     for variant in variants)]
    labels = {at: ", ".join(_short(k, f[k]) for k in differ) or "no setting differs" for at, f in full.items()}
    for variant in variants:
        mine = [(name, label) for (name, v), label in labels.items() if v == variant]
        twins = [name for name, label in mine if [lb for _, lb in mine].count(label) > 1]
        if twins:
            raise LeverError(f"studies {', '.join(map(repr, twins))} trained {task}/{variant} with the same settings")
    return labels


def rollout_rows(studies: list[Study], task: str, eval_task: str,
                  facts_of: Callable[[dict[str, np.ndarray]], pd.DataFrame]) -> pd.DataFrame:
    """One row per (study, variant) with `eval_task` rollouts of `task`'s models: its setting (setting_labels),
    the per-episode facts that `facts_of` reads from each finished seed's rollouts artifact, pooled over the
    seeds (`facts`; a seed whose facts are empty is not counted), and the seeds counted (`seeds`)."""
    labels = setting_labels(studies, task)
    rows = []
    for study in studies:
        runs = study.ok[study.ok["task"] == task]
        for variant in study.variants:
            facts = [f for run_id in runs[runs["variant"] == variant].sort_values("seed")["run_id"]
                     if (arrays := study.rollouts(run_id, eval_task)) is not None
                     and not (f := facts_of(arrays)).empty]
            if facts:
                rows.append({"study": study.name, "variant": variant, "setting": labels[(study.name, variant)],
                             "seeds": len(facts), "facts": pd.concat(facts, ignore_index=True)})
    return pd.DataFrame(rows)


def in_variant_order(agg: pd.DataFrame) -> pd.DataFrame:
    """`agg` sorted by variant in the paper's order (reports.data.store.order_variants), stable within one."""
    rank = {v: i for i, v in enumerate(order_variants(agg["variant"].unique()))}
    return agg.sort_values("variant", key=lambda v: v.map(rank), kind="stable")


def lever_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (evaluated task, variant, study), in the studies' order within each variant: success_rows'
    columns plus `setting` and `study`; studies without finished runs of `task` are left out."""
    labels = setting_labels(studies, task)
    frames = []
    for study in studies:
        agg = task_success_rows(study, task)
        if not agg.empty:
            frames.append(agg.assign(setting=[labels[(study.name, v)] for v in agg["variant"]], study=study.name))
    agg = pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()
    if agg.empty:
        return agg
    variants = {v: i for i, v in enumerate(dict.fromkeys(v for s in studies for v in s.variants))}
    order = {s.name: i for i, s in enumerate(studies)}
    agg = agg.assign(_v=agg["variant"].map(variants), _s=agg["study"].map(order))
    agg = agg.sort_values(["eval_task", "_v", "_s"], kind="stable")
    return agg.drop(columns=["_v", "_s"]).reset_index(drop=True)


def lever_table(agg: pd.DataFrame) -> pd.DataFrame:
    """THE success table (per seed, seed-level and Wilson intervals) with the setting after the variant."""
    if agg.empty:
        return pd.DataFrame()
    table = success_table(agg, paper.variant_label, paper.task_label)
    table.insert(2, "setting", list(agg["setting"]))
    return table


def _tick(setting: str) -> str:
    """A setting as a tick label: one line per key, a long key=value broken after the '='."""
    return "\n".join(part.replace("=", "=\n") if len(part) > 20 else part for part in setting.split(", "))


def lever_figure(agg: pd.DataFrame, task: str, folder: Path) -> FigureResult:
    """One panel per evaluated task: a group of bars per setting, one bar per variant (mean over seeds), the
    seed-level 95 % interval as an error bar."""
    if agg.empty:
        return gap(NAME, TITLE, f"no finished runs of {task} in the named studies")
    tasks = list(dict.fromkeys(agg["eval_task"]))
    variants = list(dict.fromkeys(agg["variant"]))
    settings = list(dict.fromkeys(agg["setting"]))
    width = 0.8 / len(variants)
    fig, axes = panel_grid(len(tasks), max(4.2, 2.0 * len(settings)), 3.6)
    for ax, eval_task in zip(axes.flat, tasks, strict=False):
        for j, variant in enumerate(variants):
            got = agg[(agg["eval_task"] == eval_task) & (agg["variant"] == variant)]
            x = np.array([settings.index(s) for s in got["setting"]]) + (j - (len(variants) - 1) / 2) * width
            mean = 100 * got["mean"].to_numpy(float)
            err = np.clip([mean - 100 * got["seed_low"].to_numpy(float), 100 * got["seed_high"].to_numpy(float) - mean],
                          0, None)
            ax.bar(x, mean, width, yerr=err, capsize=2, color=variant_color(variant, variants),
                   label=paper.variant_label(variant))
        ax.set_xticks(range(len(settings)), [_tick(s) for s in settings], fontsize=7)
        ax.set_title(paper.task_label(eval_task))
        ax.set_ylabel("success (%)")
        ax.set_ylim(0, 103)
        ax.grid(axis="y", alpha=0.3)
    legend_below(fig, axes.flat[0])
    fig.suptitle(f"{TITLE} ({task} models; mean over seeds, bars: seed-level 95 %)")
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
