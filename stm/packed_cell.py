"""The LSTM stack step of stm.cell for a pack of K models with independent weights.

Per layer the K models' weights are stacked on a leading model axis, (K, I, 4H), and a
step is one batched matmul per layer (torch.baddbmm) for all K models: the same
forward with local derivatives, hand-written backward and deferred weight gradient as
stm.cell (whose step functions take either rank), so a pack of K costs about what one
model costs in per-op overhead, and K times its arithmetic.
"""

from __future__ import annotations

import torch

from stm.cell import _Deferred, _StackStep, _Weights

# nn.LSTM's gate rows (i, f, g, o) -> (i, f, o, g), the g rows doubled (one sigmoid for all gates), as in stm.cell


def _gate_order(H: int) -> tuple[torch.Tensor, torch.Tensor]:
    order = torch.cat([torch.arange(0, 2 * H), torch.arange(3 * H, 4 * H), torch.arange(2 * H, 3 * H)])
    scale = torch.cat([torch.ones(3 * H), torch.full((H,), 2.0)])
    return order, scale


class PackedStackStepper:
    """Steps the LSTM stacks of K models one time step at a time (one per unroll, inside the
    autograd graph). `lstm` is a list per layer of (w_ih (K, 4H, I), w_hh (K, 4H, H),
    b_ih (K, 4H), b_hh (K, 4H)), nn.LSTM's layout with a leading model axis. With in_std
    ((D,) or (K, D)) the steps take centred inputs and fold the division into the first
    layer's input weights, as stm.cell.StackStepper does."""

    def __init__(self, lstm: list[tuple[torch.Tensor, ...]], in_std: torch.Tensor | None = None):
        H = lstm[0][1].shape[-1]
        self.layers = len(lstm)
        self.store = _Deferred(self.layers)
        order, scale = _gate_order(H)
        wb = []
        for k, (w_ih, w_hh, b_ih, b_hh) in enumerate(lstm):
            if k == 0 and in_std is not None:
                w_ih = w_ih / (in_std if in_std.dim() == 1 else in_std[:, None, :])
            w = torch.cat([w_ih, w_hh], dim=2)[:, order] * scale[:, None]  # (K, 4H, I + H)
            wb += [w.transpose(1, 2), ((b_ih + b_hh)[:, order] * scale).unsqueeze(1)]
        self.wb = _Weights.apply(self.store, *wb)

    def __call__(self, x: torch.Tensor, h: list[torch.Tensor], c: list[torch.Tensor]
                 ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """x (K, B, D), per-layer h, c (K, B, H) -> the next per-layer h, c (top layer last)."""
        out = _StackStep.apply(x, self.store, *h, *c, *self.wb)
        return list(out[: self.layers]), list(out[self.layers:])

    def zeros(self, x: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Zero initial (h, c) per layer for inputs shaped like x (K, B, D)."""
        H = self.wb[0].shape[-1] // 4
        z = x.new_zeros(x.shape[0], x.shape[1], H)
        return [z] * self.layers, [z] * self.layers
