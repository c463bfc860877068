"""Benchmarks (nox -s bench): one training iteration per schedule at the reacher size, and
1,000 reacher rollouts. Compare the rows of one run; `python -m stm.speed.bench` prints the ratios."""

import numpy as np
import pytest
import torch

from envs.robot import NEUTRAL_Q
from envs.tasks.base import Episode
from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.model import STM, normalization_stats
from stm.rollout import generate
from stm.speed.bench import SIZES, BenchTask, _iterations, bench_demos
from stm.training.autoconditioning import batch_loss
from stm.training.batches import DemoTensors

pytestmark = pytest.mark.bench


@pytest.fixture(scope="module")
def reacher_setup():
    spec = SIZES["reacher"]
    task = BenchTask("reacher", False)
    data = DemoTensors.build(task, bench_demos(spec["batch"], spec["steps"], False))
    stats = normalization_stats(data.states, torch.ones(data.states.shape[:2], dtype=torch.bool))
    model = STM(ModelConfig(hidden_size=spec["hidden"], mixtures=spec["mixtures"]), task.layout, *stats)
    return task, model, data.batch(torch.arange(spec["batch"]))


@pytest.mark.benchmark(group="stm-train-iteration-reacher")
@pytest.mark.parametrize("u,v", [(1, 0), (2, 2), (5, 5)], ids=["tf", "ac-u2v2", "ac-u5v5"])
def test_training_iteration(benchmark, reacher_setup, u, v):
    task, model, batch = reacher_setup
    opt = torch.optim.Adam(model.parameters(), lr=1e-4)
    cfg, kin = TrainConfig(u=u, v=v), default_tip_kinematics()

    def step():
        loss = batch_loss(model, batch, task, cfg, kin)
        opt.zero_grad(set_to_none=True)
        loss.backward()
        opt.step()
        return loss.item()

    assert np.isfinite(benchmark.pedantic(step, rounds=5, warmup_rounds=1))


@pytest.mark.benchmark(group="stm-rollouts")
def test_thousand_reacher_rollouts(benchmark, reacher_setup):
    task, model, _ = reacher_setup
    rng = np.random.default_rng(0)
    eps = [Episode(q0=NEUTRAL_Q + rng.uniform(-0.2, 0.2, 7), psi=np.tile([0.6, 0.1, 0.1], (71, 1)), horizon=70)
           for _ in range(1000)]
    ro = benchmark.pedantic(generate, args=(model, task, eps), rounds=3, warmup_rounds=1)
    assert ro.q.shape == (1000, 71, 7) and np.isfinite(ro.q).all()


@pytest.mark.benchmark(group="stm-train-iteration-reacher")
@pytest.mark.parametrize("u,v", [(1, 0), (2, 2), (5, 5)], ids=["tf", "ac-u2v2", "ac-u5v5"])
def test_packed_training_iteration(benchmark, reacher_setup, u, v):
    """One iteration of a pack of 3 models (stm.packed): compare with 3x the rows above."""
    task, model, _ = reacher_setup
    spec = SIZES["reacher"]
    step = _iterations(task, bench_demos(spec["batch"], spec["steps"], False), model.config)
    benchmark.pedantic(step(TrainConfig(u=u, v=v, batch_size=spec["batch"])), rounds=5, warmup_rounds=1)


@pytest.mark.benchmark(group="stm-rollouts")
def test_thousand_reacher_rollouts_of_three_models_batched(benchmark, reacher_setup):
    task, model, _ = reacher_setup
    rng = np.random.default_rng(0)
    eps = [Episode(q0=NEUTRAL_Q + rng.uniform(-0.2, 0.2, 7), psi=np.tile([0.6, 0.1, 0.1], (71, 1)), horizon=70)
           for _ in range(1000)]
    out = benchmark.pedantic(generate, args=([model] * 3, task, eps), rounds=3, warmup_rounds=1)
    assert len(out) == 3 and all(ro.q.shape == (1000, 71, 7) and np.isfinite(ro.q).all() for ro in out)
