"""A trained model's weights alone: the file a study export carries for each of its models
(reports.data.export, `--with-models`), a few MB where a checkpoint holds several times that.

It is a checkpoint (stm.training.checkpoint) less what only resuming needs (optimiser, RNG states, history,
seconds): format_version, model (the state dict, floating tensors as float32), model_config, train_config, layout,
task, iteration, and weights_only = True. So checkpoint.load_model rebuilds the STM from it exactly as from the
checkpoint it came from, and it too is read with torch.load(weights_only=True) (no code unpickled).

weights_bytes is deterministic: torch.save into memory stamps no date and no file name, and each tensor is saved
as its own compact storage (a slice of a packed model would otherwise drag the whole pack along), so the same
weights give the same bytes and a committed copy diffs cleanly.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any

import torch

from stm.training.checkpoint import load_checkpoint

WEIGHTS_ONLY = "weights_only"
KEPT = ("format_version", "model_config", "train_config", "layout", "task", "iteration")  # besides the weights


def _compact(t: torch.Tensor) -> torch.Tensor:
    t = t.detach().to("cpu", torch.float32 if t.is_floating_point() else t.dtype)
    return t.clone(memory_format=torch.contiguous_format)


def weights_of(ckpt: dict[str, Any]) -> dict[str, Any]:
    """The weights-only payload of a checkpoint (or of a weights file: the same payload again)."""
    out = {k: ckpt[k] for k in KEPT}
    out["model"] = {k: _compact(v) for k, v in ckpt["model"].items()}
    out[WEIGHTS_ONLY] = True
    return out


def weights_bytes(ckpt: dict[str, Any]) -> bytes:
    """The weights file of a checkpoint (or of a weights file), as bytes."""
    buf = io.BytesIO()
    torch.save(weights_of(ckpt), buf)
    return buf.getvalue()


def weights_file_bytes(path: Path) -> tuple[bytes, int]:
    """The weights file of the checkpoint or weights file at `path`, and its iteration (CheckpointError when
    unreadable)."""
    ckpt = load_checkpoint(path)
    return weights_bytes(ckpt), int(ckpt["iteration"])
