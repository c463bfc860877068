"""The ablation runner: cells = training tasks x variants x seeds, each a child run of the
study's parent run; FINISHED cells with the same config hash are skipped, unfinished ones
resume in their own run from its checkpoint artifact, failures are recorded and summarised.
The seeds of a cell group (task x variant) train together as one packed job, up to `pack` of
them (experiments/pack.py; `--pack 1`: each cell alone).

The main process creates the store, the experiment, the parent run and every child run; cells
then run in K spawned processes (experiments/runtime/processes.py: they stop with the main process) that
log through MlflowClient (with retries on SQLite lock contention). Each cell is claimed in the
store before it trains (experiments/runtime/claims.py): a second command of the same study started
meanwhile waits for the cells the first one trains instead of training them again, and both
report the same table."""

from __future__ import annotations

import logging
import shlex
import sys
import time
from concurrent.futures.process import BrokenProcessPool
from dataclasses import dataclass, field
from pathlib import Path

from experiments.cell_run import CellResult, mark_killed
from experiments.cells import Cell, build_cells
from experiments.pack import pack_units, run_unit
from experiments.runtime.claims import Claimed, claimed_cell, is_live
from experiments.runtime.processes import default_workers, training_threads, worker_pool
from experiments.runtime.schedule import prepare_datasets, run_scheduled
from experiments.runtime.spread import IdleSlots, lent
from experiments.runtime.store_faults import StoreFault, fault_reason
from experiments.runtime.tracking import (
    ABLATION,
    NOTE_TAG,
    PARENT_TAG,
    Client,
    child_runs,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_params,
    provenance_params,
    report_index,
    runs_page_url,
    set_tags,
    settle_window,
    tracking_uri,
    wait_for_earlier_runs,
)
from experiments.study_config import StudyConfig

log = logging.getLogger(__name__)
EXPERIMENT = ABLATION


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


def _progress(total: int, enabled: bool):
    from tqdm.auto import tqdm

    return tqdm(total=total, desc="cells", unit="cell", disable=not enabled)


def prepare_runs(client: Client, experiment_id: str, parent_id: str, cells: list[Cell]
                 ) -> tuple[list[tuple[Cell, str]], list[str]]:
    """(cell, run id) to run -- a cell's unfinished run is reused so that it resumes -- and the
    keys of cells already FINISHED. Commands of one study preparing at once may each create a
    run for a cell: after the settle window (tracking.settle_window) all see the same earliest
    and settle on it, so that the cell's claim (experiments/runtime/claims.py) is taken on one run; each
    deletes only the duplicates it created itself."""
    window, attempts = settle_window(client.uri), 3
    todo, skipped, pending = [], [], list(cells)
    for attempt in range(attempts):
        settled, done, pending = _settle_cells(client, experiment_id, parent_id, pending, window,
                                               last=attempt == attempts - 1)
        todo += settled
        skipped += done
        if not pending:
            break
    return todo, skipped


def _settle_cells(client: Client, experiment_id: str, parent_id: str, cells: list[Cell], window: float,
                  last: bool) -> tuple[list[tuple[Cell, str]], list[str], list[Cell]]:
    """One round of prepare_runs: (cell, run id) settled, the keys of cells FINISHED, and the cells
    to settle again (their run was withdrawn: creating it took longer than the window)."""
    existing = _runs_by_hash(client, experiment_id, parent_id)
    done = [c.key for c in cells if any(r.info.status == "FINISHED" for r in existing.get(c.config_hash, []))]
    cells = [c for c in cells if c.key not in done]
    created, slow = {}, set()
    for cell in (c for c in cells if c.config_hash not in existing):
        began = time.time()
        created[cell.config_hash] = _create_cell_run(client, experiment_id, parent_id, cell)
        if not last and time.time() - began > window:
            slow.add(cell.config_hash)  # others may have settled on a later run meanwhile
    if created:
        wait_for_earlier_runs(max(r.info.start_time for r in created.values()), window)
    settled = _runs_by_hash(client, experiment_id, parent_id)
    out, again = [], []
    for cell in cells:
        runs, own = settled.get(cell.config_hash), created.get(cell.config_hash)
        first = min(runs, key=lambda r: (r.info.start_time, r.info.run_id)) if runs else None
        if own is not None and first is not None and first.info.run_id != own.info.run_id:
            _withdraw_cell_run(client, own.info.run_id)
        elif own is not None and cell.config_hash in slow and _withdraw_cell_run(client, own.info.run_id):
            first = None
        if first is None:
            again.append(cell)
        else:
            out.append((cell, first.info.run_id))
    return out, done, again


def _runs_by_hash(client: Client, experiment_id: str, parent_id: str) -> dict[str, list]:
    by_hash: dict[str, list] = {}
    for run in child_runs(client, experiment_id, parent_id):
        by_hash.setdefault(run.data.tags.get("config_hash", ""), []).append(run)
    return by_hash


def _create_cell_run(client: Client, experiment_id: str, parent_id: str, cell: Cell):
    tags = {PARENT_TAG: parent_id, "task": cell.task, "variant": cell.variant, "seed": cell.seed,
            "profile": cell.profile, "config_hash": cell.config_hash, "study_name": cell.study_name,
            "role": "cell", "eval_tasks": ",".join(cell.eval_tasks), "split": cell.eval.split}
    return client.create_run(experiment_id, run_name=cell.key, tags={k: str(v) for k, v in tags.items()})


def _withdraw_cell_run(client: Client, run_id: str) -> bool:
    """Delete a cell run this command created, unless a claim was already taken on it."""
    if client.get_run(run_id).data.params:
        return False
    client.delete_run(run_id)
    return True


def run_study(cfg: StudyConfig, progress: bool | None = None) -> StudyOutcome:
    """Run the study's cells not FINISHED yet. Ctrl-C: the cells and the parent run KILLED (resumable), then
    KeyboardInterrupt. A store fault (experiments/runtime/store_faults.py): StoreFault carrying what finished,
    nothing more written."""
    start = time.perf_counter()
    uri = tracking_uri()
    cells = build_cells(cfg)
    study_name = cfg.resolved_study_name()
    client = Client(uri)
    experiment_id = get_or_create_experiment(client, EXPERIMENT)
    parent_id = get_or_create_parent_run(client, experiment_id, study_name,
                                         {"kind": "ablation", "profile": cfg.profile})
    outcome = StudyOutcome(experiment_id, parent_id, study_name)
    todo: list[tuple[Cell, str]] = []
    prepared = False
    try:
        log_params(client, parent_id, {"profile": cfg.profile, "study_name": study_name,
                                       "study_hash": cfg.study_hash(), **provenance_params()})
        todo, outcome.skipped = prepare_runs(client, experiment_id, parent_id, cells)
        prepared = True
        _run_cells(cfg, uri, client, outcome, todo, progress)
        client.check_store()  # a store file deleted meanwhile would take the parent's last writes with it
        outcome.seconds = time.perf_counter() - start
        finish_parent(client, outcome, len(cells), "ablation")
    except KeyboardInterrupt:
        # interrupted cells are KILLED with their last checkpoint artifact (a re-run resumes them), and so are the
        # runs prepared for cells that had not started: Ctrl-C while the runs were being created included
        _mark_interrupted(client, outcome, experiment_id, cfg.sweep.grace_period)
        raise
    except Exception as exc:
        reason = fault_reason(exc)
        if reason is None:
            raise
        outcome.seconds = time.perf_counter() - start
        done = {r.run_id for r in outcome.results if r.status == "FINISHED"}
        unfinished = [cell.key for cell, run_id in todo if run_id not in done] if prepared else \
            [c.key for c in cells]
        raise StoreFault(reason, outcome, unfinished) from exc
    return outcome


def _run_cells(cfg: StudyConfig, uri: str, client: Client, outcome: StudyOutcome, todo: list[tuple[Cell, str]],
               progress: bool | None) -> None:
    budget = cfg.workers or default_workers()  # busy processes at most: workers, and the idle ones' evaluation helpers
    units = pack_units(todo, cfg.pack, budget)
    workers = max(1, min(budget, len(units))) if units else 1
    interactive = sys.stderr.isatty() if progress is None else progress
    log.info("study %r: %d cells (%d to run in %d job(s), %d done) with %d worker(s); store %s", outcome.study_name,
             len(todo) + len(outcome.skipped), len(todo), len(units), len(outcome.skipped), workers, uri)
    for key in outcome.skipped:
        log.info("skip %s: FINISHED with the same config hash", key)
    level = logging.getLogger().getEffectiveLevel()
    claim = (cfg.sweep.heartbeat, cfg.sweep.grace_period)
    bar = _progress(len(todo), interactive)
    held: list[tuple[Cell, str]] = []
    try:
        if workers == 1:
            prepare_datasets([cell for cell, _ in todo])  # once, here, before any worker needs them
            with lent(IdleSlots(budget - 1) if budget > 1 else None):  # this process runs the unit: the rest idle
                for unit in units:
                    got = run_unit(*_unit_args(unit), uri, interactive, level, training_threads(), *claim, False)
                    _record_unit(outcome, unit, got, bar, len(todo), interactive, held)
                    client.check_store()
        else:
            _run_parallel(units, uri, workers, outcome, bar, level, interactive, claim, held, client, budget)
        for cell, run_id in held:  # cells another command of this study trains: wait for them
            got = claimed_cell(cell, uri, run_id, interactive, level, training_threads(), *claim, True)
            _record(outcome, cell, run_id, got, bar, len(todo), interactive, held)
    finally:
        bar.close()


def _mark_interrupted(client: Client, outcome: StudyOutcome, experiment_id: str, grace: float) -> None:
    """After Ctrl-C: the parent run KILLED, then the study's RUNNING cell runs (not one another command of this
    study is training: it holds a live claim on it); best effort on the way out."""
    try:
        client.set_terminated(outcome.parent_run_id, "KILLED")
        done = {r.run_id for r in outcome.results}
        runs = [r for r in child_runs(client, experiment_id, outcome.parent_run_id)
                if r.info.status == "RUNNING" and r.info.run_id not in done and not is_live(r, grace)]
        mark_killed(client, [r.info.run_id for r in runs])
    except Exception as exc:  # noqa: BLE001 - a store that fails now too: the runs stay RUNNING, resumable alike
        log.warning("could not mark the study's runs KILLED: %s", str(exc).splitlines()[0][:300])


def finish_parent(client: Client, outcome: StudyOutcome, n_cells: int, kind: str) -> None:
    """Close the parent run: counts, duration, a Markdown description (the MLflow UI shows it
    on the run's page) and its status."""
    set_tags(client, outcome.parent_run_id, {"cells": n_cells, "failed_cells": len(outcome.failures),
                                             "skipped_cells": len(outcome.skipped)})
    client.log_metric(outcome.parent_run_id, "time/study_seconds", outcome.seconds)
    client.set_tag(outcome.parent_run_id, NOTE_TAG, study_note(outcome, client, kind)[:60000])
    client.set_terminated(outcome.parent_run_id, "FAILED" if outcome.failures else "FINISHED")


def _record(outcome: StudyOutcome, cell: Cell, run_id: str, got: Claimed, bar, total: int, interactive: bool,
            held: list) -> None:
    if got.kind == "ran" and got.result.store_fault:  # the study stops: run_study reports what finished
        raise StoreFault(got.result.store_fault)
    if got.kind == "held":
        held.append((cell, run_id))
        log.info("%s: another command of this study is training it; waiting for it at the end", cell.key)
        return
    bar.update(1)
    if got.kind == "done":
        outcome.skipped.append(cell.key)
        log.info("[%d/%d] %s FINISHED by another command of this study", len(outcome.results) +
                 len(outcome.skipped), total, cell.key)
        return
    res = got.result
    outcome.results.append(res)
    if not interactive:
        log.info("[%d/%d] %s %s in %.0fs%s", len(outcome.results), total, res.key, res.status, res.seconds,
                 f": {res.error}" if res.error else "")


def _unit_args(unit: list[tuple[Cell, str]]) -> tuple[list[Cell], list[str]]:
    return [cell for cell, _ in unit], [run_id for _, run_id in unit]


def _record_unit(outcome: StudyOutcome, unit: list[tuple[Cell, str]], got: list[Claimed], bar, total: int,
                 interactive: bool, held: list) -> None:
    for (cell, run_id), g in zip(unit, got, strict=True):
        _record(outcome, cell, run_id, g, bar, total, interactive, held)


def _run_parallel(units, uri, workers, outcome, bar, level, interactive, claim, held, client, budget) -> None:
    """Each unit (a cell, or a cell group's seeds packed: experiments/pack.py) in a worker process; `budget` busy
    processes at most (experiments/runtime/spread.py)."""
    total = sum(len(u) for u in units)

    def record(unit, fut) -> None:
        try:
            got = fut.result()
        except BrokenProcessPool:
            raise
        except Exception as exc:  # e.g. a result that failed to pickle; a store fault stops the study
            if fault_reason(exc) is not None:
                raise
            got = [Claimed("ran", CellResult(cell.key, run_id, "FAILED", error=f"{type(exc).__name__}: {exc}"))
                   for cell, run_id in unit]
        _record_unit(outcome, unit, got, bar, total, interactive, held)
        client.check_store()

    try:
        with worker_pool(workers, budget) as pool:
            # datasets built here meanwhile, so that no two workers build the same one (experiments.runtime.schedule)
            run_scheduled(units, workers, lambda unit: pool.submit(run_unit, *_unit_args(unit), uri, False, level,
                                                                   training_threads(), *claim, False), record)
    except BrokenProcessPool as exc:
        done = {r.run_id for r in outcome.results} | {run_id for _, run_id in held}
        pending = [pair for unit in units for pair in unit if pair[1] not in done]
        if any(client.get_run(run_id).info.status == "KILLED" for _, run_id in pending):
            # a worker was interrupted and recorded it (SIGINT reached the workers, not this process): the study
            # was stopped, not broken; the caller marks the rest KILLED as for a Ctrl-C here
            raise KeyboardInterrupt from exc
        for cell, run_id in pending:
            text = f"worker process died ({exc}); re-run the study to resume this cell"
            try:
                set_tags(client, run_id, {"error": text})
                client.set_terminated(run_id, "FAILED")
            except Exception:
                log.exception("could not mark run %s FAILED", run_id)
            _record(outcome, cell, run_id, Claimed("ran", CellResult(cell.key, run_id, "FAILED", error=text)),
                    bar, total, interactive, held)


def success_markdown(client: Client, experiment_id: str, parent_id: str) -> str:
    """experiments.stats.success_table (the report's success table) over the FINISHED child runs, as Markdown."""
    from experiments.stats import eval_rows, success_rows, success_table
    from stm.variants import VARIANTS

    evals = eval_rows(child_runs(client, experiment_id, parent_id))
    if evals.empty:
        return "(no finished cells)"
    seen = list(dict.fromkeys(evals["variant"]))
    order = [v for v in VARIANTS if v in seen] + sorted(set(seen) - set(VARIANTS))
    return success_table(success_rows(evals, order)).to_markdown(index=False, disable_numparse=True)


def command_line() -> str:
    """The command that ran this study, as the user would type it (no path of this machine)."""
    if Path(sys.argv[0]).parent.name == "experiments" or sys.argv[0] == "-m":
        return shlex.join(["python", "-m", "experiments", *sys.argv[1:]])
    return ""


def study_note(outcome: StudyOutcome, client: Client, kind: str) -> str:
    """The parent run's description (Markdown): headline table, command, report."""
    lines = [f"**{kind} study `{outcome.study_name}`**: {len(outcome.results)} cell(s) run, "
             f"{len(outcome.skipped)} skipped (already FINISHED), {len(outcome.failures)} failed, "
             f"{outcome.seconds:.0f} s.", "",
             "Success rate (mean over seeds; rollouts = evaluation episodes pooled over seeds):", "",
             success_markdown(client, outcome.experiment_id, outcome.parent_run_id), ""]
    if command_line():
        lines += ["Command:", "", f"    {command_line()}", ""]
    name = outcome.study_name
    lines.append(f"Report: `python -m reports --study {name}` writes `{report_index(name)}`.")
    return "\n".join(lines)


def fault_summary(outcome: StudyOutcome, unfinished: list[str]) -> str:
    """The summary of a study a store fault stopped, from what this command saw (the store is not read again)."""
    finished = [r.key for r in outcome.results if r.status == "FINISHED"]
    failed = [r for r in outcome.failures if not r.store_fault]
    lines = [f"study {outcome.study_name!r} stopped by a store fault after {outcome.seconds:.0f}s: "
             f"{len(finished)} cell(s) FINISHED now, {len(outcome.skipped)} skipped (already FINISHED), "
             f"{len(failed)} failed, {len(unfinished)} left unfinished (resumable: re-run the same command)"]
    lines += [f"  FINISHED: {key}" for key in finished]
    lines += [f"  FAILED: {r.key} (run {r.run_id}): {r.error}" for r in failed]
    shown = unfinished[:20]
    lines += [f"  unfinished: {key}" for key in shown]
    if len(unfinished) > len(shown):
        lines.append(f"  ... and {len(unfinished) - len(shown)} more unfinished")
    return "\n".join(lines)


def summary_text(outcome: StudyOutcome, client: Client) -> str:
    lines = [f"study {outcome.study_name!r}: {len(outcome.results)} cell(s) run, {len(outcome.skipped)} skipped "
             f"(already FINISHED), {len(outcome.failures)} failed, {outcome.seconds:.0f}s",
             "success rate (mean over seeds; rollouts = evaluation episodes pooled over seeds):",
             success_markdown(client, outcome.experiment_id, outcome.parent_run_id)]
    if outcome.failures:
        lines.append("FAILED cells:")
        lines += [f"  {r.key} (run {r.run_id}): {r.error}" for r in outcome.failures]
    lines.append(f"runs: {runs_page_url(outcome.experiment_id)}  (start the UI with `nox -s ui`)")
    lines.append(f"report: `nox -s report` writes {report_index(outcome.study_name)}")
    return "\n".join(lines)
