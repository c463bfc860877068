"""Checkpoints: one plain dict, written atomically, read with weights_only=True.

Keys: format_version, model (state dict incl. normalisation buffers), optimizer,
model_config, train_config, layout (dicts), task, iteration, seconds,
rng (torch global + the trainer's batch generator), history, stopped_early.
Everything needed to resume bit-exactly and nothing that needs unpickling code.
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING, Any

import torch

from envs.fileio import atomic_open
from stm.config import ModelConfig, TrainConfig
from stm.model import STM, layout_from_dict, layout_to_dict

if TYPE_CHECKING:
    from envs.tasks.base import Task

FORMAT_VERSION = 1


class CheckpointError(RuntimeError):
    """A checkpoint that cannot be used: unreadable, corrupt or of another format version."""


def save_checkpoint(payload: dict[str, Any], path: Path) -> Path:
    """Write to a temporary file in the same folder, then rename over `path` (atomic on POSIX)."""
    path = Path(path)
    with atomic_open(path, "wb") as f:
        torch.save(payload, f)
    return path


def load_checkpoint(path: Path) -> dict[str, Any]:
    path = Path(path)
    if not path.is_file():
        raise CheckpointError(f"no checkpoint at {path}")
    try:
        ckpt = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as exc:  # torch raises assorted errors for truncated or foreign files
        raise CheckpointError(f"cannot read checkpoint {path}: {type(exc).__name__}: {exc}".splitlines()[0]) from None
    if not isinstance(ckpt, dict) or "format_version" not in ckpt:
        raise CheckpointError(f"{path} is not an STM checkpoint (no format_version)")
    if ckpt["format_version"] != FORMAT_VERSION:
        raise CheckpointError(f"checkpoint {path} has format version {ckpt['format_version']}, "
                              f"this code reads version {FORMAT_VERSION}")
    return ckpt


def model_from_checkpoint(ckpt: dict[str, Any]) -> STM:
    model = STM(ModelConfig.from_dict(ckpt["model_config"]), layout_from_dict(ckpt["layout"]),
                phi_mode=ckpt["train_config"].get("phi_mode", "grounded"))
    model.load_state_dict(ckpt["model"])
    return model.eval()


def load_model(path: Path, device: str | torch.device = "cpu") -> STM:
    """The trained STM stored in a checkpoint (eval mode), on `device` (stm.device; read onto the CPU first, so
    a checkpoint saved anywhere loads anywhere)."""
    from stm.device import resolve_device

    return model_from_checkpoint(load_checkpoint(path)).to(resolve_device(device))


def checkpoint_payload(model, opt, model_cfg, train_cfg, task, iteration, gen, history, seconds, stopped_early):
    """What a training checkpoint holds: enough to resume the run exactly (weights, optimiser, both RNG
    streams, history) and to check that a resume trains the same thing (configs, layout, task)."""
    return {
        "format_version": FORMAT_VERSION,
        "model": model.state_dict(),
        "optimizer": opt.state_dict(),
        "model_config": model_cfg.to_dict(),
        "train_config": train_cfg.to_dict(),
        "layout": layout_to_dict(task.layout),
        "task": task.name,
        "iteration": iteration,
        "seconds": seconds,
        "rng": {"torch": torch.get_rng_state(), "batch": gen.get_state()},
        "history": history,
        "stopped_early": stopped_early,
    }


# may change between runs: budgets and cadences, and the routes (TrainConfig.UNHASHED: an equivalent kernel)
_RESUME_FREE = {"iters", "checkpoint_every", "log_every", "val_every", "max_seconds", *TrainConfig.UNHASHED}


def check_resumable(ckpt: dict, model_cfg: ModelConfig, train_cfg: TrainConfig, task: Task, path: Path) -> None:
    """Refuse to resume from a checkpoint trained with another model, state layout or training setting."""
    if ckpt["model_config"] != model_cfg.to_dict():
        raise ValueError(f"checkpoint {path} was trained with another model config: {ckpt['model_config']}")
    if ckpt["layout"] != layout_to_dict(task.layout):
        raise ValueError(f"checkpoint {path} has state layout {ckpt['layout']}, task {task.name!r} has another")
    saved = {**TrainConfig().to_dict(), **ckpt["train_config"]}  # fields added since read as their defaults
    old = {k: v for k, v in saved.items() if k not in _RESUME_FREE}
    new = {k: v for k, v in train_cfg.to_dict().items() if k not in _RESUME_FREE}
    if old != new:
        diff = sorted(k for k in new if old.get(k) != new[k])
        raise ValueError(f"checkpoint {path} was trained with other settings ({', '.join(diff)}); "
                         "delete it or pass resume=False")
