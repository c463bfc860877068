"""Benchmarks (`nox -s bench`): physics evaluation time per episode of the block tasks,
on the expert's own rollouts (which must all succeed). Seconds per episode are in each
benchmark's extra_info."""

from __future__ import annotations

import numpy as np
import pytest

from envs.tasks import get_task

pytestmark = pytest.mark.bench

EPISODES = {"pick-place": 4, "stack": 1, "pick-place-changing-goal": 2}


@pytest.mark.parametrize("name", sorted(EPISODES))
def test_physics_evaluation_per_episode(benchmark, name):
    task = get_task(name)
    episodes = task.episodes(EPISODES[name], seed=0)
    if name == "pick-place":
        rollouts = []
        for e in episodes:
            q, grip = task.expert_trajectory(e.q0, e.info["goal"], steps=e.horizon)
            rollouts.append((q, grip))
    else:
        rollouts = [task.expert_rollout(e) for e in episodes]

    def evaluate_all():
        return [task.evaluate(q, g, e) for (q, g), e in zip(rollouts, episodes, strict=True)]

    benchmark.group = "physics"
    results = benchmark.pedantic(evaluate_all, rounds=1, iterations=1)
    seconds = benchmark.stats.stats.mean
    benchmark.extra_info.update(episodes=len(episodes), horizon=episodes[0].horizon,
                                seconds_per_episode=seconds / len(episodes),
                                success_rate=float(np.mean([r["success"] for r in results])))
    assert all(r["success"] == 1.0 for r in results)
