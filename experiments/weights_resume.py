"""A cell resumed from the latest model its run kept as weights alone (`ablation --resume-from-weights`).

A study export with models (`reports export --with-models`), imported into a fresh store, brings each cell's kept
models as artifacts weights_at/<N>/weights.pt (stm.training.weights) but no resume checkpoint: its optimiser moments
and random streams are too large for git. With StudyConfig.resume_from_weights, a cell whose run has no checkpoint
artifact but such weights at some N below train.iters resumes at the largest N: a resume checkpoint
(stm.training.checkpoint's format) is made of those weights with a fresh Adam (empty state), random streams seeded
from (training seed, N), an empty history and the training seconds the run logged at N, and the ordinary resume path
trains on from it. The rest of that run is not what the uninterrupted one would have been (the optimiser restarts,
the data order differs), so the run is tagged `resumed_from_weights`. Without the flag such a cell trains from
scratch, as before, with a warning naming the flag; a cell with a real checkpoint resumes from it whatever the flag.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

from experiments.cell_run import WEIGHTS_DIR, WEIGHTS_NAME
from experiments.cells import Cell
from experiments.runtime.tracking import Client, set_tags

log = logging.getLogger(__name__)

RESUMED_TAG = "resumed_from_weights"
STREAM_STRIDE = 1_000_003  # (seed, N) -> one generator seed, distinct for every N below the stride
# a fresh seed's history, as stm.training.loop keeps it
HISTORY_KEYS = ("train/loss", "train/grad_norm", "val/iteration", "val/metric")


def weights_iterations(client: Client, run_id: str) -> list[int]:
    """The iterations of the run's weights_at/<N>/ artifacts (an imported export's models), ascending."""
    names = [Path(f.path).name for f in client.list_artifacts(run_id, WEIGHTS_DIR) if f.is_dir]
    return sorted(int(n) for n in names if n.isdigit())


def latest_weights(client: Client, run_id: str, iters: int) -> int | None:
    """The largest N < iters the run kept weights at (a cell to resume there), or None."""
    return max((n for n in weights_iterations(client, run_id) if 0 < n < iters), default=None)


def fresh_streams(seed: int, iteration: int) -> dict[str, Any]:
    """Both random streams of a checkpoint, seeded from (training seed, iteration): the trainer's batch generator,
    and the global torch RNG state a checkpoint records (training draws nothing from it after the initialisation,
    so one seed serves both)."""
    import torch

    state = torch.Generator().manual_seed(seed * STREAM_STRIDE + iteration).get_state()
    return {"torch": state, "batch": state.clone()}


def checkpoint_from_weights(weights: dict[str, Any], lr: float, seed: int, seconds: float = 0.0) -> dict[str, Any]:
    """A resume checkpoint of a weights file (stm.training.weights): its weights, configs, layout, task and
    iteration; a default Adam at `lr` with no state yet; fresh random streams (fresh_streams); no history."""
    import torch

    from stm.training.checkpoint import model_from_checkpoint
    from stm.training.weights import KEPT

    model = model_from_checkpoint(weights)  # the weights load into the model their configs describe
    iteration = int(weights["iteration"])
    return {**{k: weights[k] for k in KEPT}, "model": weights["model"],
            "optimizer": torch.optim.Adam(model.parameters(), lr=lr).state_dict(),
            "seconds": float(seconds), "rng": fresh_streams(seed, iteration),
            "history": {k: [] for k in HISTORY_KEYS}, "stopped_early": False}


def logged_seconds(client: Client, run_id: str, iteration: int) -> float:
    """The training seconds the run logged at `iteration` (metric train/seconds), 0 if it logged none there."""
    return next((m.value for m in client.get_metric_history(run_id, "train/seconds") if m.step == iteration), 0.0)


def prepare_from_weights(client: Client, run_id: str, cell: Cell, ckpt_path: Path, work: Path) -> int | None:
    """For a cell whose run has no resume checkpoint: with cell.resume_from_weights, the checkpoint made of its latest
    kept weights below train.iters written to `ckpt_path` (where the cell resumes from), and their iteration; without
    it, a warning naming the flag where there are such weights. None where the cell trains from scratch."""
    from stm.training.checkpoint import load_checkpoint, save_checkpoint

    n = latest_weights(client, run_id, cell.train.iters)
    if n is None:
        return None
    if not cell.resume_from_weights:
        log.warning("cell %s: no resume checkpoint, models kept at %d; --resume-from-weights resumes from %d with a "
                    "fresh optimiser", cell.key, n, n)
        return None
    local = client.download_artifacts(run_id, f"{WEIGHTS_DIR}/{n}/{WEIGHTS_NAME}", str(work))
    weights = load_checkpoint(Path(local))  # unreadable: CheckpointError, the cell fails (the flag asked for them)
    payload = checkpoint_from_weights(weights, cell.train.lr, cell.train.seed, logged_seconds(client, run_id, n))
    save_checkpoint(payload, ckpt_path)
    return n


def mark_resumed(client: Client, run_id: str, cell: Cell, iteration: int) -> None:
    """The run's tag and the console's line, once the weights are known to be this cell's."""
    log.info("cell %s resumes from its kept weights at iteration %d with a fresh optimiser and random streams",
             cell.key, iteration)
    set_tags(client, run_id, {RESUMED_TAG: f"{iteration} (fresh optimiser and random streams)"})
