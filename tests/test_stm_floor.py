"""stm.speed.floor: an iteration's matrix products, recorded forward and backward and replayed alone."""

import math

import pytest
import torch
from torch import nn

from stm.speed.floor import record_matmuls, replayer


def _macs(calls) -> int:
    """Multiply-adds of recorded products (the last two shapes of each op's two matrix arguments)."""
    total = 0
    for _op, args, _ in calls:
        a, b = [x for x in args if hasattr(x, "shape") and len(x.shape) >= 2][-2:]
        total += math.prod(a.shape) * b.shape[-1]
    return total


def test_records_forward_and_backward_products_and_replays_them():
    x, w = torch.randn(4, 3, requires_grad=True), torch.randn(3, 5, requires_grad=True)
    calls = record_matmuls(lambda: (x @ w).sum().backward())
    assert len(calls) == 3  # x w, then d/dx and d/dw
    for dtype in (None, torch.bfloat16):
        replayer(calls, dtype)()


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
    assert _macs(calls) == 3 * forward
    replayer(calls)()


def test_the_warm_replay_shares_one_operand_per_layout():
    x, w = torch.randn(8, 8, requires_grad=True), torch.randn(8, 8, requires_grad=True)
    calls = record_matmuls(lambda: (x @ w @ w).sum().backward())
    distinct = {}
    for warm in (False, True):
        replay = replayer(calls, warm=warm)
        replay()
        distinct[warm] = len({id(a) for _op, args, _ in replay.calls for a in args if isinstance(a, torch.Tensor)})
    layouts = {(tuple(a.shape), a.stride) for _op, args, _ in calls for a in args if hasattr(a, "stride")}
    assert distinct[False] == sum(len([a for a in args if hasattr(a, "stride")]) for _op, args, _ in calls)
    assert distinct[True] == len(layouts) < distinct[False]
