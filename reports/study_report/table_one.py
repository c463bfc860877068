"""Table I as the paper prints it, ours beside the paper's: one row per evaluated task and variant, the cells of
each training task from the study named for it (a RESULTS template's {{ table_one("reacher=paper", ...) }}; a
study's own report takes every task from the study itself), with each cell's seed-level interval, each seed's
rate and the paper's value. Where a study judged pick-and-place on the block, a column gives the strict criterion's
rate (reports.study_report.criteria). An evaluated task may name its own study (stacking judged after a scripted
return to a start configuration: `stack=STUDY`, a milestones study run with --stack-restart start); its rows then
give, beside ours, the same models' rate restarting from the place pose in the training task's study. The figure:
bars for ours with the seed-level interval, the paper's values as markers, one group per evaluated task that has a
finished cell (no empty panel)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from experiments import stats
from experiments.eval_sweep_config import UNHASHED_DEFAULTS
from reports import paper
from reports.data.seed_aggregates import aggregate_success
from reports.data.store import Study, order_variants
from reports.plotting import FigureResult, gap, plt, save, variant_color
from reports.study_report import tables
from reports.study_report.criteria import (
    PLACE_TASK,
    STRICT_COLUMN,
    STRICT_NOTE,
    beside_cell,
    cell_strict_rate,
    judged_on_placed,
)
from reports.study_report.tables import GAP, Table

NAME, TITLE = "table_one", "Table I: success rate, ours beside the paper's"
PLACE_POSE_COLUMN = "from the place pose"
PLACE_POSE_NOTE = (f"{PLACE_POSE_COLUMN}: stacking where ours lifts clear and returns to a start configuration "
                   "between the blocks (a scripted move; the chosen protocol), the same models restarting each next "
                   "block from the place pose instead, in the training task's study: mean over seeds (seed-level "
                   "95 %), its own rollouts.")
FIGURE_TITLE = "Table I as bars: ours with its seed-level interval, the paper's as markers"  # not the table's again


def own_sources(study: Study) -> dict[str, Study]:
    """A study's own report: every training task it ran, from itself."""
    from envs.tasks import task_names  # here: it loads torch and pybullet

    tasks = set(study.children["task"].dropna())
    return {t: study for t in task_names() if t in tasks}


def training_sources(sources: dict[str, Study]) -> dict[str, Study]:
    """The sources' training tasks (the keys that are not an evaluated task's own study)."""
    from envs.tasks import training_tasks  # here: it loads torch and pybullet

    return {t: s for t, s in sources.items() if t in training_tasks()}


def source_of(sources: dict[str, Study], eval_task: str) -> Study:
    """The study an evaluated task's cells come from: its own where the sources name one, else its training
    task's."""
    from envs.tasks import model_task_of

    return sources[eval_task] if eval_task in sources else sources[model_task_of(eval_task)]


def eval_tasks(sources: dict[str, Study]) -> list[str]:
    """The evaluated tasks of the sources' training tasks that their studies evaluate (or plan to: the runs'
    eval_tasks tags), the paper's Table I tasks first in its order, then the report order."""
    from envs.tasks import evaluation_tasks, task_names

    found = []
    for task, study in training_sources(sources).items():
        evals = study.eval_metrics()
        seen = set(evals.loc[evals["task"] == task, "eval_task"]) if not evals.empty else set()
        runs = study.children[study.children["task"] == task]
        if "tags.eval_tasks" in runs:
            seen |= {t for listed in runs["tags.eval_tasks"].dropna() for t in str(listed).split(",")}
        found += [t for t in evaluation_tasks(task) if t in seen] or evaluation_tasks(task)
    rank = {t: i for i, t in enumerate(task_names())}
    first = [t for t in paper.TABLE_I_SETTING if t in found]
    return first + sorted((t for t in dict.fromkeys(found) if t not in first), key=lambda t: rank.get(t, len(rank)))


def _cells(study: Study, variants: list[str], eval_task: str) -> list[dict]:
    return aggregate_success(study.eval_metrics(), study.children, variants, [eval_task], study.model_task_of,
                             study.seeds).to_dict("records")


def _stack_restart(study: Study) -> str:
    """How a study's stacking restarts each next block (param eval.stack_restart; absent: the eval config's default,
    left out of the runs' params)."""
    col = "params.eval.stack_restart"
    said = set(study.children[col].dropna()) if col in study.children else set()
    return said.pop() if len(said) == 1 else (UNHASHED_DEFAULTS["stack_restart"] if not said else "mixed")


def _place_pose_beside(sources: dict[str, Study], eval_task: str) -> Study | None:
    """The training task's study, where an evaluated task's own study restarts stacking from a start configuration
    and that one from the place pose: its rates go beside ours."""
    from envs.tasks import model_task_of

    own, trained = source_of(sources, eval_task), sources[model_task_of(eval_task)]
    if own is trained or _stack_restart(own) != "start" or _stack_restart(trained) != "place_pose":
        return None
    return trained


def table_one_rows(sources: dict[str, Study]) -> pd.DataFrame:
    """One row per (evaluated task, variant): aggregate_success's columns for the cell in its source study, the
    study, the paper's value, where its rollouts record both criteria the strict criterion's strict_*, and where
    the row's stacking restarts from a start configuration the place-pose restart's place_pose_* (the same variant
    in the training task's study)."""
    variants = order_variants({v for s in sources.values() for v in s.variants})
    rows = []
    for eval_task in eval_tasks(sources):
        study = source_of(sources, eval_task)
        beside = _place_pose_beside(sources, eval_task)
        other = {r["variant"]: r for r in _cells(beside, variants, eval_task)} if beside is not None else {}
        for r in _cells(study, variants, eval_task):
            pose = other.get(r["variant"])
            rows.append({**r, "study": study.name, "paper": paper.paper_success(r["variant"], eval_task),
                         **cell_strict_rate(study, r),
                         **({f"place_pose_{k}": pose[k] for k in ("mean", "seed_low", "seed_high")}
                            if pose and pose["seeds"] else {})})
    return pd.DataFrame(rows)


def table_one_table(rows: pd.DataFrame, sources: dict[str, Study]) -> Table:
    """The rows as THE Table I: task, variant, ours (mean over seeds; † when a seed is missing), the seed-level
    interval, each seed's rate, the strict criterion (only where some row has it), the paper's, the study."""
    if rows.empty:
        return Table(NAME, TITLE, ["task", "variant", "ours", "paper"], [[GAP, "–", GAP, "–"]],
                     ["gap: no training task of Table I in the listed studies."])
    strict = "strict_mean" in rows and rows["strict_mean"].notna().any()
    pose = "place_pose_mean" in rows and rows["place_pose_mean"].notna().any()
    columns = ["task", "variant", "ours", stats.SEED_COLUMN, "per seed", *([STRICT_COLUMN] if strict else []),
               *([PLACE_POSE_COLUMN] if pose else []), "paper", "study"]
    out = []
    for r in rows.to_dict("records"):
        have = bool(r["seeds"])
        ours = (stats.pct(r["mean"]) + ("†" if r["status"] == "partial" else "")) if have else GAP
        cells = [paper.task_label(r["eval_task"]), paper.variant_label(r["variant"]), ours,
                 stats.interval(r["seed_low"], r["seed_high"]) if have else "–",
                 " / ".join(stats.pct(v) for v in r["seed_rates"].values()) or "–"]
        if strict:
            cells.append(beside_cell(r))
        if pose:
            cells.append(beside_cell(r, "place_pose_"))
        out.append([*cells, stats.pct(r["paper"]) if r["paper"] is not None else "–", r["study"]])
    return Table(NAME, TITLE, columns, out, _notes(rows, sources, strict, pose), rows.drop(columns=["seed_rates"]))


def _notes(rows: pd.DataFrame, sources: dict[str, Study], strict: bool, pose: bool) -> list[str]:
    from envs.tasks import evaluation_tasks

    per_seed = sorted({int(n / s) for n, s in zip(rows["n"], rows["seeds"], strict=True) if s})
    shown = list(dict.fromkeys(rows["eval_task"]))
    by_study: dict[str, tuple[Study, list[str]]] = {}
    for task in training_sources(sources):
        for t in shown:
            if t in evaluation_tasks(task):
                study = source_of(sources, t)
                by_study.setdefault(study.name, (study, []))[1].append(t)
    where = "; ".join(f"{', '.join(map(paper.task_label, tasks))}: study `{study.name}` ({study.profile} profile, "
                      f"seeds {', '.join(map(str, study.seeds))})" for study, tasks in by_study.values())
    notes = [f"Ours: {where}. Every rollout in pybullet physics, "
             f"{' or '.join(map(str, per_seed)) or 'no'} episodes per seed and task, seed k of every variant on the "
             "same episodes.",
             f"ours: mean over seeds of each seed's success rate; {stats.SEED_COLUMN}: the seed-level interval of "
             "a rate (experiments.stats.rate_interval; the one to read; none with one seed); per seed: seed 0 / 1 "
             "/ ...",
             f"paper: Table I of Zhang et al. 2019, {paper.TABLE_I_ROLLOUTS} rollouts per cell; reacher in "
             "simulation, pick-and-place and stacking on the real robot; – where the paper gives no success rate.",
             "† some seeds missing or failed (statistics over the rest); gap: the study listed for the task holds "
             "no finished run of the cell."]
    place = sources.get(PLACE_TASK)
    if place is not None and not judged_on_placed(place.ok[place.ok["task"] == PLACE_TASK]):
        judged = [t for t in by_study[place.name][1] if t in evaluation_tasks(PLACE_TASK)]
        notes.append(f"{', '.join(map(paper.task_label, judged))} in `{place.name}`: ours is the strict criterion "
                     "(every check, the last grip command open as well); the study did not judge its rollouts on "
                     "the block alone.")
    if strict:
        notes.append(STRICT_NOTE)
    if pose:
        notes.append(PLACE_POSE_NOTE)
    notes += [f"{paper.variant_label(r.variant)} / {paper.task_label(r.eval_task)}: {r.note}"
              for r in rows.itertuples() if r.note]
    return notes


def table_one_figure(rows: pd.DataFrame, folder: Path) -> FigureResult:
    """One group of bars per evaluated task with a finished cell, one bar per variant: ours (mean over seeds) with
    the seed-level 95 % interval, the paper's value as a marker; a cell without a finished run says gap."""
    if rows.empty or not rows["seeds"].any():
        return gap(NAME, FIGURE_TITLE, "no finished cell in the listed studies")
    tasks = [t for t in dict.fromkeys(rows["eval_task"]) if rows.loc[rows["eval_task"] == t, "seeds"].any()]
    variants = list(dict.fromkeys(rows["variant"]))
    width = 0.8 / len(variants)
    fig, ax = plt.subplots(figsize=(max(7.0, 1.45 * len(tasks) + 1.5), 4.0))
    for j, variant in enumerate(variants):
        got = rows[rows["variant"] == variant].set_index("eval_task").reindex(tasks)
        x = np.arange(len(tasks)) + (j - (len(variants) - 1) / 2) * width
        mean = 100 * got["mean"].to_numpy(float)
        err = np.clip([mean - 100 * got["seed_low"].to_numpy(float), 100 * got["seed_high"].to_numpy(float) - mean],
                      0, None)
        ax.bar(x, np.nan_to_num(mean), width, yerr=np.nan_to_num(err), capsize=2,
               color=variant_color(variant, variants), label=f"{paper.variant_label(variant)} (ours)")
        for xi, seeds in zip(x, got["seeds"].fillna(0), strict=True):
            if not seeds:
                ax.text(xi, 2, GAP, rotation=90, ha="center", va="bottom", color="#c00", fontsize=7)
        ref = [paper.paper_success(variant, t) for t in tasks]
        if any(r is not None for r in ref):
            ax.scatter(x, [np.nan if r is None else 100 * r for r in ref], marker="D", s=26, facecolor="white",
                       edgecolor="black", zorder=5, clip_on=False, label="paper (Table I)" if j == 0 else None)
    ax.set_xticks(range(len(tasks)), [paper.task_label(t).replace(" ", "\n", 1) if len(t) > 12 else
                                      paper.task_label(t) for t in tasks], fontsize=8)
    ax.set_ylabel("success (%)")
    ax.set_ylim(0, 105)
    ax.grid(axis="y", alpha=0.3)
    ax.set_title("Table I: ours (bars: mean over seeds, whiskers: seed-level 95 %) and the paper's (◇)", fontsize=10)
    handles, labels = ax.get_legend_handles_labels()
    order = sorted(range(len(labels)), key=lambda i: labels[i].startswith("paper"))
    ax.legend([handles[i] for i in order], [labels[i] for i in order], loc="upper left", bbox_to_anchor=(1.0, 1.0))
    return save(fig, folder, NAME, FIGURE_TITLE)


def train_time_across(sources: dict[str, Study]) -> Table:
    """Training wall time per cell of Table I: one row per training task, from its source study, with the
    iterations it planned."""
    variants = order_variants({v for s in sources.values() for v in s.variants})
    rows = []
    for task, study in training_sources(sources).items():
        summary = tables.train_time_summary(study)
        runs = study.children[study.children["task"] == task]
        iters = runs["params.train.iters"].dropna().unique() if "params.train.iters" in runs else []
        cells = []
        for v in variants:
            hit = summary[(summary["task"] == task) & (summary["variant"] == v)] if not summary.empty else summary
            cells.append(tables.train_time_cell(hit.iloc[0]) if len(hit) else GAP)
        rows.append([paper.task_label(task), study.name, ", ".join(f"{int(float(i)):,}" for i in iters) or "–", *cells])
    return Table("train_time_across", "Training time per cell of Table I (seconds)",
                 ["task", "study", "iterations", *map(paper.variant_label, variants)], rows, [tables.TRAIN_TIME_NOTE])


__all__ = ["NAME", "TITLE", "eval_tasks", "own_sources", "source_of", "table_one_figure", "table_one_rows",
           "table_one_table", "train_time_across", "training_sources"]
