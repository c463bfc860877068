"""Multimodal demonstrations: per task whose runs logged a rate per mode, the success of each
variant with its intervals beside the split of its rollouts over the modes (and between them), and a top view
of the tool-tip paths coloured by the mode each took, next to the demonstrations' paths coloured by theirs.

A task counts as multimodal from the data: its runs logged `<task>/mode_<name>_mean` metrics (the means of
the per-episode one-hot mode labels of its evaluate), and its rollouts artifacts carry the labels per episode
(`mode_<name>`, `between`; see the contract in reports/data/store.py)."""

from __future__ import annotations

import logging
import math
import re
from pathlib import Path

import numpy as np
import pandas as pd

from experiments.stats import SEED_COLUMN, WILSON_COLUMN, interval, pct, success_over_seeds
from reports.data.store import Study, order_variants
from reports.plotting import FigureResult, gap, mark_gap, panel_grid, save

log = logging.getLogger(__name__)

MODE_METRIC = re.compile(r"^metrics\.(?P<task>[^/]+)/mode_(?P<mode>.+)_mean$")
MODE_COLOURS = ("tab:blue", "tab:orange", "tab:green", "tab:purple")
BETWEEN_COLOUR = "0.6"  # grey: averaged between the modes, collided, or no mode at all


def _registry_modes(task: str) -> tuple[str, ...]:
    """The task class's mode names in its label order (index = demonstration label), if the registry has it."""
    try:
        from envs.tasks import task_class

        return tuple(getattr(task_class(task), "modes", ()))
    except Exception:  # noqa: BLE001 - a task the registry does not know keeps the data's order
        return ()


def multimodal_tasks(study: Study) -> dict[str, list[str]]:
    """Evaluated tasks whose runs logged per-mode rates -> their mode names (the task's label order when the
    registry knows it, else alphabetical)."""
    found: dict[str, set[str]] = {}
    for col in study.children.columns:
        m = MODE_METRIC.match(col)
        if m and study.children[col].notna().any():
            found.setdefault(m.group("task"), set()).add(m.group("mode"))
    out = {}
    for task, modes in sorted(found.items()):
        order = [m for m in _registry_modes(task) if m in modes]
        out[task] = order + sorted(modes - set(order))
    return out


def _pooled(runs: pd.DataFrame, task: str, name: str) -> float:
    """A per-episode rate pooled over runs (each run's mean weighted by its rollouts); NaN if never logged."""
    col, n_col = f"metrics.{task}/{name}_mean", f"metrics.{task}/n_rollouts"
    if col not in runs:
        return math.nan
    got = runs[[col, n_col]].dropna()
    return float((got[col] * got[n_col]).sum() / got[n_col].sum()) if len(got) and got[n_col].sum() else math.nan


def multimodal_table(study: Study) -> pd.DataFrame:
    """One row per (multimodal task, variant), variants in order_variants' order: success (mean over seeds),
    the pooled Wilson interval (ci_low, ci_high) and the seed-level t-interval (seed_low, seed_high)
    as experiments.stats.success_over_seeds gives them, n (rollouts) and seeds, then the fraction of rollouts in each
    mode (`mode_<name>`), `between` and `collided` (NaN where the task has no such label). Fractions 0..1;
    a variant without a finished run is a row with seeds = 0."""
    rows = []
    for task, modes in multimodal_tasks(study).items():
        rate, n_col = f"metrics.{task}/success_rate", f"metrics.{task}/n_rollouts"
        ok = study.ok
        ok = ok[ok[rate].notna() & ok[n_col].notna()] if rate in ok and n_col in ok else ok.iloc[:0]
        for variant in study.variants:
            runs = ok[ok["variant"] == variant]
            agg = success_over_seeds({int(s): (r, n) for s, r, n in zip(runs["seed"], runs[rate], runs[n_col],
                                                                         strict=True)})
            row = {"eval_task": task, "variant": variant, "success": agg["mean"], "ci_low": agg["ci_low"],
                   "ci_high": agg["ci_high"], "seed_low": agg["seed_low"], "seed_high": agg["seed_high"],
                   "n": agg["n"], "seeds": agg["seeds"]}
            row.update({f"mode_{m}": _pooled(runs, task, f"mode_{m}") for m in modes})
            row.update({k: _pooled(runs, task, k) for k in ("between", "collided")})
            rows.append(row)
    fixed = ["eval_task", "variant", "success", "ci_low", "ci_high", "seed_low", "seed_high", "n", "seeds"]
    modes = list(dict.fromkeys(k for r in rows for k in r if k.startswith("mode_")))
    return pd.DataFrame(rows, columns=[*fixed, *modes, "between", "collided"] if rows else fixed)


def rollout_feedback_of(study: Study) -> str:
    """What the study's rollouts fed back, from its runs' params (sample with its temperature, e.g.
    "sample T=0.4"); '?' when the runs logged none, 'mixed' when they differ."""
    c = study.ok
    if "params.eval.feedback" not in c:
        return "?"
    train = c["params.train.feedback"] if "params.train.feedback" in c else pd.Series("", index=c.index)
    temp = c["params.train.temperature"] if "params.train.temperature" in c else pd.Series("1.0", index=c.index)
    seen = set()
    for ev, tr, t in zip(c["params.eval.feedback"], train, temp, strict=True):
        used = "sample" if tr == "sample" else ev  # as experiments.evaluation.rollout_feedback
        seen.add(f"sample T={float(t):g}" if used == "sample" else str(used))
    return seen.pop() if len(seen) == 1 else ("?" if not seen else "mixed")


def feedback_table(studies: list[Study]) -> pd.DataFrame:
    """multimodal_table of each study with its `feedback` and `study` columns first: the rollout feedbacks side
    by side (rows by task, variant, then the studies' order)."""
    parts = [multimodal_table(s).assign(feedback=rollout_feedback_of(s), study=s.name) for s in studies]
    if not parts:
        return pd.DataFrame()
    out = pd.concat(parts, ignore_index=True)
    out["_v"] = out["variant"].map({v: i for i, v in enumerate(order_variants(out["variant"].unique()))})
    out["_s"] = out["study"].map({s.name: i for i, s in enumerate(studies)})
    out = out.sort_values(["eval_task", "_v", "_s"], kind="stable").drop(columns=["_v", "_s"])
    first = ["feedback", "study"]
    return out[[*first, *(c for c in out.columns if c not in first)]].reset_index(drop=True)


def multimodal_markdown(table: pd.DataFrame, variant_label=str) -> str:
    """multimodal_table as Markdown, one table per task; percentages, '–' where a task has no such label."""
    out = []
    for task, part in table.groupby("eval_task", sort=False):
        modes = [c for c in part.columns if c.startswith("mode_") and part[c].notna().any()]
        extra = [c for c in ("between", "collided") if c in part and part[c].notna().any()]
        lead = ["feedback"] if "feedback" in part else []
        head = [*lead, "variant", "success", SEED_COLUMN, WILSON_COLUMN, "n", "seeds",
                *(m.removeprefix("mode_") for m in modes), *extra]
        lines = [f"**{task}**", "", "| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
        for r in part.to_dict("records"):
            entries = [*(str(r[c]) for c in lead), variant_label(r["variant"]), pct(r["success"]),
                       interval(r["seed_low"], r["seed_high"]), interval(r["ci_low"], r["ci_high"]),
                       str(int(r["n"])), str(int(r["seeds"])),
                       *(pct(r[c]) for c in [*modes, *extra])]
            lines.append("| " + " | ".join(entries) + " |")
        out.append("\n".join(lines))
    return "\n\n".join(out) + "\n"


# ------------------------------------------------------------------------------------------------- figure
def _mode_of_rows(arrays: dict[str, np.ndarray], modes: list[str]) -> np.ndarray | None:
    """Index of each rollout's mode in `modes`, -1 for between; None when the artifact has no labels."""
    if not all(f"mode_{m}" in arrays for m in modes):
        return None
    labels = np.stack([arrays[f"mode_{m}"] for m in modes], axis=1) >= 0.5
    return np.where(labels.any(axis=1), labels.argmax(axis=1), -1)


def _draw_paths(ax, tips: list[np.ndarray], labels: np.ndarray, modes: list[str]) -> None:
    # one LineCollection and one scatter for all paths (two Line2D artists per rollout, thousands per
    # figure, made it the slowest figure to save); between (grey) first, under the modes' colours
    from matplotlib.collections import LineCollection
    from matplotlib.colors import to_rgba

    drawn = []  # (finite x-y path, colour), paths with no finite point left out
    for i in np.argsort(labels >= 0, kind="stable"):
        path = tips[i][np.isfinite(tips[i]).all(axis=1)][:, :2]
        colour = BETWEEN_COLOUR if labels[i] < 0 else MODE_COLOURS[labels[i] % len(MODE_COLOURS)]
        if len(path):
            drawn.append((path, to_rgba(colour)))
    if drawn:
        paths, colours = zip(*drawn, strict=True)
        ax.add_collection(LineCollection(paths, colors=colours, lw=0.7, alpha=0.6))
        ends = np.array([path[-1] for path in paths])
        ax.scatter(ends[:, 0], ends[:, 1], s=1.5, c=colours, linewidths=0)
    ax.autoscale_view()
    shares = [f"{m} {np.mean(labels == k):.0%}" for k, m in enumerate(modes)] + [f"between {np.mean(labels < 0):.0%}"]
    ax.text(0.02, 0.02, ", ".join(shares), transform=ax.transAxes, fontsize=7, va="bottom")


def _demo_paths(study: Study, task: str, modes: list[str]) -> tuple[list[np.ndarray], np.ndarray] | str:
    """Tip paths of the demonstrations the task's runs trained on and their mode index; a reason if none."""
    from envs.datasets import load_demos
    from envs.kinematics import tip_position_np
    from envs.tasks import task_class

    model_task = study.model_task_of(task)
    runs = study.ok[study.ok["task"] == model_task]

    def param(key: str):  # the first finished run's, None if not logged
        got = runs[key].dropna() if key in runs else ()
        return int(got.iloc[0]) if len(got) else None

    n_demos, seed = param("params.data.n_demos"), param("params.dataset_seed")
    opts = {"n_demos": n_demos} if n_demos is not None else {}
    seed = seed or 0
    try:
        demo_task = task_class(model_task)(**opts)
        demos = load_demos(demo_task, seed)
        labels = demo_task.demo_modes(demos) if hasattr(demo_task, "demo_modes") else demos.meta.get("modes")
    except Exception as exc:  # noqa: BLE001 - the figure keeps its other panels
        return f"no demonstrations of {model_task}: {exc}"
    if labels is None:
        return f"{model_task}'s demonstrations carry no mode labels"
    names = list(getattr(demo_task, "modes", modes))
    index = np.array([modes.index(names[k]) if 0 <= k < len(names) and names[k] in modes else -1 for k in labels])
    tips = [tip_position_np(demos.q[i, : n + 1]) for i, n in enumerate(demos.lengths)]
    return tips, index


def mode_paths(study: Study, folder: Path) -> FigureResult:
    """mode_paths.png/.pdf: per multimodal task a row of top views (x-y, metres, robot base frame): the
    demonstrations' tip paths coloured by their mode, then one panel per variant with its rollouts' paths
    (all seeds) coloured by the mode each took, grey between. Missing rollouts or labels are gap panels."""
    name, title = "mode_paths", "Tool-tip paths coloured by mode (multimodal demonstrations)"
    tasks = multimodal_tasks(study)
    if not tasks:
        return gap(name, title, "no evaluated task logged per-mode rates")
    variants = study.variants
    cols = 1 + len(variants)
    fig, axes = panel_grid(len(tasks) * cols, 3.2, 3.0, max_cols=cols)
    partial = []
    for row, (task, modes) in enumerate(tasks.items()):
        panels = axes.flat[row * cols:(row + 1) * cols]
        demo = _demo_paths(study, task, modes)
        if isinstance(demo, str):
            mark_gap(panels[0], demo)
            partial.append(f"{task}: demonstrations")
        else:
            _draw_paths(panels[0], *demo, modes)
        panels[0].set_title(f"{task}\ndemonstrations", fontsize=8)
        for ax, variant in zip(panels[1:], variants, strict=True):
            runs = study.ok[study.ok["variant"] == variant]
            tips, labels = [], []
            for run_id in runs["run_id"]:
                arrays = study.rollouts(run_id, task)
                got = None if arrays is None else _mode_of_rows(arrays, modes)
                if got is not None:
                    tips.extend(arrays["tip"])
                    labels.extend(got)
            ax.set_title(variant, fontsize=9)
            if not tips:
                mark_gap(ax, "no rollouts with mode labels")
                partial.append(f"{task}: {variant}")
                continue
            _draw_paths(ax, tips, np.array(labels), modes)
        for ax in panels:
            ax.set_aspect("equal", adjustable="datalim")
            ax.set_xlabel("x (m)", fontsize=8)
            ax.set_ylabel("y (m)", fontsize=8)
            ax.tick_params(labelsize=7)
        handles = [panels[0].plot([], [], color=MODE_COLOURS[k % len(MODE_COLOURS)], label=m)[0]
                   for k, m in enumerate(modes)]
        handles.append(panels[0].plot([], [], color=BETWEEN_COLOUR, label="between")[0])
        panels[-1].legend(handles=handles, loc="upper right", fontsize=7)
    fig.suptitle(title)
    return save(fig, folder, name, title, partial)
