"""The task registry: every module in the envs/tasks/ folder is imported once
(`discover`), and each class decorated with `@register` there is a task.

Adding a task is one new module in envs/tasks/ (plus its tests): no import line
anywhere else. This module imports no task module by name, and base.py (the Task class)
imports nothing of it: the task modules import both, so there is no import cycle.
"""

from __future__ import annotations

import importlib
import pkgutil
from pathlib import Path
from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from envs.tasks.base import Task

TASKS: dict[str, type[Task]] = {}
_PACKAGE = __name__.rpartition(".")[0]  # envs.tasks
_discovered = False


class UnknownTaskError(KeyError):
    def __str__(self) -> str:
        return self.args[0]


def register(cls: type[Task]) -> type[Task]:
    """Class decorator: make `cls` a task under `cls.name`. A second class under a name
    already taken is an error (two modules would silently shadow each other)."""
    if not cls.name:
        raise ValueError(f"{cls.__name__} has no name")
    old = TASKS.get(cls.name)
    if old is not None and (old.__module__, old.__qualname__) != (cls.__module__, cls.__qualname__):
        raise ValueError(f"task name {cls.name!r} is taken by {old.__module__}.{old.__qualname__}")
    TASKS[cls.name] = cls
    return cls


def discover() -> dict[str, type[Task]]:
    """Import every module of the envs/tasks/ folder once (their @register calls fill TASKS)."""
    global _discovered
    if not _discovered:
        _discovered = True
        for mod in pkgutil.iter_modules([str(Path(__file__).parent)]):
            if not mod.name.startswith("_"):
                importlib.import_module(f"{_PACKAGE}.{mod.name}")
    return TASKS


def task_class(name: str) -> type[Task]:
    """The registered class of a task; an unknown name lists the known ones."""
    discover()
    if name not in TASKS:
        raise UnknownTaskError(f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}")
    return TASKS[name]


def get_task(name: str, **overrides) -> Task:
    """Instantiate a registered task with constructor options."""
    return task_class(name)(**overrides)


def task_names() -> list[str]:
    """Every registered task, in report order (Task.report_rank, then name)."""
    discover()
    return sorted(TASKS, key=lambda n: (TASKS[n].report_rank, n))


def model_task_of(name: str) -> str:
    """The task whose demonstrations train the model `name` is evaluated with."""
    return task_class(name).model_task or name


def training_tasks() -> list[str]:
    """Tasks with their own demonstrations (a model is trained on each), sorted by name."""
    return sorted(n for n in discover() if model_task_of(n) == n)


def evaluation_tasks(model_task: str) -> list[str]:
    """Every task evaluated with the model trained on `model_task` (itself first, then by name)."""
    task_class(model_task)
    return [model_task, *sorted(n for n in TASKS if n != model_task and model_task_of(n) == model_task)]


def tasks_with_panel(panel: str) -> list[str]:
    """Tasks that draw the report panel `panel` (Task.panels), in report order."""
    return [n for n in task_names() if panel in TASKS[n].panels]
