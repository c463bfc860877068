"""Benchmarks (run by `nox -s bench`): smoothing 100 trajectories of 70 steps by
gradient descent vs the exact banded solve, and the IDM's latency per control step
at batch 1 (target <= 1 ms). Compare within a group: pytest-benchmark prints them
side by side in one run. Latency does not depend on the weights, so the networks
here have the paper's sizes but are untrained."""

import numpy as np
import pytest
import torch

from envs.robot import NEUTRAL_Q
from stm.control.idm import FastIDM, IDMConfig, IDMController, InverseDynamicsMDN
from stm.control.idm_data import idm_features
from stm.control.smoothing import smooth_exact, smooth_gd

pytestmark = pytest.mark.bench


@pytest.fixture(scope="module", autouse=True)
def one_torch_thread():
    """Small tensors: with the default thread pool on a busy shared CPU, torch spends
    milliseconds per call in thread hand-offs (measured 16-28 ms for the IDM at
    batch 1 with 2 threads, vs about 0.1 ms with one)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def skeletons() -> np.ndarray:
    """100 jittery joint trajectories of 70 steps around the neutral pose."""
    rng = np.random.default_rng(0)
    drift = np.cumsum(0.03 * rng.standard_normal((100, 71, 7)), axis=1)
    return NEUTRAL_Q + drift + 0.02 * rng.standard_normal((100, 71, 7))


@pytest.mark.benchmark(group="smoothing 100 x 70 steps")
def test_bench_smoothing_exact(benchmark, skeletons):
    q = benchmark(smooth_exact, skeletons, 5.0)
    assert q.shape == skeletons.shape


@pytest.mark.benchmark(group="smoothing 100 x 70 steps")
def test_bench_smoothing_gradient_descent(benchmark, skeletons):
    q = benchmark.pedantic(smooth_gd, args=(skeletons, 5.0), kwargs={"iters": 300}, rounds=5, iterations=1)
    assert np.abs(q - smooth_exact(skeletons, 5.0)).max() < 1e-6  # the same answer, slower


@pytest.fixture(scope="module")
def idm_model() -> InverseDynamicsMDN:
    torch.manual_seed(0)
    return InverseDynamicsMDN(IDMConfig()).eval()


def _state() -> np.ndarray:
    return np.r_[NEUTRAL_Q, np.zeros(7)]


@pytest.mark.benchmark(group="IDM latency per control step (batch 1)")
def test_bench_idm_control_step_numpy(benchmark, idm_model):
    ctrl = IDMController(FastIDM(idm_model))
    s = _state()
    ctrl.reset(s)
    tau = benchmark(ctrl, s, s)
    assert tau.shape == (7,)
    benchmark.extra_info["target_ms"] = 1.0


@pytest.mark.benchmark(group="IDM latency per control step (batch 1)")
def test_bench_idm_torch_inference_mode(benchmark, idm_model):
    s = _state()
    x = torch.as_tensor(idm_features(s, s, s, np.zeros(7), np.zeros(7), s), dtype=torch.float32)[None]

    def step():
        with torch.inference_mode():
            return idm_model.torques(x)

    assert benchmark(step).shape == (1, 7)
