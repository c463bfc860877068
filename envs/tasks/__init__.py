"""Registered tasks. Importing this package registers the built-in ones (one import per task module)."""

from envs.tasks import reacher  # noqa: F401
from envs.tasks.base import TASKS, Demos, Episode, StateLayout, Task, UnknownTaskError, get_task, register

__all__ = ["TASKS", "Demos", "Episode", "StateLayout", "Task", "UnknownTaskError", "get_task", "register"]
