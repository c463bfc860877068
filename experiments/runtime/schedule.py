"""Which job of an ablation runs next: the costliest ready unit first, a unit being ready once its
demonstrations exist.

Building a dataset (pick-and-place: ~150 s of IK and physics replay) and training both keep a core
busy. So the main process builds the datasets in a thread while the workers already train the units
whose datasets are built, and a free worker takes the costliest ready unit: longest processing time
first, so that no long unit starts last and runs alone at the end while the other workers idle.
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections.abc import Callable, Sequence
from concurrent.futures import FIRST_COMPLETED, Future, wait

from experiments.cells import Cell

log = logging.getLogger(__name__)

# An auto-conditioned iteration costs several teacher-forced ones (stm.speed.bench, 2 Dec: 1.8-3.1x, more with the
# validation rollouts it feeds); only the ordering uses this, so a rough factor is enough.
AC_ITERATION_WEIGHT = 4.0

Unit = list[tuple[Cell, str]]
DatasetKey = tuple[str, str, int]


def dataset_key(cell: Cell) -> DatasetKey:
    """The demonstrations a cell trains on: its training task, the task's data options and the dataset seed."""
    return cell.task, json.dumps(cell.data, sort_keys=True), cell.dataset_seed


def build_dataset(cell: Cell) -> float | None:
    """Build (or validate) the cached demonstrations of `cell`; their mean length in steps, or None when they
    could not be built (the cells of that task then fail with the error, when their worker loads them)."""
    from envs.datasets import load_demos
    from envs.tasks import get_task

    start = time.perf_counter()
    try:
        demos = load_demos(get_task(cell.task, **cell.data), seed=cell.dataset_seed)
    except Exception as exc:  # reported here once and by every cell of the task
        log.error("demonstrations for %s could not be built: %s: %s", cell.task, type(exc).__name__, exc)
        return None
    log.info("demonstrations for %s: %d demos (%.1fs)", cell.task, len(demos), time.perf_counter() - start)
    return float(demos.lengths.mean())


def datasets_of(cells: Sequence[Cell]) -> dict[DatasetKey, Cell]:
    """One cell per distinct dataset, in a stable order (task name, options, seed)."""
    return dict(sorted({dataset_key(c): c for c in cells}.items()))


def prepare_datasets(cells: Sequence[Cell]) -> dict[DatasetKey, float | None]:
    """Build every dataset of `cells` in this process, one after the other: their mean lengths."""
    return {key: build_dataset(cell) for key, cell in datasets_of(cells).items()}


def unit_cost(unit: Unit, steps: float | None) -> float:
    """A unit's relative cost, for ordering only: demonstration steps x iterations (auto-conditioned ones
    weighted), a packed seed beyond the first at half a seed's cost."""
    cell = unit[0][0]
    train = cell.train
    ac_iters = max(0, train.iters - train.tf_warmup) if train.v > 0 else 0
    iters = train.iters - ac_iters + AC_ITERATION_WEIGHT * ac_iters
    return (steps or 1.0) * iters * (1 + 0.5 * (len(unit) - 1))


def longest_first(units: Sequence[Unit], steps: dict[DatasetKey, float | None]) -> list[Unit]:
    """The units by descending cost (ties keep their order)."""
    return sorted(units, key=lambda u: -unit_cost(u, steps.get(dataset_key(u[0][0]))))


def run_scheduled(units: Sequence[Unit], workers: int, submit: Callable[[Unit], Future],
                  on_done: Callable[[Unit, Future], None]) -> None:
    """Build the units' datasets in a thread (cached and small ones first: they unblock workers soonest),
    keep `workers` units in flight, each freed slot taking the costliest unit whose dataset is built.
    submit(unit) starts a unit and returns its future; on_done(unit, future) records it."""
    cells = [cell for unit in units for cell, _ in unit]
    building = _build_in_background(_small_first(datasets_of(cells)))
    steps: dict[DatasetKey, float | None] = {}
    waiting = list(units)
    running: dict[Future, Unit] = {}
    while waiting or running:
        ready = longest_first([u for u in waiting if dataset_key(u[0][0]) in steps], steps)
        for unit in ready[: max(0, workers - len(running))]:
            waiting.remove(unit)
            running[submit(unit)] = unit
        done, _ = wait([*running, *building], return_when=FIRST_COMPLETED)
        for fut in done:
            if fut in building:
                steps[building.pop(fut)] = fut.result()
            else:
                on_done(running.pop(fut), fut)


def _build_in_background(datasets: list[tuple[DatasetKey, Cell]]) -> dict[Future, DatasetKey]:
    """One future per dataset, completed in order by a daemon thread (a Ctrl-C meanwhile does not wait for it)."""
    order = [(Future(), cell) for _, cell in datasets]  # the thread's own list: the caller pops the dict

    def build() -> None:
        for fut, cell in order:
            try:  # build_dataset reports a dataset that cannot be built and returns None
                fut.set_result(build_dataset(cell))
            except BaseException as exc:  # anything else reaches the main thread, not a silent hang
                fut.set_exception(exc)

    threading.Thread(target=build, name="datasets", daemon=True).start()
    return {fut: key for (fut, _), (key, _) in zip(order, datasets, strict=True)}


def _small_first(by_key: dict[DatasetKey, Cell]) -> list[tuple[DatasetKey, Cell]]:
    """Datasets already cached first (validated in a moment), then by size: demonstrations x their longest
    length, where the task says (n_demos, max_steps); the order only decides which workers start soonest."""
    from envs.datasets import entry_paths
    from envs.tasks import get_task

    def order(cell: Cell) -> tuple[bool, float]:
        try:
            task = get_task(cell.task, **cell.data)
        except Exception:  # an unknown task or bad options: build_dataset reports it
            return False, 0.0
        size = float(getattr(task, "n_demos", 1) * getattr(task, "max_steps", 1))
        return not entry_paths(task, cell.dataset_seed)[0].is_file(), size

    return sorted(by_key.items(), key=lambda kv: order(kv[1]))
