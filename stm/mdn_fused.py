"""The MDN head's training loss as one C++ op (stm/csrc/mdn_nll.cpp), forward and closed-form backward.

stm.mdn.mixture_nll(*stm.mdn.split_params(raw, ...), target) is ~15 ATen calls forward and more backward, each a
pass in memory over the batch's B T m D mixture means: at the pick-and-place size more time than the iteration's
matrix products. The fused op reads each row's means once forward and once backward and keeps three numbers per
component for the backward (responsibility-weighted coefficients), so it costs about one pass each way.

Same maths as stm.mdn (sigma = sigma_min + softplus, log-softmax weights, max-shifted log-sum-exp), float32
rounding apart: tests/test_stm_mdn_fused.py holds it to stm.mdn. `mixture_nll` takes the fused op where it applies
(the extension is built, float32 or float64 CPU tensors, a target of the head output's leading shape) and stm.mdn
elsewhere; the training loss uses it where the C++ kernel runs (TrainConfig.step_kernel "auto", the default, where
the extension builds, or "cpp"; stm.model.step_losses); "python" keeps stm.mdn.
"""

from __future__ import annotations

import torch

from stm import mdn
from stm.cpp_ext import self_fed_extension

DTYPES = (torch.float32, torch.float64)


class _MixtureNLL(torch.autograd.Function):
    """(raw (N, m (D + 2)), target (N, D)) -> NLL (N,); gradients for raw and, where it asks, the target."""

    @staticmethod
    def forward(ctx, raw: torch.Tensor, target: torch.Tensor, mixtures: int, sigma_min: float):
        need = any(ctx.needs_input_grad[:2])
        nll, coef = self_fed_extension().mdn_nll_forward(raw, target, mixtures, sigma_min, need)
        if need:
            ctx.save_for_backward(raw, target, coef)
        ctx.mixtures = mixtures
        return nll

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad: torch.Tensor):
        raw, target, coef = ctx.saved_tensors
        g_raw, g_target = self_fed_extension().mdn_nll_backward(grad, raw, target, coef, ctx.mixtures,
                                                                ctx.needs_input_grad[1])
        return (g_raw if ctx.needs_input_grad[0] else None), (g_target if ctx.needs_input_grad[1] else None), \
            None, None


def applies(raw: torch.Tensor, target: torch.Tensor) -> bool:
    """Whether the fused op can compute this loss (else stm.mdn does)."""
    return (raw.dtype in DTYPES and target.dtype == raw.dtype and raw.device.type == "cpu"
            and target.device == raw.device and raw.shape[:-1] == target.shape[:-1]
            and self_fed_extension() is not None)


def fused_nll(raw: torch.Tensor, target: torch.Tensor, mixtures: int, sigma_min: float) -> torch.Tensor:
    """The fused op itself: per-element NLL (...) of target (..., D) under raw head outputs (..., m (D + 2))."""
    lead, dim = raw.shape[:-1], target.shape[-1]
    if raw.shape[-1] != mdn.head_size(mixtures, dim):
        raise ValueError(f"head outputs of {raw.shape[-1]} columns for {mixtures} Gaussians of dimension {dim}")
    flat_raw = raw.reshape(-1, raw.shape[-1]).contiguous()
    flat_target = target.reshape(-1, dim).contiguous()
    return _MixtureNLL.apply(flat_raw, flat_target, mixtures, float(sigma_min)).view(lead)


def mixture_nll(raw: torch.Tensor, target: torch.Tensor, mixtures: int, sigma_min: float,
                fused: bool = True) -> torch.Tensor:
    """stm.mdn.mixture_nll(*stm.mdn.split_params(raw, mixtures, D, sigma_min), target): with the fused op where
    `fused` and it applies, else stm.mdn's (the reference)."""
    if fused and applies(raw, target):
        return fused_nll(raw, target, mixtures, sigma_min)
    return mdn.mixture_nll(*mdn.split_params(raw, mixtures, target.shape[-1], sigma_min), target)
