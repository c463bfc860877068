"""Single steps of an nn.LSTM stack for the auto-conditioned unroll, with a hand-written backward.

Why: a fused nn.LSTM call pays ~100 us of set-up per layer, too much for one or two
steps, and a step written in autograd ops records ~30 graph nodes per step. Here one
step of the whole stack is ONE autograd node (`StackStep`): the forward runs the gate
maths without recording, the backward is the textbook LSTM backward. The weight
gradient is not computed per step: each step leaves its ([x, h], d gates) rows in a
`DeferredGrads` store and the node that handed out the weights (`DeferredWeights`, upstream of
every step) turns them into one matmul per layer when autograd reaches it, after all
the steps (autograd runs a node only once every consumer of its outputs is done).

Same maths and weights as nn.LSTM: gates i, f, g, o (rearranged to i, f, o, g) with
c' = f c + i g and h' = o tanh(c'); biases b_ih + b_hh. Checked against nn.LSTM and a
plain reference unroll in tests/test_stm_speed_equivalence.py.

The steps carry a leading model axis (x (K, B, D), w (K, I, 4H)): K independent models step at once
with batched matmuls, and one model is a pack of one (stm.packed_lstm_step.PackedStackStepper).

Low-precision products (TrainConfig.matmul_dtype "bfloat16"): every matrix product of a step,
forward, backward and the deferred weight gradient, takes its operands in that dtype (the
weights cast once per unroll) and hands back float32; the state, the gate maths and all
gradients outside the products stay float32. Why explicit casts and not torch.autocast: the
hand-written backward would get products of autocast's dtype where it adds float32 tensors.
"""

from __future__ import annotations

import torch


def product_dtype(name: str) -> torch.dtype | None:
    """TrainConfig.matmul_dtype -> the dtype of the low-precision products, None for float32 (today's path)."""
    if name == "float32":
        return None
    if name == "bfloat16":
        return torch.bfloat16
    raise ValueError(f"unknown matmul_dtype {name!r}; known: float32, bfloat16")


def mm(a: torch.Tensor, b: torch.Tensor, dtype: torch.dtype | None) -> torch.Tensor:
    """a @ b; with dtype, the product of the operands cast to it, as float32."""
    return a @ b if dtype is None else torch.matmul(a.to(dtype), b.to(dtype)).float()


class DeferredGrads:
    """Per unroll: the ([x, h], d gates) rows each layer's steps left for the weight gradient; with a
    low-precision product dtype, also the weights and biases cast to it once (`low`, as wb)."""

    def __init__(self, layers: int, dtype: torch.dtype | None = None):
        self.xh: list[list[torch.Tensor]] = [[] for _ in range(layers)]
        self.dgates: list[list[torch.Tensor]] = [[] for _ in range(layers)]
        self.dtype = dtype
        self.low: list[torch.Tensor] = []


class DeferredWeights(torch.autograd.Function):
    """Identity on (w_t, b) per layer; backward = the deferred weight gradients of all steps."""

    @staticmethod
    def forward(ctx, store: DeferredGrads, *wb: torch.Tensor):
        ctx.store = store
        ctx.set_materialize_grads(False)
        return tuple(t.view_as(t) for t in wb)

    @staticmethod
    def backward(ctx, *grads):
        store, out = ctx.store, []
        for k in range(len(grads) // 2):
            xh, dg = store.xh[k], store.dgates[k]
            store.xh[k], store.dgates[k] = [], []  # a second backward (retain_graph) starts afresh
            gw, gb = grads[2 * k], grads[2 * k + 1]
            if xh:  # rows (K, N, .) of a pack of K
                xh, dg = torch.cat(xh, -2), torch.cat(dg, -2)
                dw, db = mm(xh.transpose(-2, -1), dg, store.dtype), dg.sum(-2, keepdim=True)
                gw = dw if gw is None else gw + dw
                gb = db if gb is None else gb + db
            out += [gw, gb]
        return (None, *out)


def cast_once(store: DeferredGrads, wb: list[torch.Tensor]) -> None:
    """The weights and biases in the store's product dtype, for every step of the unroll (their gradients go
    through the deferred float32 path, so the casts are detached)."""
    if store.dtype is not None:
        store.low = [t.detach().to(store.dtype) for t in wb]


def _affine(b: torch.Tensor, x: torch.Tensor, w: torch.Tensor) -> torch.Tensor:
    """b + x @ w for a pack (x (K, B, I), w (K, I, O), b (K, 1, O))."""
    return torch.baddbmm(b, x, w)


def _stack_forward(x: torch.Tensor, hs: list[torch.Tensor], cs: list[torch.Tensor], ws: list[torch.Tensor],
                   bs: list[torch.Tensor], dtype: torch.dtype | None = None
                   ) -> tuple[list[torch.Tensor], list[torch.Tensor], list[list[torch.Tensor]]]:
    """The forward of one step, bottom layer first; also, per layer, the local derivatives the
    backward needs, so that it is a few ops per layer:
      d pre-activations = [dc, dc, dh, dc] * [g, c, tanh(c'), 2 i] * s (1 - s)  (`gd`: all but the first)
      dc = dc' + dh * o (1 - tanh(c')^2)                                          (`o_dt`: the last factor)
    with s the gate sigmoids (the g gate's doubled: g = 2 s_g - 1). With dtype, ws and bs are in it, [x, h] is
    cast to it for the product (and saved so for the weight gradient) and the gates come back as float32."""
    H = hs[0].shape[-1]
    h_out: list[torch.Tensor] = []
    c_out: list[torch.Tensor] = []
    saved: list[list[torch.Tensor]] = []
    inp = x
    for k in range(len(hs)):
        xh = torch.cat([inp, hs[k]], -1)
        if dtype is None:
            pre = _affine(bs[k], xh, ws[k])
        else:
            xh = xh.to(dtype)
            pre = _affine(bs[k], xh, ws[k]).float()
        sig = torch.sigmoid(pre)  # i, f, o and sigmoid(2 g_pre)
        i, f, o = sig[..., :H], sig[..., H: 2 * H], sig[..., 2 * H: 3 * H]
        g = sig[..., 3 * H:] * 2.0 - 1.0  # tanh(x) = 2 sigmoid(2x) - 1: one sigmoid for all gates
        c_new = torch.addcmul(f * cs[k], i, g)
        tc = torch.tanh(c_new)
        inp = o * tc
        gd = torch.cat([g, cs[k], tc, i * 2.0], -1) * torch.addcmul(sig, sig, sig, value=-1.0)
        o_dt = torch.addcmul(o, inp, tc, value=-1.0)
        h_out.append(inp)
        c_out.append(c_new)
        saved.append([xh, gd, o_dt, f])
    return h_out, c_out, saved


def _stack_backward(gh: list[torch.Tensor | None], gc: list[torch.Tensor | None], ws: list[torch.Tensor],
                    saved: list[list[torch.Tensor]], need_x: bool, dtype: torch.dtype | None = None
                    ) -> tuple[torch.Tensor | None, list[torch.Tensor], list[torch.Tensor], list[torch.Tensor]]:
    """The LSTM backward of one step, top layer first. Returns d x, d h_k, d c_k and, per layer,
    d gates (for the deferred weight gradient). With dtype (ws in it) the products run in it."""
    L = len(saved)
    grad_h: list[torch.Tensor] = []
    grad_c: list[torch.Tensor] = []
    dgs: list[torch.Tensor] = []
    below: torch.Tensor | None = None  # gradient reaching layer k's output from layer k + 1's input
    for j in range(L):
        k = L - 1 - j
        xh, gd, o_dt, f = saved[k]
        ghk, gck = gh[k], gc[k]
        if ghk is None:
            dh = below if below is not None else torch.zeros_like(f)
        else:
            dh = ghk if below is None else ghk + below
        dc = o_dt * dh if gck is None else torch.addcmul(gck, o_dt, dh)
        dgates = torch.cat([dc, dc, dh, dc], -1).mul_(gd)
        grad_c.append(dc * f)
        H = f.shape[-1]
        d_in = xh.shape[-1] - H
        if k > 0 or need_x:
            dxh = mm(dgates, ws[k].transpose(-2, -1), dtype)
            below = dxh[..., :d_in]
            grad_h.append(dxh[..., d_in:])
        else:  # a ground-truth input: only the recurrent part
            below = None
            grad_h.append(mm(dgates, ws[k][..., d_in:, :].transpose(-2, -1), dtype))
        dgs.append(dgates)
    grad_h.reverse()
    grad_c.reverse()
    dgs.reverse()
    return below, grad_h, grad_c, dgs


class StackStep(torch.autograd.Function):
    """One time step of the L-layer stacks of K models: x (K, B, D), per layer h_k, c_k (K, B, H) -> h_k', c_k',
    with weights (K, I, 4H) and biases (K, 1, 4H).

    Per-layer tensors in and out (no stack/select per step); w_t has the gate columns in
    the order i, f, o, g, those of g doubled, so that one sigmoid gives all four gates."""

    @staticmethod
    def forward(ctx, x, store: DeferredGrads, *args):
        L = len(args) // 4
        hs, cs, wb = list(args[:L]), list(args[L: 2 * L]), args[2 * L:]
        if store.dtype is not None:  # the products' weights: cast once per unroll (the stepper's)
            wb = store.low
        ws, bs = list(wb[0::2]), list(wb[1::2])
        h_out, c_out, saved = _stack_forward(x, hs, cs, ws, bs, store.dtype)
        ctx.saved, ctx.store, ctx.w = saved, store, ws
        return (*h_out, *c_out)

    @staticmethod
    def backward(ctx, *grads):
        L = len(ctx.saved)
        dx, grad_h, grad_c, dgs = _stack_backward(list(grads[:L]), list(grads[L:]), ctx.w, ctx.saved,
                                                  ctx.needs_input_grad[0], ctx.store.dtype)
        store = ctx.store
        for k in range(L):
            store.xh[k].append(ctx.saved[k][0])
            store.dgates[k].append(dgs[k])
        return (dx, None, *grad_h, *grad_c) + (None,) * (2 * L)


def gate_order(H: int, device: torch.device | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """nn.LSTM's gate rows (i, f, g, o) -> (i, f, o, g), and the scale that doubles the g rows: tanh(x) =
    2 sigmoid(2x) - 1, so one sigmoid covers all four gates (tanh costs several times a sigmoid per element).
    On the weights' device (made there: no host copy inside a captured CUDA graph)."""
    order = torch.cat([torch.arange(0, 2 * H, device=device), torch.arange(3 * H, 4 * H, device=device),
                       torch.arange(2 * H, 3 * H, device=device)])
    scale = torch.cat([torch.ones(3 * H, device=device), torch.full((H,), 2.0, device=device)])
    return order, scale
