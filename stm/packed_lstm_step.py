"""The LSTM stack step of stm.lstm_step for a pack of K models with independent weights (one model: a pack of one).

Per layer the K models' weights are stacked on a leading model axis, (K, I, 4H), and a
step is one batched matmul per layer (torch.baddbmm) for all K models: the same
forward with local derivatives, hand-written backward and deferred weight gradient as
stm.lstm_step (whose step functions take either rank), so a pack of K costs about what one
model costs in per-op overhead, and K times its arithmetic. With a low-precision product dtype
(stm.lstm_step.product_dtype) the stepper's and the layer sequence's products run in it; the fused
sequence (nn.LSTM's kernel) stays float32.
"""

from __future__ import annotations

import torch

from stm.lstm_step import DeferredGrads, DeferredWeights, StackStep, cast_once, gate_order, mm


class PackedStackStepper:
    """Steps the LSTM stacks of K models one time step at a time (one per unroll, inside the
    autograd graph: it rearranges the weights once). `lstm` is a list per layer of (w_ih (K, 4H, I),
    w_hh (K, 4H, H), b_ih (K, 4H), b_hh (K, 4H)), nn.LSTM's layout with a leading model axis. With in_std
    ((D,) or (K, D)) the steps take centred inputs x - mean and compute what the LSTM gives for
    (x - mean) / in_std: the division is folded into the first layer's input weights, W ((x - m) / s) =
    (W / s)(x - m), one op fewer per step. (The mean is not folded: (W / s) x - (W / s) m would cancel
    catastrophically where s is tiny.) With dtype the products run in it (stm.lstm_step.product_dtype)."""

    def __init__(self, lstm: list[tuple[torch.Tensor, ...]], in_std: torch.Tensor | None = None,
                 dtype: torch.dtype | None = None):
        H = lstm[0][1].shape[-1]
        self.layers = len(lstm)
        self.dtype = dtype
        self.store = DeferredGrads(self.layers, dtype)
        order, scale = gate_order(H, lstm[0][1].device)
        wb = []
        for k, (w_ih, w_hh, b_ih, b_hh) in enumerate(lstm):
            if k == 0 and in_std is not None:
                w_ih = w_ih / (in_std if in_std.dim() == 1 else in_std[:, None, :])
            w = torch.cat([w_ih, w_hh], dim=2)[:, order] * scale[:, None]  # (K, 4H, I + H)
            wb += [w.transpose(1, 2), ((b_ih + b_hh)[:, order] * scale).unsqueeze(1)]
        self.wb = DeferredWeights.apply(self.store, *wb)
        cast_once(self.store, wb)

    def __call__(self, x: torch.Tensor, h: list[torch.Tensor], c: list[torch.Tensor]
                 ) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """x (K, B, D), per-layer h, c (K, B, H) -> the next per-layer h, c (top layer last)."""
        out = StackStep.apply(x, self.store, *h, *c, *self.wb)
        return list(out[: self.layers]), list(out[self.layers:])

    def zeros(self, x: torch.Tensor) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Zero initial (h, c) per layer for inputs shaped like x (K, B, D)."""
        H = self.wb[0].shape[-1] // 4
        z = x.new_zeros(x.shape[0], x.shape[1], H)
        return [z] * self.layers, [z] * self.layers


class _LayerSeq(torch.autograd.Function):
    """n time steps of ONE layer for K models: inputs (K, B, n, I) known in advance (ground
    truth, or the layer below's outputs), so their projection is one batched matmul for all
    steps, and only the recurrent part is stepped. One autograd node per layer and chunk; the
    backward steps back through time, then computes the input and weight gradients in one
    batched matmul each. Weights as the stepper's: w_t (K, I + H, 4H) (gates i, f, o, 2g),
    b (K, 1, 4H); with dtype, every product in it (the input projection kept in it)."""

    @staticmethod
    def forward(ctx, x, h0, c0, w_t, b, dtype=None):
        K, B, n, I = x.shape
        H = h0.shape[-1]
        w_x, w_h = w_t[:, :I], w_t[:, I:].contiguous()
        if dtype is not None:
            x_, w_x, w_h, b = x.to(dtype), w_x.to(dtype), w_h.to(dtype), b.to(dtype)
        proj = torch.baddbmm(b, (x if dtype is None else x_).reshape(K, B * n, I), w_x).view(K, B, n, 4 * H)
        h, c = h0, c0
        hs, gds, odts, fs = [], [], [], []
        for t in range(n):
            if dtype is None:
                pre = torch.baddbmm(proj[:, :, t], h, w_h)
            else:
                pre = torch.baddbmm(proj[:, :, t], h.to(dtype), w_h).float()
            sig = torch.sigmoid(pre)
            i, f, o = sig[..., :H], sig[..., H: 2 * H], sig[..., 2 * H: 3 * H]
            g = sig[..., 3 * H:] * 2.0 - 1.0
            c_new = torch.addcmul(f * c, i, g)
            tc = torch.tanh(c_new)
            h_new = o * tc
            gds.append(torch.cat([g, c, tc, i * 2.0], -1) * torch.addcmul(sig, sig, sig, value=-1.0))
            odts.append(torch.addcmul(o, h_new, tc, value=-1.0))
            fs.append(f)
            hs.append(h_new)
            h, c = h_new, c_new
        out = torch.stack(hs, 2)
        ctx.save_for_backward(x, h0, w_t, out)
        ctx.local = (gds, odts, fs)
        ctx.dtype = dtype
        return out, h, c

    @staticmethod
    def backward(ctx, g_out, g_hn, g_cn):
        x, h0, w_t, out = ctx.saved_tensors
        gds, odts, fs = ctx.local
        K, B, n, I = x.shape
        H = h0.shape[-1]
        dt = ctx.dtype
        w_hT = w_t[:, I:].transpose(1, 2).contiguous()
        if dt is not None:
            w_hT = w_hT.to(dt)
        dh_rec = g_hn if g_hn is not None else torch.zeros_like(h0)
        dc = g_cn if g_cn is not None else torch.zeros_like(h0)
        dgs = [None] * n
        for t in reversed(range(n)):
            dh = dh_rec if g_out is None else dh_rec + g_out[:, :, t]
            dc = torch.addcmul(dc, odts[t], dh)
            dgates = torch.cat([dc, dc, dh, dc], -1).mul_(gds[t])
            dgs[t] = dgates
            dc = dc * fs[t]
            dh_rec = torch.bmm(dgates, w_hT) if dt is None else torch.bmm(dgates.to(dt), w_hT).float()
        dg = torch.stack(dgs, 2).view(K, B * n, 4 * H)
        h_prev = torch.cat([h0.unsqueeze(2), out[:, :, :-1]], 2).reshape(K, B * n, H)
        xh = torch.cat([x.reshape(K, B * n, I), h_prev], -1)
        bmm = torch.bmm if dt is None else lambda a, b: mm(a, b, dt)
        dw = bmm(xh.transpose(1, 2), dg)
        db = dg.sum(1, keepdim=True)
        dx = bmm(dg, w_t[:, :I].transpose(1, 2)).view(K, B, n, I) if ctx.needs_input_grad[0] else None
        return dx, dh_rec, dc, dw, db, None


def layer_sequence(stepper: PackedStackStepper, x: torch.Tensor, h: list[torch.Tensor], c: list[torch.Tensor]
                   ) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
    """n known inputs x (K, B, n, D) (centred, as the stepper's) through the whole stack, layer
    by layer: top hidden states (K, B, n, H) and the per-layer (h, c) after the last step."""
    h_out, c_out = [], []
    for k in range(stepper.layers):
        x, hn, cn = _LayerSeq.apply(x, h[k], c[k], stepper.wb[2 * k], stepper.wb[2 * k + 1], stepper.dtype)
        h_out.append(hn)
        c_out.append(cn)
    return x, h_out, c_out


def fused_sequence(lstm: list[tuple[torch.Tensor, ...]], z: torch.Tensor, h: list[torch.Tensor] | None = None,
                   c: list[torch.Tensor] | None = None) -> tuple[torch.Tensor, list[torch.Tensor], list[torch.Tensor]]:
    """Normalised inputs z (K, B, n, D) through each model's stack (`lstm` as PackedStackStepper's) in one
    fused LSTM call per model (oneDNN's multi-step kernel on CPU: per model it beats any batched step for long
    known input runs), from per-layer states h, c (K, B, H) or zeros; top hidden states (K, B, n, H) and the
    per-layer (h, c) after the last step."""
    outs, hn, cn = [], [], []
    weights = [t.unbind(0) for layer in lstm for t in layer]  # one autograd node per tensor, not one per model
    for k in range(z.shape[0]):
        flat = [w[k] for w in weights]
        hx = None if h is None else (torch.stack([x[k] for x in h]), torch.stack([x[k] for x in c]))
        if hx is None:
            zeros = z.new_zeros(len(lstm), z.shape[1], lstm[0][1].shape[-1])
            hx = (zeros, zeros)
        out, hk, ck = torch._VF.lstm(z[k], hx, flat, True, len(lstm), 0.0, True, False, True)
        outs.append(out)
        hn.append(hk)
        cn.append(ck)
    hn_, cn_ = torch.stack(hn, 1), torch.stack(cn, 1)  # (L, K, B, H)
    return torch.stack(outs), list(hn_.unbind(0)), list(cn_.unbind(0))
