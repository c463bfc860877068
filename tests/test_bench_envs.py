"""Benchmarks of the envs package (`nox -s bench`; not part of `nox -s tests`).

- batched FK (pytorch-kinematics) in poses/s at B = 1 and B = 4096, next to pybullet's
  per-call FK in the same run (target: >= 200,000 poses/s at B = 4096);
- demonstrations generated per second for each training task;
- physics evaluation of 100 reacher rollouts in DIRECT mode (target: under 60 s).
Throughputs are in each benchmark's extra_info (`--benchmark-json` keeps them).
"""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest
import torch

from envs.kinematics import default_kinematics
from envs.robot import LIMITS, load_in_pybullet
from envs.tasks import get_task

pytestmark = pytest.mark.bench

FK_TARGET_POSES_PER_SECOND = 200_000
EVAL_TARGET_SECONDS = 60.0


@pytest.mark.parametrize("batch, threads", [(1, None), (4096, None), (4096, 1)],
                         ids=["B1", "B4096", "B4096-1thread"])
def test_fk_batched_pytorch_kinematics(benchmark, batch, threads):
    kin = default_kinematics(torch.float32)
    q = torch.as_tensor(LIMITS.sample(np.random.default_rng(0), batch), dtype=torch.float32)
    before = torch.get_num_threads()
    if threads:
        torch.set_num_threads(threads)
    try:
        with torch.no_grad():
            benchmark.group = "fk"
            benchmark(kin.tip_position, q)
    finally:
        torch.set_num_threads(before)
    stats = benchmark.stats.stats
    benchmark.extra_info.update(poses_per_second=batch / stats.mean, poses_per_second_best=batch / stats.min,
                                batch=batch, torch_threads=threads or before,
                                target_poses_per_second=FK_TARGET_POSES_PER_SECOND)


def test_fk_pybullet_per_call(benchmark):
    client = p.connect(p.DIRECT)
    try:
        robot = load_in_pybullet(client)
        qs = LIMITS.sample(np.random.default_rng(0), 256)
        state = {"i": 0}

        def one_pose():
            q = qs[state["i"] % len(qs)]
            state["i"] += 1
            robot.reset(q)
            return p.getLinkState(robot.body, robot.tip, computeForwardKinematics=True, physicsClientId=client)[4]

        benchmark.group = "fk"
        benchmark(one_pose)
    finally:
        p.disconnect(client)
    stats = benchmark.stats.stats
    benchmark.extra_info.update(poses_per_second=1.0 / stats.mean, poses_per_second_best=1.0 / stats.min,
                                seconds_per_call=stats.mean)


# small sets keep the benchmark short; the rate is per demonstration, physics replay included
GENERATION = {"reacher": {"n_demos": 10}, "circle": {}, "pick-place": {"n_demos": 4}}


@pytest.mark.parametrize("name", sorted(GENERATION))
def test_demos_generated_per_second(benchmark, name):
    task = get_task(name, **GENERATION[name])
    benchmark.group = "demos"
    demos = benchmark.pedantic(task.demos, args=(0,), rounds=1, iterations=1)
    seconds = benchmark.stats.stats.mean
    benchmark.extra_info.update(demos=len(demos), demos_per_second=len(demos) / seconds, seconds=seconds,
                                rejections=demos.meta.get("rejections"))


def test_physics_evaluation_of_100_reacher_rollouts(benchmark):
    task = get_task("reacher")
    episodes = task.episodes(100, seed=0)
    q0 = np.stack([e.q0 for e in episodes])
    goals = np.stack([e.psi[-1] for e in episodes])
    q, _, ok = task.expert(q0, goals)  # the rollouts: the expert's paths, held to the horizon
    horizon = episodes[0].horizon
    q = np.concatenate([q, np.repeat(q[:, -1:], horizon + 1 - q.shape[1], axis=1)], axis=1)

    def evaluate_all():
        return [task.evaluate(q[i], None, episodes[i]) for i in range(100)]

    benchmark.group = "physics"
    results = benchmark.pedantic(evaluate_all, rounds=1, iterations=1)
    seconds = benchmark.stats.stats.mean
    benchmark.extra_info.update(rollouts=100, horizon=horizon, seconds=seconds, rollouts_per_second=100 / seconds,
                                target_seconds=EVAL_TARGET_SECONDS,
                                success_rate=float(np.mean([r["success"] for r in results])))
    assert ok.all() and all(r["success"] == 1.0 for r in results)
