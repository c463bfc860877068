"""Registered tasks: importing this package imports every module in envs/tasks/
(envs.tasks.registry.discover), so a new task is one new module with an @register class.

The Task interface (base) and the registry (registry); the tasks: reacher and its changing goal (reacher), the
multimodal reachers (reacher_obstacle_multimodal, reacher_posture_multimodal), circle drawing (circle),
pick-and-place (pickplace), its changing goal (pickplace_changing_goal) and stacking (stack, with its protocol
between blocks in stack_protocol); the IK experts' shared pieces (expert) and the pick-and-place expert
(pickplace_expert).

Adding a task: envs/tasks/<name>.py with a `@register`-ed subclass of envs.tasks.base.Task
(the interface and its defaults are documented there) and tests/test_tasks_<name>.py.
An evaluation-only task sets `model_task` to the training task whose model it uses."""

from envs.tasks.base import Demos, Episode, StateLayout, Task
from envs.tasks.registry import (
    TASKS,
    UnknownTaskError,
    discover,
    evaluation_tasks,
    get_task,
    model_task_of,
    register,
    task_class,
    task_names,
    tasks_with_panel,
    training_tasks,
)

discover()

__all__ = ["TASKS", "Demos", "Episode", "StateLayout", "Task", "UnknownTaskError", "evaluation_tasks", "get_task",
           "model_task_of", "register", "task_class", "task_names", "tasks_with_panel", "training_tasks"]
