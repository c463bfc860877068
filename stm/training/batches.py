"""The demonstrations as tensors, and the training batches drawn from them: per seed, from its own generator,
B demonstrations (without replacement when there are enough) or windows of them (stm.training.windows); a pack's seeds'
batches stacked on a leading model axis."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass, field

import torch

from envs.kinematics import default_kinematics
from envs.tasks.base import Demos, Task
from stm.config import TrainConfig
from stm.training.windows import Windows, sample_windows, take_steps


@dataclass
class Batch:
    """Tensors of a batch of demos, cropped to the longest: states (..., B, T+1, D) raw units, q (..., B, T+1, 7),
    psi (..., B, T+1, P), mask (..., B, T) True where transition t -> t+1 is valid; a pack's batches have a
    leading model axis. Windows of demos (stm.training.windows) carry their burn-in: raw states (..., B, n, D) and where
    they are valid."""

    states: torch.Tensor
    q: torch.Tensor
    psi: torch.Tensor
    mask: torch.Tensor
    burn: tuple[torch.Tensor, torch.Tensor] | None = None

    def to(self, device: torch.device) -> Batch:
        """This batch on `device` (itself where it is there already)."""
        if self.states.device == device:
            return self
        burn = None if self.burn is None else tuple(t.to(device) for t in self.burn)
        return Batch(self.states.to(device), self.q.to(device), self.psi.to(device), self.mask.to(device), burn)


@dataclass
class Draw:
    """One seed's draw for an iteration: which demos, and their windows when training on windows."""

    idx: torch.Tensor
    windows: Windows | None = None


@dataclass
class DemoTensors:
    states: torch.Tensor
    q: torch.Tensor
    psi: torch.Tensor
    lengths: torch.Tensor
    extra: dict = field(default_factory=dict)

    @classmethod
    def build(cls, task: Task, demos: Demos) -> DemoTensors:
        if len(demos) == 0:
            raise ValueError("the demonstration set is empty")
        states = task.demo_states(demos, default_kinematics(torch.float64))
        if states.shape[-1] != task.layout.dim:
            raise ValueError(f"demo states have size {states.shape[-1]}, task layout says {task.layout.dim}")
        return cls(states=torch.as_tensor(states, dtype=torch.float32),
                   q=torch.as_tensor(demos.q, dtype=torch.float32),
                   psi=torch.as_tensor(demos.psi, dtype=torch.float32),
                   lengths=torch.as_tensor(demos.lengths, dtype=torch.long))

    def __len__(self) -> int:
        return len(self.lengths)

    def batch(self, idx: torch.Tensor, full: bool = False) -> Batch:
        """Demos idx (..., B), cropped to the longest (full: padded to the longest demo of all, a static shape)."""
        lengths = self.lengths[idx]
        T = int((self.lengths if full else lengths).max())
        mask = torch.arange(T) < lengths[..., None]
        return Batch(self.states[idx, : T + 1], self.q[idx, : T + 1], self.psi[idx, : T + 1], mask)

    def windows(self, idx: torch.Tensor, window: int, burn_in: int, generator: torch.Generator) -> Windows:
        return sample_windows(self.lengths[idx], window, burn_in, generator, self.states.shape[1] - 1)

    def window_batch(self, idx: torch.Tensor, windows: Windows) -> Batch:
        """The windows of demos idx (self.windows), cropped to the longest, with their burn-in."""
        T = windows.longest
        steps = windows.steps[..., : T + 1]
        states = self.states[idx]
        burn = (take_steps(states, windows.burn), windows.burn_valid) if windows.burn.shape[-1] else None
        return Batch(take_steps(states, steps), take_steps(self.q[idx], steps), take_steps(self.psi[idx], steps),
                     windows.mask[..., :T], burn)

    def draw(self, cfg: TrainConfig, generator: torch.Generator) -> Draw:
        """A seed's batch for one iteration: cfg.batch_size demos, then their windows when cfg.window is set."""
        n, b = len(self), cfg.batch_size
        idx = torch.randperm(n, generator=generator)[:b] if b <= n else torch.randint(n, (b,), generator=generator)
        return Draw(idx, self.windows(idx, cfg.window, cfg.burn_in, generator) if cfg.window else None)

    def stacked(self, draws: list[Draw], full: bool = False) -> Batch:
        """The seeds' draws stacked (K, B, T+1, .), padded to the longest (full: of all demos, whole demos)."""
        idx = torch.stack([d.idx for d in draws])
        if draws[0].windows is None:
            return self.batch(idx, full)
        return self.window_batch(idx, Windows(*(torch.stack([getattr(d.windows, f.name) for d in draws])
                                                for f in dataclasses.fields(Windows))))
