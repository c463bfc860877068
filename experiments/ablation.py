"""The ablation runner: cells = training tasks x variants x seeds, each a child run of the
study's parent run; FINISHED cells with the same config hash are skipped, unfinished ones
resume in their own run from its checkpoint artifact, failures are recorded and summarised.

The main process creates the store, the experiment, the parent run and every child run
(serialising schema creation and run creation); cells then run in K spawned processes that
log through MlflowClient (with retries on SQLite lock contention)."""

from __future__ import annotations

import contextlib
import json
import logging
import multiprocessing as mp
import os
import sys
import time
from concurrent.futures import ProcessPoolExecutor, as_completed
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field

from experiments.cells import Cell, build_cells
from experiments.config import StudyConfig
from experiments.tracking import (
    PARENT_TAG,
    Client,
    child_runs,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_params,
    provenance_params,
    runs_page_url,
    set_tags,
    tracking_uri,
)
from experiments.worker import CellResult, mark_killed, run_cell

log = logging.getLogger(__name__)
EXPERIMENT = "ablation"
# One torch thread per cell: the models are small, so intra-op threads mostly spin; measured
# on pick-place (2 cores, loaded machine) 2 threads cost ~10x the CPU time and ~5x the wall time
# of 1 thread per iteration. Parallelism comes from the worker processes instead.
TORCH_THREADS = 1


@dataclass
class StudyOutcome:
    experiment_id: str
    parent_run_id: str
    study_name: str
    results: list[CellResult] = field(default_factory=list)
    skipped: list[str] = field(default_factory=list)
    seconds: float = 0.0

    @property
    def failures(self) -> list[CellResult]:
        return [r for r in self.results if r.status != "FINISHED"]


def default_workers() -> int:
    return len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)


def _progress(total: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="cells", unit="cell", disable=not enabled)


def prepare_runs(client: Client, experiment_id: str, parent_id: str, cells: list[Cell]
                 ) -> tuple[list[tuple[Cell, str]], list[str]]:
    """(cell, run id) to run -- an unfinished run of the same config is reused so that it
    resumes -- and the keys of cells already FINISHED."""
    by_hash: dict[str, list] = {}
    for run in child_runs(client, experiment_id, parent_id):
        by_hash.setdefault(run.data.tags.get("config_hash", ""), []).append(run)
    todo, skipped = [], []
    for cell in cells:
        runs = sorted(by_hash.get(cell.config_hash, []), key=lambda r: r.info.start_time, reverse=True)
        if any(r.info.status == "FINISHED" for r in runs):
            skipped.append(cell.key)
            continue
        tags = {PARENT_TAG: parent_id, "task": cell.task, "variant": cell.variant, "seed": cell.seed,
                "profile": cell.profile, "config_hash": cell.config_hash, "study_name": cell.study_name,
                "role": "cell", "eval_tasks": ",".join(cell.eval_tasks)}
        if runs:  # killed or failed before: resume in the same run
            run_id = runs[0].info.run_id
        else:
            run_id = client.create_run(experiment_id, run_name=cell.key.replace("/", "-"),
                                       tags={k: str(v) for k, v in tags.items()}).info.run_id
        todo.append((cell, run_id))
    return todo, skipped


def prepare_datasets(cells: list[Cell]) -> None:
    """Build (or validate) the cached demonstrations of the cells' training tasks once, in the
    main process, so that parallel workers never generate the same dataset twice."""
    from envs.datasets import load_demos
    from envs.tasks import get_task

    datasets = {(c.task, json.dumps(c.data, sort_keys=True), c.dataset_seed): c for c in cells}
    for (name, _, seed), cell in sorted(datasets.items()):
        start = time.perf_counter()
        try:
            demos = load_demos(get_task(name, **cell.data), seed=seed)
        except Exception as exc:  # the task's cells will fail with this error and be reported
            log.error("demonstrations for %s could not be built: %s: %s", name, type(exc).__name__, exc)
            continue
        log.info("demonstrations for %s: %d demos (%.1fs)", name, len(demos), time.perf_counter() - start)


def run_study(cfg: StudyConfig, progress: bool | None = None) -> StudyOutcome:
    start = time.perf_counter()
    uri = tracking_uri()
    cells = build_cells(cfg)
    study_name = cfg.resolved_study_name()
    client = Client(uri)
    experiment_id = get_or_create_experiment(client, EXPERIMENT)
    parent_id = get_or_create_parent_run(client, experiment_id, study_name,
                                         {"kind": "ablation", "profile": cfg.profile})
    log_params(client, parent_id, {"profile": cfg.profile, "study_name": study_name,
                                   "study_hash": cfg.study_hash(), **provenance_params()})
    outcome = StudyOutcome(experiment_id, parent_id, study_name)
    todo, outcome.skipped = prepare_runs(client, experiment_id, parent_id, cells)
    for key in outcome.skipped:
        log.info("skip %s: FINISHED with the same config hash", key)
    prepare_datasets([cell for cell, _ in todo])
    workers = cfg.workers or default_workers()
    workers = max(1, min(workers, len(todo))) if todo else 1
    interactive = sys.stderr.isatty() if progress is None else progress
    log.info("study %r: %d cells (%d to run, %d done) with %d worker(s); store %s", study_name, len(cells),
             len(todo), len(outcome.skipped), workers, uri)
    level = logging.getLogger().getEffectiveLevel()
    bar = _progress(len(todo), interactive)
    try:
        if workers == 1:
            for cell, run_id in todo:
                res = run_cell(cell, uri, run_id, progress=interactive, log_level=level,
                               threads=TORCH_THREADS)
                _record(outcome, res, bar, len(todo), interactive)
        else:
            _run_parallel(todo, uri, workers, outcome, bar, level, interactive)
    except KeyboardInterrupt:
        # interrupted cells are KILLED with their last checkpoint artifact: a re-run resumes them
        done = {r.run_id for r in outcome.results}
        mark_killed(client, [run_id for _, run_id in todo if run_id not in done])
        client.set_terminated(parent_id, "KILLED")
        raise
    finally:
        bar.close()
    outcome.seconds = time.perf_counter() - start
    status = "FAILED" if outcome.failures else "FINISHED"
    set_tags(client, parent_id, {"cells": len(cells), "failed_cells": len(outcome.failures),
                                 "skipped_cells": len(outcome.skipped)})
    client.log_metric(parent_id, "time/study_seconds", outcome.seconds)
    client.set_terminated(parent_id, status)
    return outcome


def _record(outcome: StudyOutcome, res: CellResult, bar, total: int, interactive: bool) -> None:
    outcome.results.append(res)
    bar.update(1)
    if not interactive:
        log.info("[%d/%d] %s %s in %.0fs%s", len(outcome.results), total, res.key, res.status, res.seconds,
                 f": {res.error}" if res.error else "")


@contextlib.contextmanager
def _stop_on_interrupt(pool: ProcessPoolExecutor):
    """On Ctrl-C, stop the workers now (the pool's own exit would run every queued cell first)."""
    try:
        yield
    except KeyboardInterrupt:
        for proc in list((pool._processes or {}).values()):  # no public API to stop running calls
            proc.terminate()
        pool.shutdown(wait=False, cancel_futures=True)
        raise


def _run_parallel(todo, uri, workers, outcome, bar, level, interactive) -> None:
    ctx = mp.get_context("spawn")  # fresh interpreters: no forked torch/pybullet/sqlite state
    pending = {}
    try:
        with ProcessPoolExecutor(max_workers=workers, mp_context=ctx) as pool, _stop_on_interrupt(pool):
            for cell, run_id in todo:
                fut = pool.submit(run_cell, cell, uri, run_id, False, level, TORCH_THREADS)
                pending[fut] = (cell, run_id)
            for fut in as_completed(pending):
                cell, run_id = pending[fut]
                try:
                    res = fut.result()
                except BrokenProcessPool:
                    raise
                except Exception as exc:  # e.g. a result that failed to pickle
                    res = CellResult(cell.key, run_id, "FAILED", error=f"{type(exc).__name__}: {exc}")
                _record(outcome, res, bar, len(todo), interactive)
    except BrokenProcessPool as exc:
        done = {r.run_id for r in outcome.results}
        client = Client(uri)
        for cell, run_id in todo:
            if run_id not in done:
                text = f"worker process died ({exc}); re-run the study to resume this cell"
                try:
                    set_tags(client, run_id, {"error": text})
                    client.set_terminated(run_id, "FAILED")
                except Exception:
                    log.exception("could not mark run %s FAILED", run_id)
                _record(outcome, CellResult(cell.key, run_id, "FAILED", error=text), bar, len(todo), interactive)


def success_table(client: Client, experiment_id: str, parent_id: str) -> str:
    """experiments.stats.success_table (the report's success table) over the FINISHED child runs, as Markdown."""
    from experiments.stats import eval_rows, success_cells
    from experiments.stats import success_table as table
    from stm.registry import VARIANTS

    evals = eval_rows(child_runs(client, experiment_id, parent_id))
    if evals.empty:
        return "(no finished cells)"
    seen = list(dict.fromkeys(evals["variant"]))
    order = [v for v in VARIANTS if v in seen] + sorted(set(seen) - set(VARIANTS))
    return table(success_cells(evals, order)).to_markdown(index=False, disable_numparse=True)


def summary_text(outcome: StudyOutcome, client: Client) -> str:
    lines = [f"study {outcome.study_name!r}: {len(outcome.results)} cell(s) run, {len(outcome.skipped)} skipped "
             f"(already FINISHED), {len(outcome.failures)} failed, {outcome.seconds:.0f}s",
             "success rate (mean over seeds; rollouts = evaluation episodes pooled over seeds):",
             success_table(client, outcome.experiment_id, outcome.parent_run_id)]
    if outcome.failures:
        lines.append("FAILED cells:")
        lines += [f"  {r.key} (run {r.run_id}): {r.error}" for r in outcome.failures]
    lines.append(f"runs: {runs_page_url(outcome.experiment_id)}  (start the UI with `nox -s ui`)")
    lines.append(f"report: `nox -s report` writes reports/out/{outcome.study_name}/index.html")
    return "\n".join(lines)
