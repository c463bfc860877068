"""A cell group's seeds trained as one packed job (stm.training.loop.train_packed): cells of one training task
and variant that differ only in their seed share one process and one batched model.

Each seed keeps its own MLflow child run with what experiments.cell_run.run_cell logs (the
shared `CellRun`): params, config, its own checkpoint artifact to resume from, metrics,
evaluation, rollouts and figures, so that a report cannot tell a packed cell from one trained
alone. A seed whose loss goes non-finite is FAILED with its reason; the others go on. Each
cell of a pack is claimed in the store (experiments/runtime/claims.py) before it trains; a cell another
process holds is left out of the pack (and waited for, alone, when `wait`). A unit of one cell
is run by claims.claimed_cell, the unpacked path.
"""

from __future__ import annotations

import logging
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from experiments.cell_run import (
    CellResult,
    CellRun,
    CheckpointMismatch,
    as_cell,
    load_task,
    mark_killed,
    run_cell,
    seed_everything,
    setup_process,
    test_signal,
)
from experiments.cells import Cell
from experiments.runtime.claims import Beat, Claimed, acquire, claimed_cell, holder_id, settle_finished
from experiments.runtime.tracking import Client

log = logging.getLogger(__name__)


def pack_units(todo: Sequence[tuple[Cell, str]], pack: int, workers: int = 1) -> list[list[tuple[Cell, str]]]:
    """(cell, run id) pairs in units of at most `pack` cells (0: no limit) of one cell group: one
    training task and variant, and configs that differ only in what a pack allows per seed. Without a
    limit, the largest units are halved while there are fewer units than `workers`: a pack trains in one
    process, and a core without a unit would idle."""
    from stm.training.loop import PER_SEED

    groups: dict[str, list[tuple[Cell, str]]] = {}
    for cell, run_id in todo:
        train = {k: v for k, v in cell.train.to_dict().items() if k not in PER_SEED}
        key = repr((cell.task, cell.variant, cell.model.to_dict(), train, cell.eval_dict(), cell.data,
                    cell.dataset_seed, cell.eval_tasks))
        groups.setdefault(key, []).append((cell, run_id))
    size = pack or max([len(g) for g in groups.values()], default=1)
    units = [g[i: i + size] for g in groups.values() for i in range(0, len(g), size)]
    while not pack and len(units) < workers and any(len(u) > 1 for u in units):
        i = max(range(len(units)), key=lambda j: len(units[j]))  # the first of the largest
        half = (len(units[i]) + 1) // 2
        units[i: i + 1] = [units[i][:half], units[i][half:]]
    return units


def run_unit(cells: list[Cell], run_ids: list[str], uri: str, progress: bool, level: int,
             threads: int | None, beat: float, grace: float, wait: bool) -> list[Claimed]:
    """Entry point for worker processes: one Claimed per cell, in order; a unit of one cell is
    claims.claimed_cell (today's path), more are a packed job over the cells this process claims."""
    if len(cells) == 1:
        return [claimed_cell(cells[0], uri, run_ids[0], progress, level, threads, beat, grace, wait)]
    setup_process(level, threads)
    client, me = Client(uri, create=False), holder_id()
    got: list[Claimed | int] = [acquire(client, run_id, c.key, me, beat, grace, False)
                                for c, run_id in zip(cells, run_ids, strict=True)]
    mine = [i for i, g in enumerate(got) if isinstance(g, int)]
    beats = [Beat(client, run_ids[i], got[i], beat) for i in mine]
    try:
        if len(mine) > 1:
            results = run_pack([cells[i] for i in mine], uri, [run_ids[i] for i in mine], level, threads)
        else:  # the others are held by another process: this one alone, unpacked
            results = [run_cell(cells[i], uri, run_ids[i], progress, level, threads) for i in mine]
    finally:
        for b in beats:
            b.release()
    for i, res in zip(mine, results, strict=True):
        settle_finished(client, res.run_id, cells[i].task, res)
        got[i] = Claimed("ran", res)
    if wait:  # cells another process holds: wait for each (it trains alone if that process died)
        got = [claimed_cell(c, uri, run_id, progress, level, threads, beat, grace, True)
               if isinstance(g, Claimed) and g.kind == "held" else g
               for c, run_id, g in zip(cells, run_ids, got, strict=True)]
    return got


def run_pack(cells: list[Cell | dict[str, Any]], uri: str, run_ids: list[str], log_level: int = logging.INFO,
             threads: int | None = None) -> list[CellResult]:
    """Train the cells (one cell group's seeds) with one stm.training.loop.train_packed call, each
    in its own run as run_cell would; one CellResult per cell, in order."""
    from stm.training.loop import train_packed

    setup_process(log_level, threads)
    cells = [as_cell(c) for c in cells]
    client = Client(uri, create=False)
    start = time.perf_counter()
    runs = [CellRun(cell, client, run_id) for cell, run_id in zip(cells, run_ids, strict=True)]
    results: dict[int, CellResult] = {}
    try:
        with tempfile.TemporaryDirectory(prefix="acrmdn-pack-") as tmp:
            for k, run in enumerate(runs):
                try:
                    run.start(Path(tmp) / str(k))
                except Exception as exc:
                    results[k] = run.failed(exc, start)
            live = [k for k in range(len(runs)) if k not in results]
            marks: dict[int, int] = {}  # seed in the pack -> its last checkpoint's iteration

            def checkpointed(live: list[int], j: int, path: Path, it: int) -> None:
                runs[live[j]].on_checkpoint(path, it, signal=False)
                marks[j] = it
                if len(marks) == len(live) and min(marks.values()) >= it:  # the fault tests' hook: every seed's
                    test_signal([(runs[k].run_id, it) for k in live])  # checkpoint of this iteration is stored

            try:
                task, demos = load_task(cells[live[0]]) if live else (None, None)
                for k in list(live):  # a seed whose checkpoint is another config's fails alone, before training
                    try:
                        runs[k].check_checkpoint(task)
                    except CheckpointMismatch as exc:
                        results[k] = runs[k].failed(exc, start)
                        live.remove(k)
                seed_everything(cells[live[0]].seed if live else 0)
                log.info("pack %s: training seeds %s, %d iterations", cells[0].key.rsplit("/", 1)[0],
                         ", ".join(str(cells[k].seed) for k in live), cells[0].train.iters)
                trained = train_packed(
                    cells[0].model, [cells[k].train for k in live], task, demos,
                    checkpoint_paths=[runs[k].ckpt_path for k in live],
                    on_metrics=lambda j, it, m: runs[live[j]].buffer.add(it, m),
                    on_checkpoint=lambda j, path, it: checkpointed(live, j, path, it),
                    on_validation=lambda j, it, v: runs[live[j]].on_validation(it, v),
                    device=cells[0].device) if live else []
            except Exception as exc:  # the pack as a whole (its task, data or training): every seed fails
                for k in live:
                    results[k] = runs[k].failed(exc, start)
                trained = []
            for k, result in zip(live, trained, strict=False):
                try:
                    if result.failure is not None:
                        raise result.failure
                    results[k] = runs[k].finished(runs[k].evaluate(result), start)
                except Exception as exc:
                    results[k] = runs[k].failed(exc, start)
    except KeyboardInterrupt:  # Ctrl-C: KILLED, each seed resumable from its checkpoint (taken where it stood)
        mark_killed(client, run_ids)
        raise
    return [results[k] for k in range(len(runs))]
