"""Where the changing-goal reacher's episodes fail, read from the rollouts themselves:
{{ goal_switch("reacher", "STUDY", "STUDY", ...) }} in a RESULTS template. Per study (labelled by its setting, as
the lever table labels it: reports.analyses.levers) and variant, over every finished seed's changing-goal episodes: the
success rate; of the failures, the share that never set off for the new goal (under SET_OFF of the way at the
end: the switch ignored) and the share still moving at the end (on the way, too slow); the median progress
toward the new goal at the end and the median number of steps after the switch to half-way. The figure draws
the median remaining distance to the new goal against the steps after the switch, beside minimum-jerk reaches
of the expert's lengths: what an imitation of the expert would do."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reports import paper
from reports.analyses.levers import in_variant_order, rollout_rows
from reports.data.store import Study, order_variants
from reports.plotting import FigureResult, gap, legend_below, panel_grid, plt, save, variant_color

NAME, TITLE = "goal_switch", "Changing-goal reacher: distance to the new goal after the switch"
EVAL_TASK = "reacher-changing-goal"  # its success is the tip at the new goal, so the tip's path says why it failed
MOVING = 0.002  # m per step (2 cm/s at 0.1 s steps): faster than this over the last 5 steps is "still moving"
TAIL = 5  # steps over which the end speed is measured
SET_OFF = 0.1  # progress toward the new goal under which a failed episode never set off


def episode_facts(arrays: dict[str, np.ndarray]) -> pd.DataFrame:
    """One row per episode of a changing-goal rollouts artifact that switched (switch_step >= 0): success, the
    end's distance to the new and the first goal, the end speed, the progress toward the new goal at the end
    (1 - end distance / distance at the switch), the steps after the switch to half-way (NaN if never) and the
    remaining fraction of the distance at each step after the switch."""
    tip, k = np.asarray(arrays["tip"], float), np.asarray(arrays["switch_step"], int)
    goal, new_goal = np.asarray(arrays["goal"], float), np.asarray(arrays["new_goal"], float)
    success = np.asarray(arrays["success"], float)
    rows = []
    for i in np.flatnonzero(k >= 0):
        d = np.linalg.norm(tip[i, k[i]:] - new_goal[i], axis=-1)
        remaining = d / d[0] if d[0] > 0 else np.zeros_like(d)
        half = np.flatnonzero(remaining <= 0.5)
        rows.append({"success": success[i], "end_to_new": d[-1],
                     "end_to_first": float(np.linalg.norm(tip[i, -1] - goal[i])),
                     "end_speed": float(np.linalg.norm(tip[i, -1] - tip[i, -1 - TAIL]) / TAIL),
                     "progress": 1.0 - remaining[-1], "steps_to_half": float(half[0]) if len(half) else np.nan,
                     "remaining": remaining})
    return pd.DataFrame(rows)


def switch_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (study, variant) with changing-goal rollouts of `task`'s models
    (reports.analyses.levers.rollout_rows)."""
    return rollout_rows(studies, task, EVAL_TASK, episode_facts)


def switch_table(agg: pd.DataFrame) -> pd.DataFrame:
    """The failures' anatomy, one row per (variant, study), as strings."""
    if agg.empty:
        return pd.DataFrame()
    rows = []
    for r in in_variant_order(agg).itertuples():
        f = r.facts
        failed = f[f["success"] < 1]
        rows.append({
            "variant": paper.variant_label(r.variant), "setting": r.setting,
            "success": f"{100 * f['success'].mean():.0f}%",
            "failures that never set off": _share(failed["progress"] < SET_OFF),
            "failures still moving": _share(failed["end_speed"] > MOVING),
            "median progress at the end": f"{100 * f['progress'].median():.0f}%",
            "median steps to half-way": _steps(f["steps_to_half"]),
            "episodes": str(len(f)), "seeds": str(r.seeds),
        })
    return pd.DataFrame(rows)


def _share(mask: pd.Series) -> str:
    return f"{100 * mask.mean():.0f}%" if len(mask) else "–"


def _steps(s: pd.Series) -> str:
    """The median number of steps, counting never as more than any (NaN sorts last)."""
    return "–" if s.isna().sum() * 2 >= len(s) else f"{s.fillna(np.inf).median():.0f}"


def min_jerk_remaining(steps: int, length: int) -> np.ndarray:
    """Remaining fraction of a minimum-jerk reach of `steps` steps at each of `length` steps from its start."""
    tau = np.clip(np.arange(length) / steps, 0.0, 1.0)
    return 1.0 - (10 * tau**3 - 15 * tau**4 + 6 * tau**5)


def switch_figure(agg: pd.DataFrame, task: str, folder: Path) -> FigureResult:
    """One panel per study: the median remaining fraction of the distance to the new goal against the steps
    after the switch, a line per variant, and minimum-jerk reaches of the task's shortest and longest expert
    reach as the band an imitation of the expert would lie in."""
    if agg.empty:
        return gap(NAME, TITLE, f"no changing-goal rollouts of {task} models in the named studies")
    from envs.tasks import task_class  # here: it loads torch and pybullet

    expert = task_class(task)()
    demo_steps = (expert.min_steps, expert.max_steps)
    studies = list(dict.fromkeys(agg["study"]))
    variants = order_variants(agg["variant"].unique())
    fig, axes = panel_grid(len(studies), 4.2, 3.4)
    for ax, study in zip(axes.flat, studies, strict=False):
        mine = agg[agg["study"] == study]
        length = max(len(x) for f in mine["facts"] for x in f["remaining"])
        ref = [min_jerk_remaining(n, length) for n in demo_steps]
        ax.fill_between(np.arange(length), ref[0], ref[1], color="0.85",
                        label=f"expert reach ({demo_steps[0]}-{demo_steps[1]} steps)")
        for r in mine.itertuples():
            curves = np.array([np.pad(x, (0, length - len(x)), constant_values=np.nan) for x in r.facts["remaining"]])
            ax.plot(np.nanmedian(curves, axis=0), color=variant_color(r.variant, variants),
                    label=paper.variant_label(r.variant))
        ax.axhline(0.0, color="0.5", lw=0.5)
        ax.set_title(f"{study}\n{mine['setting'].iloc[0]}", fontsize=8)
        ax.set_xlabel("steps after the switch")
        ax.set_ylabel("distance left / at the switch")
        ax.set_ylim(-0.05, 1.05)
        ax.grid(alpha=0.3)
    legend_below(fig, axes.flat[0])
    fig.suptitle(f"{TITLE} (median over episodes and seeds)")
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
