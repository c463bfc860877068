"""Registered tasks: importing this package imports every module in envs/tasks/
(envs.tasks.registry.discover), so a new task is one new module with an @register class."""

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
