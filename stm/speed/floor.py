"""The floor of a training iteration: its matrix products' arithmetic at the core's peak GEMM rate.

An iteration's arithmetic is almost all matrix products (the LSTM's gates, the mixture head, the feedback head's
rows, their gradients); everything else is elementwise maths and per-op overhead. `iteration_flops` counts the
products' floating-point operations (2 M N K each) from the shapes (the model's, the batch's and the schedule's);
`peak_gflops` measures the rate this core reaches on one large warm product (2048^3 on a CPU: warm-up, then the best
of a few); their quotient is the floor, the time the iteration could take if it did nothing but its products, each
at the core's best. The bench's floor_ratio is the iteration's time over it (stm.speed.bench).

`record_matmuls` and `replayer` time the products the iteration really calls (op, shapes, strides, dtypes), replayed
alone on warm operands (one tensor per layout, in cache): what the iteration's own product shapes cost at best, which
small per-step products may leave well above the floor. Products issued outside ATen's dispatcher (the C++ steps'
bf16 GEMM through MKL) are not seen there.

A fused LSTM layer (oneDNN's, behind nn.LSTM on the CPU; its input is time-major) does its products inside one op;
it is recorded as the products an unfused layer needs: the input projection of all steps at once, one recurrent
product per step, and backward the same transposed plus the two weight gradients over all steps at once.
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_map

from envs.tasks.base import StateLayout
from stm.config import ModelConfig, TrainConfig

aten = torch.ops.aten
MATMUL_OPS = {aten.mm, aten.addmm, aten.bmm, aten.baddbmm, aten.addbmm, aten.mv, aten.addmv, aten.dot}
POINT_FEEDBACKS = ("component_mean", "mixture_mean")  # the self-fed steps read only the head rows they need
PEAK_SIZE = {"cpu": 2048, "cuda": 8192}  # the square product the peak is measured on, per device type


def _self_fed_steps(T: int, u: int, v: int) -> int:
    """Self-fed input steps of T under [gt]*u + [self]*v repeated (stm.training.autoconditioning.schedule)."""
    if v == 0:
        return 0
    full, rest = divmod(T, u + v)
    return full * v + max(0, rest - u)


def iteration_flops(model_cfg: ModelConfig, layout: StateLayout, cfg: TrainConfig, batch: int, steps: int
                    ) -> dict[str, int]:
    """Floating-point operations of one model's training iteration on `batch` sequences of `steps` inputs (the
    whole demos) under cfg's schedule: the matrix products an unfused step-by-step LSTM stack, the head and the
    feedback head's rows need, forward and backward. Per part: lstm, head, feedback and their total.

    lstm: per layer and step the gates' product ([x, h] -> 4H) forward, its weight gradient, and the gradient of
    [x, h], less the bottom layer's input gradient wherever the input is not fed back (ground truth, or detached
    feedback). head: the head on every step's top hidden state, forward, its input and weight gradients. feedback:
    on each self-fed step the head rows the fed-back state reads (the mixture logits and the first `dims` mean
    coordinates per component, or `dims` outputs of a deterministic head), forward and, unless detached, both
    gradients. Sampled feedback reads the whole head per step and is not counted (a ValueError)."""
    if cfg.v > 0 and model_cfg.head == "mdn" and cfg.feedback not in POINT_FEEDBACKS:
        raise ValueError(f"the floor counts point feedback ({', '.join(POINT_FEEDBACKS)}), not {cfg.feedback!r}")
    H, L, D, N = model_cfg.hidden_size, model_cfg.num_layers, layout.dim, batch * steps
    fed = batch * _self_fed_steps(steps, cfg.u, cfg.v)
    gates = 4 * H
    inputs = [D + H] + [2 * H] * (L - 1)  # [x, h] per layer
    forward = sum(2 * N * gates * i for i in inputs)
    input_grad_rows = 0 if cfg.detach_feedback else fed  # the bottom layer's x gradient: fed-back rows only
    data_grad = forward - 2 * (N - input_grad_rows) * gates * D
    lstm = 2 * forward + data_grad  # forward, weight gradient, [x, h] gradient
    m = model_cfg.mixtures
    out = m * (D + 2) if model_cfg.head == "mdn" else D
    head = 3 * 2 * N * H * out
    dims = layout.phi.stop if cfg.phi_mode == "free" else layout.phi.start
    rows = m + m * dims if model_cfg.head == "mdn" else dims
    feedback = (1 if cfg.detach_feedback else 3) * 2 * fed * H * rows
    return {"lstm": lstm, "head": head, "feedback": feedback, "total": lstm + head + feedback}


def peak_gflops(dtype: torch.dtype, clock: Callable[[], float], device: torch.device | None = None,
                n: int | None = None, reps: int = 5) -> float:
    """GFLOP per second of `clock` of one warm n^3 product in `dtype` (n: PEAK_SIZE of the device's type): a
    warm-up, then the best of `reps` (the least disturbed by other load)."""
    device = device or torch.device("cpu")
    n = n or PEAK_SIZE.get(device.type, PEAK_SIZE["cpu"])
    a, b = (torch.randn(n, n, device=device).to(dtype) for _ in range(2))
    out = torch.empty(n, n, dtype=dtype, device=device)

    def product() -> float:
        start = clock()
        torch.mm(a, b, out=out)
        if device.type == "cuda":
            torch.cuda.synchronize(device)
        return clock() - start

    product()
    best = min(product() for _ in range(reps))
    return 2 * n ** 3 / max(best, 1e-9) / 1e9


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

    def make(self, device: torch.device | None = None) -> torch.Tensor:
        size = 1 + sum((n - 1) * s for n, s in zip(self.shape, self.stride, strict=True) if n > 0)
        values = torch.randn(size, device=device) if self.dtype.is_floating_point else \
            torch.zeros(size, device=device)
        return values.to(self.dtype).as_strided(self.shape, self.stride)


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


def product_flops(calls: list[tuple]) -> int:
    """Floating-point operations of recorded products: 2 M N P per (batch of) (M, P) @ (P, N) (a vector's N = 1)."""
    total = 0
    for _op, args, _kwargs in calls:
        a, b = [x for x in args if isinstance(x, _Spec) and len(x.shape) >= 1][-2:]
        batches = a.shape[0] if len(a.shape) == 3 else 1
        rows = a.shape[-2] if len(a.shape) >= 2 else 1
        cols = b.shape[-1] if len(b.shape) >= 2 else 1
        total += 2 * batches * rows * a.shape[-1] * cols
    return total


def replayer(calls: list[tuple], device: torch.device | None = None):
    """A function that calls the recorded products again, in order, on one random tensor per layout (on `device`,
    the CPU by default), reused by every call: warm in cache, as an iteration's products read what the op before
    just wrote. On CUDA the fused LSTM's products (cuDNN's, not oneDNN's) are not recorded."""
    shared: dict[tuple, torch.Tensor] = {}

    def operand(spec: _Spec) -> torch.Tensor:
        key = (spec.shape, spec.stride, spec.dtype)
        if key not in shared:
            shared[key] = spec.make(device)
        return shared[key]

    made = [(func, *tree_map(lambda a: operand(a) if isinstance(a, _Spec) else a, (args, kwargs)))
            for func, args, kwargs in calls]

    def replay():
        for func, args, kwargs in made:
            func(*args, **kwargs)

    replay.calls = made  # what it replays, operands included
    return replay
