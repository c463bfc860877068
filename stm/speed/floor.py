"""The matrix-product floor of a training iteration: its matrix products replayed alone.

An iteration's arithmetic is almost all matrix products (LSTM gates, MDN head, their
gradients); everything else is per-op overhead and small elementwise maths. Recording
the products one iteration calls (op, shapes, strides, dtypes) and replaying them on
fresh tensors, without anything in between, times what the iteration could cost if
nothing else did: the floor. The replay in bfloat16 is the floor with bf16 products.
Fresh tensors (one per argument of each call, as the iteration's saved activations are)
come cold from memory; the warm replay (`warm=True`) reuses one tensor per layout, as an
iteration does where a product reads what the last op just wrote: products at their
best, a lower bound under the floor (measured about 0.75-0.8x of it at the pick-and-place size).

A fused LSTM layer (oneDNN's, behind nn.LSTM on the CPU; its input is time-major) does
its products inside one op; it is recorded as the products an unfused layer needs: the
input projection of all steps at once, one recurrent product per step, and backward the
same transposed plus the two weight gradients over all steps at once. (oneDNN's fused
layer can beat these, so a teacher-forced iteration may come close to its floor.)
"""

from __future__ import annotations

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map

aten = torch.ops.aten
MATMUL_OPS = {aten.mm, aten.addmm, aten.bmm, aten.baddbmm, aten.addbmm, aten.mv, aten.addmv, aten.dot}


class _Spec:
    """A tensor argument's layout: replayed as random values with the same shape and strides."""

    def __init__(self, shape: tuple[int, ...], stride: tuple[int, ...], dtype: torch.dtype = torch.float32):
        self.shape, self.stride, self.dtype = tuple(shape), tuple(stride), dtype

    @classmethod
    def of(cls, t: torch.Tensor) -> _Spec:
        return cls(t.shape, t.stride(), t.dtype)

    @classmethod
    def matrix(cls, rows: int, cols: int, dtype: torch.dtype, transposed: bool = False) -> _Spec:
        """A contiguous matrix, or the transposed view of a contiguous (cols, rows) one."""
        return cls((rows, cols), (1, rows) if transposed else (cols, 1), dtype)

    def make(self, dtype: torch.dtype | None, device: torch.device | None = None) -> torch.Tensor:
        dtype = dtype if dtype is not None and self.dtype.is_floating_point else self.dtype
        size = 1 + sum((n - 1) * s for n, s in zip(self.shape, self.stride, strict=True) if n > 0)
        return torch.randn(size, dtype=dtype, device=device).as_strided(self.shape, self.stride)


def _lstm_layer(x: torch.Tensor, w_ih: torch.Tensor, backward: bool) -> list[tuple]:
    """The products of an unfused LSTM layer over x (T, B, I) with w_ih (4H, I)."""
    T, B = x.shape[:2]
    (G, I), H, dt = w_ih.shape, w_ih.shape[0] // 4, w_ih.dtype
    M = _Spec.matrix
    if not backward:  # gates = b + x W_ih^T (all steps), then + h_{t-1} W_hh^T step by step
        return ([(aten.addmm.default, (_Spec((G,), (1,), dt), M(T * B, I, dt), M(I, G, dt, True)), {})]
                + [(aten.addmm.default, (M(B, G, dt), M(B, H, dt), M(H, G, dt, True)), {})] * T)
    return ([(aten.mm.default, (M(B, G, dt), M(G, H, dt)), {})] * T  # dh_{t-1} = dgates W_hh, step by step
            + [(aten.mm.default, (M(T * B, G, dt), M(G, I, dt)), {}),  # dx
               (aten.mm.default, (M(G, T * B, dt, True), M(T * B, I, dt)), {}),  # dW_ih
               (aten.mm.default, (M(G, T * B, dt, True), M(T * B, H, dt)), {})])  # dW_hh


class _Record(TorchDispatchMode):
    def __init__(self):
        super().__init__()
        self.calls: list[tuple] = []

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        if func.overloadpacket in MATMUL_OPS:
            spec = tree_map(lambda a: _Spec.of(a) if isinstance(a, torch.Tensor) else a, (args, kwargs))
            self.calls.append((func, *spec))
        elif func.overloadpacket in (aten.mkldnn_rnn_layer, aten.mkldnn_rnn_layer_backward):  # (input, w_ih, ...)
            self.calls += _lstm_layer(args[0], args[1], backward=func.overloadpacket is not aten.mkldnn_rnn_layer)
        return func(*args, **kwargs)


def record_matmuls(fn) -> list[tuple]:
    """The matrix products one call of fn makes, forward and backward: (op, args, kwargs) with tensor specs."""
    with _Record() as rec:
        fn()
    return rec.calls


def replayer(calls: list[tuple], dtype: torch.dtype | None = None, device: torch.device | None = None,
             warm: bool = False):
    """A function that calls the recorded products again, in order, on fresh random tensors (in `dtype` where
    given: every floating-point argument cast to it; on `device`, the CPU by default), or with `warm` on one
    tensor per layout, reused by every call (in cache). On CUDA the fused LSTM's products (cuDNN's, not
    oneDNN's) are not recorded: the floor of a teacher-forced iteration leaves them out."""
    shared: dict[tuple, torch.Tensor] = {}

    def operand(spec: _Spec) -> torch.Tensor:
        if not warm:
            return spec.make(dtype, device)
        key = (spec.shape, spec.stride, spec.dtype)
        if key not in shared:
            shared[key] = spec.make(dtype, device)
        return shared[key]

    made = [(func, *tree_map(lambda a: operand(a) if isinstance(a, _Spec) else a, (args, kwargs)))
            for func, args, kwargs in calls]

    def replay():
        for func, args, kwargs in made:
            func(*args, **kwargs)

    replay.calls = made  # what it replays, operands included
    return replay
