"""Subnormal floats flushed to zero while training.

A mixture head fitted to teacher-forced demonstrations grows sharply peaked: the responsibilities of the far
components and the gradients through them fall below float32's smallest normal number (1.2e-38), and every
matrix product that meets them takes the CPU's slow path (`python -m stm.speed.bench --weights CHECKPOINT` times
a checkpoint's training iteration with them flushed and kept). Values that small are far below anything the loss or the
weights resolve, so training flushes them (the CPU's flush-to-zero and denormals-are-zero modes); the rest of the
process keeps IEEE arithmetic. The modes belong to the calling thread: a training process runs one torch thread
(experiments.runtime.processes.training_threads).
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch

_SUBNORMAL = 1e-40  # float32 holds it only as a subnormal


def flushing() -> bool:
    """Whether this thread's float arithmetic flushes subnormals to zero now."""
    return torch.tensor([_SUBNORMAL], dtype=torch.float32).mul(1.0).item() == 0.0


@contextlib.contextmanager
def subnormals_flushed(flush: bool = True) -> Iterator[None]:
    """Subnormals read and written as zero inside the block (where the CPU has the modes: x86 with SSE3), or with
    flush=False kept as IEEE has them; as they were before after it."""
    before = flushing()
    torch.set_flush_denormal(flush)
    try:
        yield
    finally:
        torch.set_flush_denormal(before)
