"""The placeholders over several studies of one training task ({{ data_scaling(...) }}, {{ lever(...) }},
{{ goal_switch(...) }}, {{ stacking(...) }}, {{ pick_place_failures(...) }}, {{ placement(...) }},
{{ comparisons(...) }}): how each builds its rows, table and figure, and the studies they name, a milestones study's
stage included as NAME@ITERATION."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import pandas as pd

from experiments.runtime.tracking import MILESTONE_ITERATION
from experiments.stats import SUCCESS_NOTE
from reports.analyses import data_scaling, goal_switch, levers, pick_place_failures, placement, stacking
from reports.data.store import StoreError, Study, file_safe
from reports.plotting import FigureResult
from reports.results import comparisons
from reports.results.template import MULTI_STUDY


@dataclass(frozen=True)
class AcrossStudies:
    """How a placeholder over several studies of one training task builds its rows, table and figure."""

    name: str  # the figure's name
    rows: Callable[[list[Study], str], pd.DataFrame]
    table: Callable[[pd.DataFrame], pd.DataFrame]
    figure: Callable[[pd.DataFrame, str, Path], FigureResult] | None  # None: a table alone
    error: type[Exception]  # what rows raises when the studies cannot be put side by side
    note: Callable[[str], str]  # the table's columns explained, for a task
    out_name: Callable[[str, list[Study]], str]  # the figure's file name


ACROSS = {  # template.MULTI_STUDY's placeholders
    "data_scaling": AcrossStudies(
        data_scaling.NAME, data_scaling.scaling_rows, data_scaling.scaling_table, data_scaling.scaling_figure,
        data_scaling.DataScalingError,
        lambda task: f"demos: the demonstrations the {task} model trained on; {SUCCESS_NOTE}",
        lambda task, studies: f"{file_safe(task)}_data_scaling"),
    "lever": AcrossStudies(
        levers.NAME, levers.lever_rows, levers.lever_table, levers.lever_figure, levers.LeverError,
        lambda task: (f"setting: what sets the study's {task} runs of that variant apart from the other studies "
                      f"named here (their params; one not logged is at its default); {SUCCESS_NOTE}"),
        lambda task, studies: f"{file_safe(task)}_lever_{file_safe(studies[-1].name)}"),
    "goal_switch": AcrossStudies(
        goal_switch.NAME, goal_switch.switch_rows, goal_switch.switch_table, goal_switch.switch_figure,
        levers.LeverError,
        lambda task: (f"the {goal_switch.EVAL_TASK} episodes of the {task} models, pooled over seeds; setting: as "
                      f"in the lever table; never set off (under {goal_switch.SET_OFF:.0%} of the way to the new "
                      f"goal at the end), still moving (faster than {goal_switch.MOVING * 1000:g} mm per step over "
                      f"the last {goal_switch.TAIL}): shares of the failed episodes; progress: 1 - distance to the "
                      f"new goal at the end / at the switch; steps to half-way: after the switch, '–' when most "
                      f"never get there."),
        lambda task, studies: f"{file_safe(task)}_goal_switch_{file_safe(studies[-1].name)}"),
    "stacking": AcrossStudies(
        stacking.NAME, stacking.stacking_rows, stacking.stacking_table, stacking.stacking_figure, levers.LeverError,
        lambda task: (f"the {stacking.EVAL_TASK} episodes of the {task} models, pooled over seeds; setting: as in "
                      f"the lever table; came for block k: the tool tip within {stacking.REACH * 100:g} cm of the "
                      f"point where block k is grasped during its sub-episode (each next block starts where the "
                      f"last place ended); tower of at least k: blocks standing as a tower from the bottom up; "
                      f"closest approach: the tip's, to each block's grasp point."),
        lambda task, studies: f"{file_safe(task)}_stacking_{file_safe(studies[-1].name)}"),
    "pick_place_failures": AcrossStudies(
        pick_place_failures.NAME, pick_place_failures.failure_rows, pick_place_failures.failure_table,
        pick_place_failures.failure_figure, levers.LeverError,
        lambda task: (f"the pick-and-place and changing-goal pick-and-place episodes of the {task} models, pooled "
                      f"over seeds, each in the first stage it did not get through; setting: as in the lever table; "
                      f"never came for the block: the tool tip never within {stacking.REACH * 100:g} cm of the point "
                      f"where the block is grasped; off the goal: the block's bottom ends more than "
                      f"{pick_place_failures.XY_TOL * 100:g} cm from the goal in xy; not released: within that, yet "
                      f"failed, counted (episodes) by the first check failed: its height more than "
                      f"{pick_place_failures.Z_TOL * 100:g} cm off, tilted more than {pick_place_failures.MAX_TILT:g} "
                      f"rad, a finger on it, the tip within {pick_place_failures.AWAY * 100:g} cm of it, the last grip "
                      f"command closed (not recorded: rollouts from before tilt, finger contact and grip were kept); "
                      f"tip ends over the new goal: within {pick_place_failures.OVER * 100:g} cm in xy, of all "
                      f"changing-goal episodes."),
        lambda task, studies: f"{file_safe(task)}_pick_place_failures_{file_safe(studies[-1].name)}"),
    "placement": AcrossStudies(
        placement.NAME, placement.placement_rows, placement.placement_table, None, levers.LeverError, placement.note,
        lambda task, studies: ""),
    "comparisons": AcrossStudies(
        comparisons.TITLE, comparisons.paper_rows, comparisons.paper_table, None, comparisons.ComparisonError,
        lambda task: comparisons.NOTE, lambda task, studies: ""),
}
assert set(ACROSS) == set(MULTI_STUDY), "every multi-study placeholder of the template language is built here"


def whole_study(name: str) -> str:
    """The study a template's NAME@ITERATION is a stage of (NAME itself when it names no iteration)."""
    return name.partition("@")[0]


def at_iteration(study: Study, iteration: int) -> Study:
    """A milestones study's runs of the checkpoints kept at `iteration`, as a study named NAME@ITERATION
    (so that a table can set one stage of training beside a study trained that long)."""
    col = f"params.{MILESTONE_ITERATION}"
    kept = study.children[col].dropna().astype(int) if col in study.children else pd.Series(dtype=int)
    if iteration not in set(kept):
        listed = ", ".join(str(i) for i in sorted(set(kept))) or "none: not a milestones study"
        raise StoreError(f"study {study.name!r} has no runs at iteration {iteration} (kept: {listed})")
    return Study(study.experiment, {**study.parent, "tags.study_name": f"{study.name}@{iteration}"},
                 study.children[study.children[col].astype(float) == iteration], study.client)
