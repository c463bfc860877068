"""The self-fed steps of the auto-conditioned unroll, a whole segment per call, in C++ (stm/csrc/segment.cpp).

A self-fed step of stm.training.autoconditioning.unroll in Python is the feedback head, the fed-back state
(stm.model.feedback_state with the tip kinematics of stm.fk) and the LSTM stack step (stm.lstm_step): ~330 small
ATen calls forward and backward, each paying Python's per-op cost. `cpp_steps` gives the unroll one autograd
node per run of self-fed steps instead, whose forward and backward make no ATen call per step: the products go to
BLAS with the arguments ATen's products pass it (stm/csrc/products.cpp), the gates' sigmoid and tanh and the tip's
sine are computed as ATen computes them (vec_math.cpp), and the rest (the cell update, the head's pick of a
component, the fed-back state, their backward) runs in plain loops over the step's rows (lstm_step.cpp,
feedback_state.cpp), on buffers made once per segment; so the results are those of the ATen calls they replace,
bit for bit, and an iteration's ATen calls are its segments' and chunks' set-up (about 4,300 at the pick-and-place
size, from 23,700 with the per-step calls issued from C++). And one node per ground-truth chunk between them, a
layer sequence in C++ (lstm_step.cpp, stepped likewise; oneDNN's fused layer, which the Python path calls for one
model, pays more set-up than five steps cost; the Python layer sequence, for a pack, pays Python's per-op cost).
Weight gradients are one product per layer and chunk (or segment), summed in place over the unroll (_GradSums) and
handed to autograd once; deferring all rows to one product after the unroll, as the Python steps do, would copy
every row once more.

TrainConfig.step_kernel "auto" (the default, where the extension builds) or "cpp" selects it where it applies: on
the CPU, an MDN head feeding back component_mean or a deterministic head; phi fed back free, or grounded where the
task's phi is the tip plus a function of psi (checked on the batch); the inputs not requested back. Elsewhere, and
with "auto" where the extension cannot be built (stm.cpp_ext warns once), the Python steps run.
tests/test_stm_self_fed.py holds it to the Python path.

With bf16 products (train.matmul_dtype "bfloat16", float32 weights) the segment's and the layer sequence's
products, forward, backward and weight gradients, take bf16 operands, the weights cast once per unroll (the
stepper's casts, and the feedback head's rows here), and give float32, as stm.lstm_step's do; the state, gate
maths, fed-back state and kinematics stay float32. Where libtorch carries MKL's bf16 x bf16 -> float32 GEMM
(x86) the C++ products take it: unlike the Python path's ATen bf16 products, no bf16 rounding of the products'
outputs and the biases added in float32 (and the feedback head's weight gradient summed in float32 per segment,
where autograd sums the Python path's per-step bf16 ones in bf16); the ground-truth chunks of one model run bf16
products too, where the Python path calls oneDNN's float32 fused layer. tests/test_stm_self_fed.py holds it to
the Python bf16 path within bf16's rounding.
"""

from __future__ import annotations

import torch

from stm.config import TrainConfig
from stm.cpp_ext import self_fed_extension, step_kernel
from stm.fk import TipKinematics
from stm.packed import PackView

JOINTS = 7


def supported(view: PackView, cfg: TrainConfig, return_inputs: bool = False) -> bool:
    """Whether the C++ segment may run this unroll's self-fed steps (before the task and kinematics checks)."""
    return (step_kernel(cfg.step_kernel, view.state_mean.device.type) == "cpp" and cfg.v > 0 and not return_inputs
            and cfg.matmul_dtype in ("float32", "bfloat16") and (not view.is_mdn or cfg.feedback == "component_mean"))


def _phi_offset(task, psi: torch.Tensor, dtype: torch.dtype) -> torch.Tensor | None:
    """task.phi(tip, psi) - tip (K, B, T, 3) where phi is the tip plus a function of psi alone (as every task's),
    else None. Checked on two probe tips: the difference must be bitwise the same."""
    zero = psi.new_zeros(*psi.shape[:-1], 3).to(dtype)
    off = task.phi(zero, psi)
    if off.shape != zero.shape:
        return None
    probe = torch.linspace(-0.7, 0.9, 3, dtype=dtype).expand_as(zero)
    return off if torch.equal(task.phi(probe, psi), probe + off) else None


def _interleave(dw: list[torch.Tensor], db: list[torch.Tensor]) -> list[torch.Tensor]:
    """Per-layer weight and bias gradients in the stepper's order (w_0, b_0, w_1, ...)."""
    return [g for pair in zip(dw, db, strict=True) for g in pair]


class _Constants:
    """What a segment reads besides the states and weights: normalisation, joint limits, the FK tables."""

    def __init__(self, view: PackView, task, kin: TipKinematics, cfg: TrainConfig, layers: int):
        layout = task.layout
        self.layers = layers
        self.mean, self.lower, self.upper = view.state_mean, kin.lower, kin.upper
        plan = kin.grad_plan
        self.fk = [kin.signs, kin.phases, plan.index, kin.coef, kin.row_sums]
        free = cfg.phi_mode == "free"
        dims = layout.phi.stop if free else layout.phi.start
        self.dims = dims
        self.ints = [plan.degree, plan.slots, plan.monomials, view.config.mixtures if view.is_mdn else 0, dims,
                     int(layout.gripper), int(free), layout.phi.start, layout.phi_dim, int(cfg.detach_feedback)]


class _GradSums:
    """The LSTM weight gradients of an unroll's C++ nodes (its ground-truth chunks and segments), summed in place:
    each node's backward adds its chunk's product into one buffer per layer (beta = 1) instead of handing autograd
    its own to add (a pass over the gradient per node and layer). The unroll's first node hands autograd the sums,
    the others None: every other node follows it in the chain of h, c, so autograd runs all the others' backwards
    (those it runs at all) before the first's, each once (once_differentiable)."""

    def __init__(self):
        self.nodes = 0
        self.dw: list[torch.Tensor] = []
        self.db: list[torch.Tensor] = []

    def register(self) -> bool:
        """A node's forward: whether it is the unroll's first."""
        self.nodes += 1
        return self.nodes == 1

    def hand(self, first: bool, dw: list[torch.Tensor], db: list[torch.Tensor]) -> list[torch.Tensor | None]:
        """A node's backward, after adding its gradients to the sums (dw, db: them): the weights' gradients."""
        if not first:
            self.dw, self.db = dw, db
            return [None] * (2 * len(dw))
        self.dw, self.db = [], []
        return _interleave(dw, db)


class _Segment(torch.autograd.Function):
    """n self-fed steps of the stack: (h, c per layer (K, B, H), q before the first step (K, B, 7)) -> the top
    hidden states (K, B, n, H) and the per-layer h, c after the last step."""

    @staticmethod
    def forward(ctx, consts: _Constants, sums: _GradSums, low: list[torch.Tensor], q0, psi, offset, w_fb, b_fb,
                *hc_wb):
        L = consts.layers
        ctx.sums, ctx.first = sums, sums.register()
        h, c, wb = list(hc_wb[:L]), list(hc_wb[L: 2 * L]), hc_wb[2 * L:]
        block, h, c, seg = self_fed_extension().segment_forward(
            h, c, list(wb[0::2]), list(wb[1::2]), w_fb, b_fb, q0, psi, offset, consts.mean, consts.lower,
            consts.upper, consts.fk, consts.ints, low)
        ctx.seg = seg
        ctx.set_materialize_grads(False)
        return (block, *h, *c)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_block, *g_hc):
        L = len(g_hc) // 2
        sums = ctx.sums
        dh, dc, dw_fb, db_fb, dw, db = self_fed_extension().segment_backward(ctx.seg, g_block, list(g_hc[:L]),
                                                                              list(g_hc[L:]), sums.dw, sums.db)
        ctx.seg = None
        return (None, None, None, None, None, None, dw_fb, db_fb, *dh, *dc, *sums.hand(ctx.first, dw, db))


class _Sequence(torch.autograd.Function):
    """n known inputs (K, B, n, D) through the stack (the C++ layer sequence): top hidden states (K, B, n, H) and
    the per-layer h, c after the last step. The inputs get no gradient (ground truth)."""

    @staticmethod
    def forward(ctx, layers: int, sums: _GradSums, recurrent, low: list[torch.Tensor], x, *hc_wb):
        ctx.sums, ctx.first = sums, sums.register()
        h, c, wb = list(hc_wb[:layers]), list(hc_wb[layers: 2 * layers]), hc_wb[2 * layers:]
        out, h, c, seq = self_fed_extension().sequence_forward(x, h, c, list(wb[0::2]), list(wb[1::2]), *recurrent,
                                                               low)
        ctx.seq = seq
        ctx.set_materialize_grads(False)
        return (out, *h, *c)

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, g_out, *g_hc):
        L = len(g_hc) // 2
        sums = ctx.sums
        dh, dc, dw, db = self_fed_extension().sequence_backward(ctx.seq, g_out, list(g_hc[:L]), list(g_hc[L:]),
                                                                sums.dw, sums.db)
        ctx.seq = None
        return (None, None, None, None, None, *dh, *dc, *sums.hand(ctx.first, dw, db))


class CppSteps:
    """An unroll's steps after the first chunk in C++: `known` runs ground-truth chunks, `self_fed` self-fed
    segments; both on the unroll's stepper's weights (w (K, I + H, 4H) with the gate columns i, f, o, 2g). With
    bf16 products (the stepper's store has a dtype) the products take the weights cast once per unroll: the
    stepper's w per layer (`low_w`), and the feedback head's w_fb here (first in `low_fb`)."""

    def __init__(self, consts: _Constants, stepper, psi: torch.Tensor, offset: torch.Tensor, w_fb, b_fb):
        self.consts, self.stepper, self.psi, self.offset = consts, stepper, psi, offset
        self.w_fb, self.b_fb = w_fb, b_fb
        self.layers = stepper.layers
        self.sums = _GradSums()
        self._recurrent: tuple[list[torch.Tensor], list[torch.Tensor]] | None = None
        dt = stepper.store.dtype
        self.low_w = list(stepper.store.low[0::2]) if dt is not None else []
        self.low_fb = [w_fb.detach().to(dt), *self.low_w] if dt is not None else []

    def recurrent(self) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        """Per layer the recurrent rows of w (K, H, 4H) and their transpose (K, 4H, H), contiguous: copied once per
        unroll for all its ground-truth chunks (the weights are transposed views; the gradients are the chunks')."""
        if self._recurrent is None:
            if self.low_w:  # bf16 products read the cast weights as they are
                self._recurrent = ([], [])
                return self._recurrent
            with torch.no_grad():
                ws = [w.detach() for w in self.stepper.wb[0::2]]
                H = ws[0].shape[-1] // 4
                self._recurrent = ([w[:, -H:].contiguous() for w in ws],
                                   [w[:, -H:].transpose(1, 2).contiguous() for w in ws])
        return self._recurrent

    def _split(self, out):
        L = self.layers
        return out[0], list(out[1: 1 + L]), list(out[1 + L:])

    def known(self, x: torch.Tensor, h: list[torch.Tensor], c: list[torch.Tensor]):
        """Centred known inputs (K, B, n, D) from per-layer h, c -> (top hidden states (K, B, n, H), h, c)."""
        st = self.stepper
        return self._split(_Sequence.apply(self.layers, self.sums, self.recurrent(), self.low_w, x, *h, *c, *st.wb))

    def self_fed(self, h: list[torch.Tensor], c: list[torch.Tensor], q0: torch.Tensor, t: int, n: int):
        """n self-fed steps from input step t, q (K, B, 7) before them -> (top hidden states (K, B, n, H), h, c)."""
        st = self.stepper
        return self._split(_Segment.apply(self.consts, self.sums, self.low_fb, q0, self.psi[:, :, t: t + n],
                                          self.offset[:, :, t: t + n], self.w_fb, self.b_fb, *h, *c, *st.wb))


def cpp_steps(view: PackView, cfg: TrainConfig, task, kin, stepper, psi: torch.Tensor,
              return_inputs: bool = False) -> CppSteps | None:
    """The C++ steps for an unroll (psi (K, B, T+1, P): the unroll's); None where the Python steps must run (see
    the module docstring)."""
    if not supported(view, cfg, return_inputs) or self_fed_extension() is None:
        return None
    grounded = cfg.phi_mode == "grounded"
    if grounded and not isinstance(kin, TipKinematics):
        return None
    if stepper.wb[0].dtype not in (torch.float32, torch.float64):  # the C++ step loops: float and double
        return None
    dt = stepper.store.dtype
    if dt is not None and (dt != torch.bfloat16 or stepper.wb[0].dtype != torch.float32):
        return None  # bf16 products give float32 (products.h, low_bmm)
    dtype = view.state_mean.dtype
    offset = _phi_offset(task, psi, dtype) if grounded else psi.new_zeros(*psi.shape[:-1], 3)
    if offset is None:
        return None
    consts = _Constants(view, task, kin, cfg, stepper.layers)
    w_fb, b_fb = view.feedback_weights(cfg.feedback, consts.dims)
    return CppSteps(consts, stepper, psi, offset, w_fb, b_fb)
