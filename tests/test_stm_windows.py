"""Windowed training with burn-in (stm.training.windows): windows lie in their demonstrations and cover every step
equally often; a burn-in that reaches the demonstration's start gives exactly the state of a
whole-demonstration unroll; a window config trains (packed training equals it: tests/test_stm_packed.py)."""

import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from envs.kinematics import default_kinematics
from stm.config import ModelConfig, TrainConfig
from stm.model import STM, normalization_stats
from stm.training.autoconditioning import unroll_model as unroll
from stm.training.batches import DemoTensors
from stm.training.loop import train
from stm.training.windows import sample_windows

TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    demos = task.demos(0)
    data = DemoTensors.build(task, demos)
    valid = torch.arange(data.states.shape[1])[None, :] <= data.lengths[:, None]
    torch.manual_seed(0)
    return task, demos, data, STM(TINY, task.layout, *normalization_stats(data.states, valid, task.layout))


def test_windows_lie_in_their_demos_and_cover_every_step_equally_often():
    lengths = torch.tensor([5, 12, 30])
    window, draws = 4, 60_000
    w = sample_windows(lengths.repeat(draws, 1), window, 3, torch.Generator().manual_seed(0), last_step=30)
    trained = w.steps[..., :-1]  # a transition t -> t+1 per trained step
    assert w.mask.any(-1).all()  # no empty window
    assert (trained[w.mask] < lengths.repeat(draws, 1)[..., None].expand_as(trained)[w.mask]).all()
    assert (w.burn[~w.burn_valid] == 0).all() and w.burn_valid.sum() > 0
    for i, n in enumerate(lengths.tolist()):
        counts = np.bincount(trained[:, i][w.mask[:, i]].numpy(), minlength=n)
        expected = draws * window / (n + window - 1)  # offsets uniform over [-(window - 1), n - 1]
        np.testing.assert_allclose(counts, expected, rtol=0.05)
    # a trained transition reads two consecutive steps: a window is one stretch of its demonstration
    assert (torch.diff(w.steps, dim=-1)[w.mask] == 1).all()


def test_a_burn_in_from_the_start_gives_the_whole_demo_state(toy):
    """Teacher forcing from a burnt-in state = the same steps of a whole-demonstration unroll, exactly when the
    burn-in reaches back to the start (here always: burn_in >= the longest demo)."""
    task, _, data, model = toy
    kin = default_kinematics(torch.float32)
    idx = torch.arange(len(data.lengths))
    tf = TrainConfig(u=1, v=0)
    with torch.no_grad():
        whole = unroll(model, data.batch(idx), task, tf, kin)
        windows = data.windows(idx, 4, int(data.lengths.max()), torch.Generator().manual_seed(1))
        part = unroll(model, data.window_batch(idx, windows), task, tf, kin)
    steps = windows.steps[:, : part.shape[1]]
    expected = torch.take_along_dim(whole, steps.clamp(max=whole.shape[1] - 1)[..., None], dim=1)
    mask = windows.mask[:, : part.shape[1]]
    torch.testing.assert_close(part[mask], expected[mask], rtol=1e-5, atol=1e-5)
    assert (windows.steps[:, 0] > 0).any()  # some windows start inside their demo: the burn-in mattered


def test_a_short_burn_in_differs_from_none(toy):
    task, _, data, model = toy
    kin = default_kinematics(torch.float32)
    idx = torch.arange(len(data.lengths))
    tf = TrainConfig(u=1, v=0)
    with torch.no_grad():
        windows = data.windows(idx, 4, 3, torch.Generator().manual_seed(1))
        warm = unroll(model, data.window_batch(idx, windows), task, tf, kin)
        cold_batch = data.window_batch(idx, windows)
        cold_batch.burn = None
        cold = unroll(model, cold_batch, task, tf, kin)
    inside = windows.steps[:, 0] >= 3  # burnt in over 3 real steps
    assert (warm[inside] - cold[inside]).abs().max() > 1e-3
    torch.testing.assert_close(warm[~inside & (windows.steps[:, 0] == 0)], cold[~inside & (windows.steps[:, 0] == 0)])


def test_windowed_auto_conditioned_training_runs_and_learns(toy):
    task, demos, _, _ = toy
    cfg = TrainConfig(iters=30, batch_size=4, lr=1e-2, u=2, v=2, window=5, burn_in=3, log_every=0,
                      checkpoint_every=0)
    result = train(TINY, cfg, task, demos)
    losses = result.history["train/loss"]
    assert np.isfinite(losses).all() and np.mean(losses[-5:]) < np.mean(losses[:5])


def test_a_burn_in_without_a_window_is_refused():
    with pytest.raises(ValueError, match="burn_in needs a window"):
        TrainConfig(burn_in=3)
