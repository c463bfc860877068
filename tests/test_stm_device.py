"""--device auto|cpu|cuda[:N] (stm.device): resolution and its one-line errors, the CPU path unchanged, and the
parts of the CUDA path that run on a CPU (the graph-replayed iteration's logic, run eagerly; constants and
batches moved by .to). The CUDA graph capture itself needs a GPU."""

import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

import stm.training.loop
from stm.config import ModelConfig, TrainConfig
from stm.device import DeviceError, check_device_name, resolve_device
from stm.fk import default_tip_kinematics
from stm.training.batches import DemoTensors
from stm.training.cuda_graph import capturable
from stm.training.loop import train, train_packed
from stm.variants import VARIANTS

TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)
BASE = TrainConfig(iters=6, batch_size=4, lr=3e-3, u=2, v=2, log_every=0, checkpoint_every=0)


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    return task, task.demos(0)


def test_resolve_device(monkeypatch):
    assert resolve_device("cpu") == torch.device("cpu")
    assert resolve_device(torch.device("cpu")) == torch.device("cpu")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    assert resolve_device("auto") == torch.device("cpu")
    with pytest.raises(DeviceError, match="'cuda': torch sees no CUDA GPU here.*use --device cpu or auto"):
        resolve_device("cuda")
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    assert resolve_device("auto") == resolve_device("cuda") == torch.device("cuda", 0)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    with pytest.raises(DeviceError, match=r"'cuda:7': this machine has 2 CUDA GPU\(s\), cuda:0..cuda:1"):
        resolve_device("cuda:7")


@pytest.mark.parametrize("bad", ["tpu", "gpu", "cuda:", "cuda:x", "CPU", "cpu:0", "", "auto "])
def test_a_bad_device_name_is_one_clear_line(bad):
    with pytest.raises(DeviceError, match=r"unknown device .*; allowed: auto, cpu, cuda or cuda:N$"):
        check_device_name(bad)


def test_device_cpu_trains_bit_identically_to_the_default(toy):
    task, demos = toy
    model_cfg, cfg = VARIANTS["ac-lstm-mdn"].configs(TINY, BASE)
    default = train(model_cfg, cfg, task, demos)
    on_cpu = train(model_cfg, cfg, task, demos, device="cpu")
    assert on_cpu.history == default.history
    for k, v in default.model.state_dict().items():
        assert torch.equal(on_cpu.model.state_dict()[k], v)


class EagerGraphs:
    """stm.training.cuda_graph.StepGraphs without the capture: runs the iteration the graph would replay, eagerly."""

    def __init__(self, params):
        self.params, self.keys = params, []

    def run(self, key, fn, batches):
        self.keys.append((key, *(tuple(b.states.shape) for b in batches)))
        for p in self.params:
            p.grad = None
        return fn(batches)


@pytest.mark.parametrize("variant", ["lstm-mdn", "ac-lstm-mdn", "ac-lstm"])
def test_the_graphed_iteration_trains_as_the_eager_one(toy, monkeypatch, variant):
    """What a CUDA run replays (whole demos padded to the longest, the seeds' schedule groups, losses and
    gradients from one function, clipping and Adam outside) trains the pack as the eager iterations do."""
    task, demos = toy
    model_cfg, cfg = VARIANTS[variant].configs(TINY, TrainConfig.from_dict({**BASE.to_dict(), "tf_warmup": 2}))
    cfgs = [TrainConfig.from_dict({**cfg.to_dict(), "seed": s, "tf_warmup": w}) for s, w in ((0, 2), (1, 0))]
    eager = train_packed(model_cfg, cfgs, task, demos)
    made = []
    monkeypatch.setattr(stm.training.loop, "use_graphs", lambda device, c: True)
    monkeypatch.setattr(stm.training.loop, "StepGraphs", lambda params: made.append(EagerGraphs(params)) or made[-1])
    graphed = train_packed(model_cfg, cfgs, task, demos)
    longest = int(max(demos.lengths))
    assert made and {k[1][2] for k in made[0].keys} == {longest + 1}  # static: every batch padded to all demos
    for e, g in zip(eager, graphed, strict=True):
        np.testing.assert_allclose(g.history["train/loss"], e.history["train/loss"], rtol=1e-5)
        np.testing.assert_allclose(g.history["train/grad_norm"], e.history["train/grad_norm"], rtol=1e-4)
        for k, v in e.model.state_dict().items():
            assert torch.allclose(g.model.state_dict()[k], v, atol=2e-5)


def test_what_a_graph_cannot_replay_stays_eager():
    assert capturable(TrainConfig())
    assert not capturable(TrainConfig(input_noise=0.1))  # drawn from each seed's CPU generator
    assert not capturable(TrainConfig(feedback="sample"))
    assert not capturable(TrainConfig(window=5))  # lengths vary
    assert not stm.training.loop.use_graphs(torch.device("cpu"), TrainConfig())


def test_kinematics_and_batches_move_to_a_device(toy):
    kin = default_tip_kinematics(torch.float32)
    assert kin.to("cpu") is kin
    meta = kin.to("meta")
    for name in ("coef", "row_sums", "signs", "phases", "lower", "upper"):
        assert getattr(meta, name).device.type == "meta" and getattr(kin, name).device.type == "cpu"
    assert meta.tip_plan.index.device.type == "meta" and kin.grad_plan.index.device.type == "cpu"
    assert meta.tip_position(torch.zeros(4, 7, device="meta")).shape == (4, 3)
    task, demos = toy
    data = DemoTensors.build(task, demos)
    batch = data.batch(torch.arange(3))
    assert batch.to(torch.device("cpu")) is batch
    moved = batch.to(torch.device("meta"))
    assert moved.states.device.type == moved.mask.device.type == "meta" and moved.states.shape == batch.states.shape
    full = data.batch(torch.arange(2), full=True)
    assert full.states.shape[1] == int(data.lengths.max()) + 1 and full.mask.shape[1] == int(data.lengths.max())


def test_bench_takes_a_device(monkeypatch, capsys):
    from stm.speed import bench

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)
    for bad, message in (("tpu", "unknown device 'tpu'"), ("cuda", "torch sees no CUDA GPU here")):
        with pytest.raises(SystemExit) as exit_:
            bench.main(["--device", bad, "--no-rollouts", "--no-fk"])
        assert exit_.value.code == 2 and message in capsys.readouterr().err
