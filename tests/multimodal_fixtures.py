"""Fixtures the multimodal task tests share: the task with a few demonstrations, its
demonstrations (seed 3) and 20 evaluation episodes (seed 7), module-scoped.
Use: `task, demos, episodes = task_fixtures("reacher-posture-multimodal", n_demos=12)`."""

from __future__ import annotations

import pytest

from envs.tasks import get_task


def task_fixtures(name: str, n_demos: int):
    @pytest.fixture(scope="module")
    def task():
        return get_task(name, n_demos=n_demos)

    @pytest.fixture(scope="module")
    def demos(task):
        return task.demos(seed=3)

    @pytest.fixture(scope="module")
    def episodes(task):
        return task.episodes(20, seed=7)

    return task, demos, episodes
