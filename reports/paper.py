"""The paper's reported numbers (Zhang et al. 2019, see shared/PAPER.md), as data to print beside ours."""

from __future__ import annotations

# Table I: success rate over 20 rollouts (reacher in simulation; pick-and-place and stacking on the real robot).
TABLE_I: dict[str, dict[str, float]] = {
    "lstm": {"reacher": 0.80, "pick-place": 0.00, "stack": 0.00},
    "ac-lstm": {"reacher": 0.90, "pick-place": 0.50, "stack": 0.25},
    "lstm-mdn": {"reacher": 0.90, "pick-place": 0.60, "stack": 0.30},
    "ac-lstm-mdn": {"reacher": 1.00, "pick-place": 1.00, "stack": 0.80},
}
TABLE_I_ROLLOUTS = 20
TABLE_I_SETTING = {"reacher": "simulation", "pick-place": "real robot", "stack": "real robot"}

# Variant names as the paper writes them.
VARIANT_LABELS = {"lstm": "LSTM", "ac-lstm": "a.c. LSTM", "lstm-mdn": "LSTM-MDN", "ac-lstm-mdn": "a.c. LSTM-MDN"}

# The tasks of the extended success table, in column order, with display names.
SUCCESS_TASKS: dict[str, str] = {
    "reacher": "reacher",
    "pick-place": "pick-and-place",
    "stack": "stacking",
    "reacher-changing-goal": "changing-goal reacher",
    "pick-place-changing-goal": "changing-goal pick-and-place",
}

# Circle drawing: average RMSE per radius (cm -> value; the paper does not state the unit), the bound on the
# radial error at any point (% of r), and STM generation speed relative to solving the circle with IK.
CIRCLE_RMSE: dict[float, float] = {5.0: 0.017, 10.0: 0.028, 15.0: 0.110}
CIRCLE_RMSE_UNIT_NOTE = "unit unstated in the paper"
CIRCLE_MAX_RADIAL_ERROR_PCT = 10.0
CIRCLE_TRAINING_RADII_CM = (5.0, 20.0)  # demonstrations cover radii 5-20 cm
STM_SPEEDUP_OVER_IK = 2.0

# Reacher success (the gripper within 5 cm of the goal at the end) is defined once, by the task:
# envs.tasks.reacher.SUCCESS_RADIUS (imported where needed: importing envs.tasks loads torch and pybullet).


def variant_label(name: str) -> str:
    return VARIANT_LABELS.get(name, name)


def task_label(name: str) -> str:
    """The task's display name (Task.label); a name no task registers stays as it is."""
    from envs.tasks import UnknownTaskError, task_class  # here: it loads torch and pybullet

    try:
        return task_class(name).label
    except UnknownTaskError:
        return name


def paper_success(variant: str, task: str) -> float | None:
    """The paper's success rate of a variant on a task, or None where the paper has none."""
    return TABLE_I.get(variant, {}).get(task)
