"""stm.speed.floor: an iteration's FLOPs counted from the shapes, the core's peak GEMM rate, and the iteration's
products recorded forward and backward and replayed alone."""

import dataclasses
import time

import pytest
import torch
from torch import nn

from stm.config import ModelConfig, TrainConfig
from stm.speed.bench import _iterations
from stm.speed.bench_inputs import BenchTask, bench_demos
from stm.speed.floor import iteration_flops, peak_gflops, product_flops, record_matmuls, replayer


def test_records_forward_and_backward_products_and_replays_them():
    x, w = torch.randn(4, 3, requires_grad=True), torch.randn(3, 5, requires_grad=True)
    calls = record_matmuls(lambda: (x @ w).sum().backward())
    assert len(calls) == 3  # x w, then d/dx and d/dw
    assert product_flops(calls) == 3 * 2 * 4 * 3 * 5
    replayer(calls)()


@pytest.mark.parametrize("layers", [1, 2])
def test_lstm_layers_recorded_as_the_products_of_an_unfused_layer(layers):
    """Whether nn.LSTM runs fused (oneDNN) or step by step, its products do the same arithmetic: per layer
    4H (I + H) multiply-adds per step and sample forward, twice that backward (input and weight gradients)."""
    T, B, I, H = 5, 2, 3, 8
    lstm = nn.LSTM(I, H, num_layers=layers, batch_first=True)
    x = torch.randn(B, T, I, requires_grad=True)
    h0 = (torch.zeros(layers, B, H, requires_grad=True), torch.zeros(layers, B, H, requires_grad=True))
    calls = record_matmuls(lambda: lstm(x, h0)[0].sum().backward())
    forward = sum(T * B * 4 * H * (i + H) for i in [I] + [H] * (layers - 1))
    assert product_flops(calls) == 3 * 2 * forward
    replayer(calls)()


def test_the_replay_shares_one_warm_operand_per_layout():
    x, w = torch.randn(8, 8, requires_grad=True), torch.randn(8, 8, requires_grad=True)
    calls = record_matmuls(lambda: (x @ w @ w).sum().backward())
    replay = replayer(calls)
    replay()
    distinct = len({id(a) for _op, args, _ in replay.calls for a in args if isinstance(a, torch.Tensor)})
    layouts = {(tuple(a.shape), a.stride) for _op, args, _ in calls for a in args if hasattr(a, "stride")}
    assert distinct == len(layouts) < sum(len([a for a in args if hasattr(a, "stride")]) for _op, args, _ in calls)


def test_iteration_flops_by_hand():
    """One layer, H = 2, B = 1, T = 4, u = v = 2: the gates' product is 2 * 4H * (D + H) per step forward, and the
    input's part of its gradient is needed only on the 2 self-fed steps."""
    layout = BenchTask("reacher", False).layout
    D = layout.dim
    model = ModelConfig(hidden_size=2, num_layers=1, mixtures=1)
    flops = iteration_flops(model, layout, TrainConfig(u=2, v=2), batch=1, steps=4)
    forward = 4 * 2 * 8 * (D + 2)
    assert flops["lstm"] == forward + forward + (forward - 2 * 2 * 8 * D)
    assert flops["head"] == 3 * 4 * 2 * 2 * (D + 2)
    dims = layout.phi.start  # grounded: the feedback reads the logits and the dq means
    assert flops["feedback"] == 3 * 2 * 2 * 2 * (1 + dims)
    assert flops["total"] == flops["lstm"] + flops["head"] + flops["feedback"]
    tf = iteration_flops(model, layout, TrainConfig(v=0), batch=1, steps=4)
    assert tf["feedback"] == 0 and tf["lstm"] == 3 * forward - 4 * 2 * 8 * D
    with pytest.raises(ValueError, match="point feedback"):
        iteration_flops(model, layout, TrainConfig(feedback="sample"), batch=1, steps=4)


@pytest.mark.parametrize("cfg", [TrainConfig(v=0), TrainConfig(u=2, v=3), TrainConfig(u=1, v=7),
                                 TrainConfig(u=3, v=2, feedback="mixture_mean"),
                                 TrainConfig(u=2, v=3, detach_feedback=True)],
                         ids=["tf", "u2v3", "u1v7", "mixture-mean", "detached"])
@pytest.mark.parametrize("kernel", ["python", "cpp"])
def test_iteration_flops_are_the_products_a_packed_iteration_calls(cfg, kernel):
    """The count from the shapes equals what a pack's iteration calls, per model, on either route (phi fed back
    free: a grounded phi adds the tip kinematics' few products, which the floor leaves out). A teacher-forced
    iteration calls oneDNN's fused layer, which also gives the bottom layer's input gradient."""
    cfg = dataclasses.replace(cfg, phi_mode="free", step_kernel=kernel)
    task, B, T, K = BenchTask("pick-place", True), 3, 11, 2
    model = ModelConfig(hidden_size=8, num_layers=2, mixtures=2)
    step = _iterations(task, bench_demos(B, T, True), model, k=K)(dataclasses.replace(cfg, batch_size=B))
    step()
    recorded = product_flops(record_matmuls(step)) / K
    counted = iteration_flops(model, task.layout, cfg, B, T)["total"]
    fused_input_grad = 2 * B * T * 4 * model.hidden_size * task.layout.dim if cfg.v == 0 else 0
    assert recorded == counted + fused_input_grad


def test_peak_is_the_best_of_warm_products():
    ticks = iter(range(100))
    rate = peak_gflops(torch.float32, lambda: float(next(ticks)), n=64, reps=3)  # every product "takes" 1 s
    assert rate == pytest.approx(2 * 64 ** 3 / 1e9)
    assert peak_gflops(torch.float32, time.perf_counter, n=256, reps=2) > 0.1
    assert peak_gflops(torch.bfloat16, time.perf_counter, n=256, reps=2) > 0.1
