"""A training iteration's forward and backward captured once as a CUDA graph, then replayed (CUDA only).

Why: an iteration is thousands of small kernels (every self-fed step is a few per layer); launched from
Python each costs microseconds of host time, a graph replays them all in one launch. A graph replays fixed
kernels on fixed memory, so it serves iterations of static shapes and no host work: whole demonstrations
padded to the longest demo (stm.training.batches: full), no input noise or sampled feedback (those draw from each
seed's CPU generator) and no windows (their lengths vary). Per schedule (the seeds' (u, v) groups) one graph
is captured after a few warm-up iterations on a side stream (torch.cuda.graphs' recipe); each iteration then
copies its batches into the graph's static inputs and replays it: the per-seed losses come out in its static
outputs and the gradients in the pack's .grad (graph memory, overwritten by the next replay). Clipping and the
Adam step stay outside, as stm.training.loop runs them. Anything that cannot be captured falls back to the eager step.
"""

from __future__ import annotations

import logging
from collections.abc import Callable

import torch

from stm.config import TrainConfig
from stm.training.batches import Batch

log = logging.getLogger(__name__)

WARMUP = 3  # eager iterations on a side stream before capture (lazy init, allocator, cuDNN plans)
MAX_GRAPHS = 4  # distinct schedules captured per run (tf_warmup and a seed's own (u, v) add some)


def capturable(cfg: TrainConfig) -> bool:
    """Whether an iteration under cfg has static shapes and no host work: whole demos, no CPU random draws."""
    return cfg.window == 0 and cfg.input_noise == 0 and cfg.feedback != "sample"


class _Captured:
    def __init__(self, fn: Callable[[list[Batch]], list[torch.Tensor]], batches: list[Batch],
                 params: list[torch.Tensor]):
        self.static = [Batch(b.states.clone(), b.q.clone(), b.psi.clone(), b.mask.clone()) for b in batches]
        side = torch.cuda.Stream()
        side.wait_stream(torch.cuda.current_stream())
        with torch.cuda.stream(side):
            for _ in range(WARMUP):
                for p in params:
                    p.grad = None
                fn(self.static)
        torch.cuda.current_stream().wait_stream(side)
        for p in params:
            p.grad = None
        self.graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(self.graph):
            self.losses = fn(self.static)
        self.grads = [p.grad for p in params]

    def replay(self, batches: list[Batch], params: list[torch.Tensor]) -> list[torch.Tensor]:
        for dst, src in zip(self.static, batches, strict=True):
            for d, s in ((dst.states, src.states), (dst.q, src.q), (dst.psi, src.psi), (dst.mask, src.mask)):
                d.copy_(s, non_blocking=True)
        self.graph.replay()
        for p, g in zip(params, self.grads, strict=True):
            p.grad = g
        return self.losses


class StepGraphs:
    """The captured iterations of one training run, keyed by their schedule groups and shapes."""

    def __init__(self, params: list[torch.Tensor]):
        self.params = params
        self.graphs: dict[tuple, _Captured] = {}
        self.broken = False  # a capture failed: eager from then on

    def run(self, key: tuple, fn: Callable[[list[Batch]], list[torch.Tensor]], batches: list[Batch]
            ) -> list[torch.Tensor] | None:
        """Per group its (k,) losses, the gradients in the params' .grad; None where this iteration cannot be
        replayed (the caller runs it eagerly). fn(batches) must run forward and backward with no host work."""
        key = (key, *(tuple(b.states.shape) for b in batches))
        graph = self.graphs.get(key)
        if graph is None:
            if self.broken or len(self.graphs) >= MAX_GRAPHS:
                return None
            try:
                graph = self.graphs[key] = _Captured(fn, batches, self.params)
            except Exception as exc:  # an op that needs the host: the run goes on eagerly
                log.warning("CUDA graph capture failed, training eagerly: %s", str(exc).splitlines()[0])
                self.broken = True
                for p in self.params:
                    p.grad = None
                return None
            log.info("captured a CUDA graph of the training iteration for %s", key)
        return graph.replay(batches, self.params)
