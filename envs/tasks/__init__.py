"""Registered tasks. Importing this package registers the built-in ones (one import per task module)."""

import envs.tasks.circle  # noqa: F401
import envs.tasks.pickplace  # noqa: F401
import envs.tasks.reacher  # noqa: F401
import envs.tasks.reacher_obstacle_multimodal  # noqa: F401
import envs.tasks.reacher_posture_multimodal  # noqa: F401
from envs.tasks.base import TASKS, Demos, Episode, StateLayout, Task, UnknownTaskError, get_task, register

__all__ = ["TASKS", "Demos", "Episode", "StateLayout", "Task", "UnknownTaskError", "get_task", "register"]
