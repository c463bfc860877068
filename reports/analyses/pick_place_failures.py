"""Where the pick-and-place episodes fail, read from the rollouts themselves:
{{ pick_place_failures("pick-place", "STUDY", ...) }} in a RESULTS template. Per evaluated task (pick-and-place
and the changing-goal pick-and-place), study (labelled by its setting, as the lever table labels it:
reports.analyses.levers) and variant, over every finished seed's episodes, each episode in the first stage it
did not get through:
- never came for the block: the tool tip never within stacking.REACH of the point where the block is grasped;
- off the goal: the block's bottom ends more than XY_TOL (the task's own tolerance) from the goal in xy;
- not released: the block is within XY_TOL of the goal in xy, yet the episode failed (its height, tilt, the last
  grip command, a finger on it, or the tip within AWAY of it: the task's checks after the carry);
- placed: success.
The episodes not released are split by the first of the task's checks they fail (RELEASE_FAULTS): the block's
bottom more than Z_TOL off the goal's height, tilted more than MAX_TILT, a finger on it, the tip within AWAY of
it, or the last grip command closed; rollouts recorded before the last three were kept per episode leave those
as "not recorded". Of the episodes whose last grip command is closed, those where it shut again after opening
(the rollout's grip_closes above one, where recorded: a demonstration closes once, at the grasp) rather than
never opening. For a changing-goal task, the share of all
episodes whose tip ends over the new goal (within OVER in xy): the arm went there, with or without the block.
The figure stacks the four stages' shares per row."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reports import paper
from reports.analyses.levers import in_variant_order, rollout_rows
from reports.analyses.stacking import REACH, grasp_point
from reports.data.store import Study
from reports.plotting import FigureResult, gap, legend_below, plt, save

NAME, TITLE = "pick_place_failures", "Pick-and-place: the stage each episode fails at"
EVAL_TASKS = ("pick-place", "pick-place-changing-goal")
XY_TOL = 0.02  # m: envs.tasks.pickplace.XY_TOL, the success check's xy tolerance
Z_TOL = 0.01  # m: envs.tasks.pickplace.Z_TOL, the success check's height tolerance
MAX_TILT = 0.2  # rad: envs.tasks.pickplace.MAX_TILT
AWAY = 0.06  # m: envs.tasks.pickplace.AWAY, how far the tip must end from the placed block's centre
OVER = 0.03  # m: the tip's end within this of the new goal in xy is "over it"
STAGES = ("never came for the block", "off the goal", "not released", "placed")
STAGE_COLORS = ("#9e9e9e", "#e6862e", "#c9b200", "#3a8d3f")
RELEASE_FAULTS = ("height off", "tilted", "a finger on it", "tip at the block", "grip left closed", "not recorded")


def episode_facts(arrays: dict[str, np.ndarray], grasp: np.ndarray) -> pd.DataFrame:
    """One row per episode: its stage (STAGES), for an episode not released its fault (RELEASE_FAULTS, else ""),
    whether the grip command shut again after opening (NaN where not recorded) and whether the tip ends over the
    new goal (NaN where the episode has no goal switch)."""
    tip = np.asarray(arrays["tip"], float)
    success = np.asarray(arrays["success"], float) > 0.5
    came = np.linalg.norm(tip - grasp, axis=-1).min(axis=1) < REACH
    at_goal_xy = np.asarray(arrays["xy_error"], float) <= XY_TOL
    stage = np.select([success, ~came, ~at_goal_xy], [STAGES[3], STAGES[0], STAGES[1]], default=STAGES[2])
    fault = np.where(stage != STAGES[2], "", np.select(_release_checks(arrays, len(tip)), RELEASE_FAULTS[:-1],
                                                        default=RELEASE_FAULTS[-1]))
    over_new = np.full(len(tip), np.nan)
    if "new_goal" in arrays and "switch_step" in arrays:
        switched = np.asarray(arrays["switch_step"]) >= 0
        end_xy = np.linalg.norm(tip[:, -1, :2] - np.asarray(arrays["new_goal"], float)[:, :2], axis=-1)
        over_new[switched] = (end_xy < OVER)[switched]
    closes = _recorded(arrays, "grip_closes", len(tip))
    closed_again = np.where(np.isnan(closes), np.nan, closes > 1)
    return pd.DataFrame({"stage": stage, "release_fault": fault, "closed_again": closed_again,
                         "over_new_goal": over_new})


def _recorded(arrays: dict[str, np.ndarray], key: str, n: int) -> np.ndarray:
    """The per-episode fact `key` as floats, NaN for each of the n episodes where the rollouts predate it."""
    return np.asarray(arrays[key], float) if key in arrays else np.full(n, np.nan)


def _release_checks(arrays: dict[str, np.ndarray], n: int) -> list[np.ndarray]:
    """Per RELEASE_FAULTS but the last, where each episode fails that check (False where it is not recorded)."""
    def fact(key: str) -> np.ndarray:
        return _recorded(arrays, key, n)

    with np.errstate(invalid="ignore"):  # NaN: not recorded, compares False
        return [np.abs(fact("z_error")) > Z_TOL, fact("tilt") > MAX_TILT, fact("touching") > 0.5,
                fact("tip_to_block") < AWAY, fact("grip_closed") > 0.5]


def failure_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (evaluated task, study, variant) with rollouts of `task`'s models (levers.rollout_rows)."""
    grasp = grasp_point()
    frames = [rows.assign(eval_task=eval_task) for eval_task in EVAL_TASKS
              if not (rows := rollout_rows(studies, task, eval_task, lambda a: episode_facts(a, grasp))).empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def stage_shares(facts: pd.DataFrame) -> list[float]:
    """The share of the episodes at each of STAGES."""
    return [float((facts["stage"] == s).mean()) for s in STAGES]


def _percent(share: float) -> str:
    return "–" if np.isnan(share) else f"{100 * share:.0f}%"


def _in_order(agg: pd.DataFrame) -> pd.DataFrame:
    """agg's rows by evaluated task (EVAL_TASKS' order), then variant (the paper's order)."""
    return pd.concat([in_variant_order(agg[agg["eval_task"] == e]) for e in EVAL_TASKS])


def _closed_again(facts: pd.DataFrame) -> str:
    """"k of n": of the n not-released episodes failed by the grip command and with their closes recorded, the k
    whose command shut again after opening; "–" where there are none."""
    again = facts.loc[facts["release_fault"] == "grip left closed", "closed_again"].dropna()
    return f"{int(again.sum())} of {len(again)}" if len(again) else "–"


def failure_table(agg: pd.DataFrame) -> pd.DataFrame:
    """One row per (evaluated task, variant, study), as strings."""
    if agg.empty:
        return pd.DataFrame()
    rows = []
    for r in _in_order(agg).itertuples():
        faults = r.facts["release_fault"].value_counts()
        over = r.facts["over_new_goal"].dropna()
        rows.append({
            "task": paper.task_label(r.eval_task), "variant": paper.variant_label(r.variant), "setting": r.setting,
            **{s: _percent(v) for s, v in zip(STAGES, stage_shares(r.facts), strict=True)},
            "not released, by check: " + " / ".join(RELEASE_FAULTS): " / ".join(
                str(faults.get(f, 0)) for f in RELEASE_FAULTS),
            "grip left closed: shut again after opening": _closed_again(r.facts),
            f"tip ends over the new goal (< {OVER * 100:g} cm)": _percent(over.mean() if len(over) else np.nan),
            "episodes": str(len(r.facts)), "seeds": str(r.seeds),
        })
    return pd.DataFrame(rows)


def failure_figure(agg: pd.DataFrame, task: str, folder: Path) -> FigureResult:
    """One horizontal bar per (evaluated task, study, variant): the shares of the episodes at each stage, stacked."""
    if agg.empty:
        return gap(NAME, TITLE, f"no pick-and-place rollouts of {task} models in the named studies")
    ordered = _in_order(agg)
    labels = [f"{paper.task_label(r.eval_task)} · {paper.variant_label(r.variant)}\n{r.study}"
              for r in ordered.itertuples()]
    shares = np.array([stage_shares(r.facts) for r in ordered.itertuples()]) * 100
    fig, ax = plt.subplots(figsize=(8.0, 0.55 * len(labels) + 1.6))
    y = np.arange(len(labels))[::-1]
    left = np.zeros(len(labels))
    for k, (stage, color) in enumerate(zip(STAGES, STAGE_COLORS, strict=True)):
        ax.barh(y, shares[:, k], left=left, color=color, label=stage, height=0.7)
        left += shares[:, k]
    ax.set_yticks(y, labels, fontsize=7)
    ax.set_xlabel("episodes (%)")
    ax.set_xlim(0, 100)
    ax.grid(axis="x", alpha=0.3)
    legend_below(fig, ax)
    fig.suptitle(TITLE)
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
