"""Windowed training with burn-in (a lever, not in the paper): instead of its whole demonstration,
each sample of a batch trains `window` consecutive steps of it, and the LSTM state at the window's first step
is warmed up by the `burn_in` ground-truth steps before it, run without gradient (R2D2's burn-in). An
iteration then unrolls window + burn_in steps instead of the longest demonstration (pick-and-place: ~170).

Where a window starts is drawn per sample so that every step of a demonstration is trained equally often: an
offset o uniform in [-(window - 1), length - 1], the window the steps [o, o + window) that lie in the
demonstration. A window that starts at the demonstration's start needs no burn-in (the state there is zero, as
in a whole-demonstration unroll); one that starts fewer than burn_in steps in warms up from the start, so its
state is exactly the teacher-forced state of a whole-demonstration unroll."""

from __future__ import annotations

from dataclasses import dataclass

import torch


@dataclass
class Windows:
    """Where each sample's window lies: steps (..., B, window + 1) the demonstration steps it reads (inputs and
    their next states; clamped where past the end), mask (..., B, window) True where a transition is trained,
    burn (..., B, burn_in) the burn-in steps before it, burn_valid where those lie in the demonstration."""

    steps: torch.Tensor
    mask: torch.Tensor
    burn: torch.Tensor
    burn_valid: torch.Tensor

    @property
    def longest(self) -> int:
        """Transitions in the longest window of the batch (the unroll's length)."""
        return int(self.mask.sum(-1).max())


def sample_windows(lengths: torch.Tensor, window: int, burn_in: int, generator: torch.Generator,
                   last_step: int) -> Windows:
    """Windows for demonstrations of `lengths` (..., B) transitions; `last_step` is the last index the state
    tensors hold (steps are clamped to it)."""
    low = 1 - window
    offsets = low + (torch.rand(lengths.shape, generator=generator) * (lengths - low)).long()
    start = offsets.clamp(min=0)
    end = torch.minimum(offsets + window, lengths)
    j = torch.arange(window + 1)
    steps = start[..., None] + j
    mask = steps[..., :-1] < end[..., None]
    burn = start[..., None] - burn_in + torch.arange(burn_in)
    return Windows(steps.clamp(max=last_step), mask, burn.clamp(min=0), burn >= 0)


def take_steps(x: torch.Tensor, steps: torch.Tensor) -> torch.Tensor:
    """x (..., B, T+1, D) at steps (..., B, n) -> (..., B, n, D)."""
    return torch.take_along_dim(x, steps[..., None], dim=-2)


@torch.no_grad()
def burn_in_state(stepper, centred: torch.Tensor, valid: torch.Tensor, hl: list[torch.Tensor],
                  cl: list[torch.Tensor]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
    """Per-layer (h, c) after stepping `stepper` over centred ground-truth inputs (..., B, n, D) from zero states
    hl, cl (..., B, H); a sample's state stays zero over its steps before the demonstration's start (valid
    False), so a short burn-in starts exactly where a whole-demonstration unroll does. No gradient."""
    for j in range(centred.shape[-2]):
        nh, nc = stepper(centred[..., j, :], hl, cl)
        keep = valid[..., j, None]
        hl = [torch.where(keep, a, b) for a, b in zip(nh, hl, strict=True)]
        cl = [torch.where(keep, a, b) for a, b in zip(nc, cl, strict=True)]
    return hl, cl
