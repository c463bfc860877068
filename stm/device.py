"""Where a model trains: `--device auto|cpu|cuda|cuda:N`, resolved once, with a one-line error for a bad value.

"auto" is CUDA where torch sees a GPU, else the CPU. Training puts everything of its iteration on that device
(the pack, its optimiser, the batches, the tip kinematics' constants); the random streams stay CPU generators
(stm.mdn draws on the generator's device and moves the draws), so a seed draws the same data order, noise and
samples on any device. Checkpoints and trained models come back on the CPU (they load anywhere); rollouts run
on their model's device (stm.rollout), the physics on the CPU.
"""

from __future__ import annotations

import re

import torch

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"
_PATTERN = re.compile(r"auto|cpu|cuda(:\d+)?")


class DeviceError(ValueError):
    """A device string that does not name a device of this machine."""


def check_device_name(spec: str) -> str:
    """The spec if it is well formed (availability is checked by resolve_device, where the work runs)."""
    if not isinstance(spec, str) or not _PATTERN.fullmatch(spec):
        raise DeviceError(f"unknown device {spec!r}; allowed: {DEVICE_CHOICES}")
    return spec


def resolve_device(spec: str | torch.device = "cpu") -> torch.device:
    """auto -> cuda if torch.cuda.is_available() else cpu; cpu; cuda[:N] if this machine has that GPU. A GPU
    comes back with its index (cuda: the current one), so that tensors' devices compare equal to it."""
    if isinstance(spec, torch.device):
        spec = str(spec)
    check_device_name(spec)
    if spec == "auto":
        spec = "cuda" if torch.cuda.is_available() else "cpu"
    device = torch.device(spec)
    if device.type == "cuda":
        if not torch.cuda.is_available():
            raise DeviceError(f"device {spec!r}: torch sees no CUDA GPU here (torch {torch.__version__}); "
                              "use --device cpu or auto")
        count = torch.cuda.device_count()
        if device.index is not None and device.index >= count:
            raise DeviceError(f"device {spec!r}: this machine has {count} CUDA GPU(s), cuda:0..cuda:{count - 1}")
        if device.index is None:  # (asking the current device would start CUDA in a process that only checks)
            device = torch.device("cuda", torch.cuda.current_device() if torch.cuda.is_initialized() else 0)
    return device
