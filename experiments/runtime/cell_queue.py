"""`python -m experiments ablation ... --worker`: ablation cells pulled from a queue that
several worker commands share, on one host or many (see docs/scale-out.md).

The queue is an Optuna study in an RDB storage (`--queue postgresql://...`, or by default
`queue.db` next to a local mlflow.db): each unfinished cell is a WAITING trial carrying the
cell's config hash. A worker takes the next one with Optuna's own atomic pop (`study.ask`),
runs the cell in its MLflow child run (reused, so a cell resumes from its last checkpoint
artifact) and beats a heartbeat meanwhile. A cell whose worker stops beating for
`sweep.grace_period` s is marked FAIL by whichever worker looks next and re-queued
(`sweep.max_retry` times); the retry resumes the same MLflow run from its checkpoint. Every
worker enqueues the cells that are neither FINISHED nor queued; duplicates from workers that
started at the same moment are skipped when popped. A worker stops when nothing is WAITING or
RUNNING, so the last one out writes a complete summary; before it stops it checks the queue
against MLflow, and queues again any cell that neither FINISHED nor failed by its own error (an
entry whose re-queue was lost with the worker that failed it as stale). We keep no scheduler of
our own.

With `--pack K` (default: all seeds) an entry holds up to K seeds of one cell group, which the
worker that pops it trains as one packed job (experiments/pack.py): the entry is the unit, so
packing needs no coordination between workers. The first worker to queue a cell sets its
entry's size; entries that share a cell (workers started at once) are run by the earliest,
and the cell claims keep a cell from training twice whatever the entries.
"""

from __future__ import annotations

import logging
import time
from collections import Counter

from experiments.ablation import EXPERIMENT, StudyOutcome, finish_parent, prepare_runs
from experiments.cell_run import CellResult
from experiments.cells import Cell, build_cells
from experiments.pack import pack_units, run_unit
from experiments.runtime.claims import released
from experiments.runtime.optuna_storage import describe, drain, open_storage, trials_in, worker_id
from experiments.runtime.processes import training_threads, worker_pool
from experiments.runtime.schedule import prepare_datasets
from experiments.runtime.tracking import (
    Client,
    child_runs,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_params,
    provenance_params,
    set_tags,
    sqlite_path,
    tracking_uri,
)
from experiments.study_config import ConfigError, StudyConfig, from_dict

log = logging.getLogger(__name__)
QUEUE_PREFIX = "ablation-cells:"
QUEUE_DB = "queue.db"


def resolve_queue(url: str | None, uri: str | None = None) -> str:
    """The queue's Optuna RDB URL: `url`, else queue.db next to a local sqlite mlflow.db."""
    if not url:
        db = sqlite_path(uri or tracking_uri())
        if db is None:
            raise ConfigError("--queue: required when MLFLOW_TRACKING_URI is not a local sqlite store; "
                              "allowed: postgresql://..., sqlite:///...")
        return f"sqlite:///{db.parent / QUEUE_DB}"
    if not url.startswith(("postgresql://", "postgresql+", "sqlite:///")):
        raise ConfigError(f"--queue: unsupported URL {url!r}; allowed: postgresql://..., sqlite:///... "
                          "(an RDB storage: the queue needs heartbeats)")
    return url


def entry_hashes(trial) -> list[str]:
    """The config hashes of a queue entry's cells (one cell, or a cell group's seeds to pack)."""
    return list(trial.user_attrs.get("config_hashes") or [trial.user_attrs.get("config_hash")])


def enqueue_missing(study, cells: list[Cell], finished: set[str], pack: int = 1) -> int:
    """Queue every cell that is neither FINISHED in MLflow nor WAITING/RUNNING in the queue, in
    entries of up to `pack` seeds of one cell group (experiments.pack.pack_units)."""
    queued = {h for t in trials_in(study, "WAITING", "RUNNING") for h in entry_hashes(t)}
    new = [c for c in cells if c.config_hash not in finished | queued]
    for unit in pack_units([(c, "") for c in new], pack):
        hashes = [c.config_hash for c, _ in unit]
        attrs = {"config_hash": hashes[0], "cell": unit[0][0].key} if len(unit) == 1 else \
            {"config_hashes": hashes, "cell": ", ".join(c.key for c, _ in unit)}
        study.enqueue_trial({}, user_attrs=attrs, skip_if_exists=False)
    return len(new)


def finished_hashes(client: Client, experiment_id: str, parent_id: str) -> set[str]:
    return {r.data.tags.get("config_hash", "") for r in child_runs(client, experiment_id, parent_id)
            if r.info.status == "FINISHED"}


def latest_runs(client: Client, experiment_id: str, parent_id: str) -> dict[str, object]:
    """Each cell's newest run in the study, by config hash."""
    latest: dict[str, object] = {}
    for run in sorted(child_runs(client, experiment_id, parent_id), key=lambda r: r.info.start_time):
        latest[run.data.tags.get("config_hash", "")] = run
    return latest


def unsettled_hashes(client: Client, experiment_id: str, parent_id: str, hashes: list[str]) -> list[str]:
    """The cells that neither FINISHED nor failed by their own error (a FAILED run whose holder gave up
    its claim): never run, still RUNNING, KILLED, or FAILED by the queue for a holder that stopped beating.
    Asked once the queue is empty, these are cells whose entries ended without them: a stale entry's
    re-queue lost with the process that failed it, or a live holder's entry failed as stale and its
    holder killed later."""
    latest = latest_runs(client, experiment_id, parent_id)
    return [h for h in hashes if (run := latest.get(h)) is None or not (
        run.info.status == "FINISHED" or (run.info.status == "FAILED" and released(run)))]


def _refill(study, cfg: StudyConfig, cells: dict[str, Cell], client: Client, experiment_id: str,
            parent_id: str, requeued: Counter):
    """drain's refill for the cell queue: queue the unsettled cells again, each at most
    `sweep.max_retry` times by this worker (the claims keep a cell from training twice)."""
    def refill() -> int:
        lost = [h for h in unsettled_hashes(client, experiment_id, parent_id, list(cells))
                if requeued[h] < cfg.sweep.max_retry]
        if lost:
            log.warning("the queue is empty but %d cell(s) are not settled: queued again: %s", len(lost),
                        ", ".join(cells[h].key for h in lost))
            requeued.update(lost)
        return enqueue_missing(study, [cells[h] for h in lost], set(), cfg.pack)

    return refill


def _cell_objective(cfg: StudyConfig, cells: dict[str, Cell], client: Client, uri: str, experiment_id: str,
                    parent_id: str, level: int, ran: list[CellResult]):
    def objective(trial) -> float:
        import optuna

        hashes = [h for h in entry_hashes(trial) if h in cells]
        if not hashes:  # a fresh trial, asked for after another worker took the last WAITING one
            trial.set_user_attr("skipped", "nothing queued")
            raise optuna.TrialPruned("no cell queued")
        trial.set_user_attr("worker", worker_id())
        finished = finished_hashes(client, experiment_id, parent_id)
        # queued twice by workers that started together: the earlier entry runs a cell
        earlier = {h for t in trials_in(trial.study, "WAITING", "RUNNING") if t.number < trial.number
                   for h in entry_hashes(t)}
        todo = [cells[h] for h in hashes if h not in finished | earlier]
        if not todo:
            trial.set_user_attr("skipped", "already FINISHED or queued earlier")
            return 0.0
        unit = prepare_runs(client, experiment_id, parent_id, todo)[0]
        if not unit:
            trial.set_user_attr("skipped", "FINISHED by another command")
            return 0.0
        run_ids = [run_id for _, run_id in unit]
        trial.set_user_attr("mlflow_run_id" if len(unit) == 1 else "mlflow_run_ids", run_ids[0] if len(unit) == 1
                            else run_ids)
        for run_id in run_ids:
            set_tags(client, run_id, {"queue_entry": trial.number})  # its `worker` tag: the claim's holder
        log.info("worker %s: %s (queue entry %d, run(s) %s)", worker_id(), ", ".join(c.key for c, _ in unit),
                 trial.number, ", ".join(run_ids))
        # the claims wait out a dead worker's claim on a run (on another host: up to the grace period)
        got = run_unit([c for c, _ in unit], run_ids, uri, False, level, training_threads(),
                       cfg.sweep.heartbeat, cfg.sweep.grace_period, True)
        results = [g.result for g in got if g.kind != "done"]
        if not results:
            trial.set_user_attr("skipped", "FINISHED by another command")
            return 0.0
        ran.extend(results)
        errors = [f"{r.key}: {r.error}" for r in results if r.status != "FINISHED"]
        if errors:
            raise RuntimeError("; ".join(errors))  # the queue entry FAILs too; a re-run queues the cell again
        return 0.0

    return objective


def _work(cfg_dict: dict, queue_url: str, uri: str, experiment_id: str, parent_id: str, level: int
          ) -> list[CellResult]:
    """One worker process: pop and run cells until nothing is WAITING or RUNNING."""
    import optuna

    logging.basicConfig(level=level, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    cfg = from_dict(cfg_dict)
    cells = {c.config_hash: c for c in build_cells(cfg)}
    client = Client(uri, create=False)
    study = optuna.load_study(study_name=QUEUE_PREFIX + cfg.resolved_study_name(),
                              storage=open_storage(queue_url, cfg.sweep, uri),
                              sampler=optuna.samplers.RandomSampler())
    ran: list[CellResult] = []
    objective = _cell_objective(cfg, cells, client, uri, experiment_id, parent_id, level, ran)
    # dead workers' cells go back to WAITING and are taken like the others
    drain(study, lambda: study.optimize(objective, n_trials=1, catch=(Exception,)), cfg.sweep.heartbeat, "cell",
          _refill(study, cfg, cells, client, experiment_id, parent_id, Counter()))
    return ran


def run_worker(cfg: StudyConfig, queue_url: str | None = None) -> StudyOutcome:
    """Join the study's queue (creating it, the experiment and the parent run if this is the
    first worker), work it with `cfg.workers` local processes, and summarise the whole study."""
    import optuna

    start = time.perf_counter()
    optuna.logging.set_verbosity(optuna.logging.WARNING)
    uri = tracking_uri()
    queue_url = resolve_queue(queue_url, uri)
    cells = build_cells(cfg)
    study_name = cfg.resolved_study_name()
    client = Client(uri)
    experiment_id = get_or_create_experiment(client, EXPERIMENT)
    parent_id = get_or_create_parent_run(client, experiment_id, study_name,
                                         {"kind": "ablation", "profile": cfg.profile, "queue": describe(queue_url)})
    log_params(client, parent_id, {"profile": cfg.profile, "study_name": study_name,
                                   "study_hash": cfg.study_hash(), **provenance_params()})
    storage = open_storage(queue_url, cfg.sweep, uri)  # an RDB storage (resolve_queue): heartbeats on
    study = optuna.create_study(study_name=QUEUE_PREFIX + study_name, storage=storage, load_if_exists=True)
    added = enqueue_missing(study, cells, finished_hashes(client, experiment_id, parent_id), cfg.pack)
    log.info("study %r: %d cells, %d newly queued; queue %s", study_name, len(cells), added, describe(queue_url))
    prepare_datasets(cells)  # cached per host: built once, not in every process
    level = logging.getLogger().getEffectiveLevel()
    args = (cfg.to_dict(), queue_url, uri, experiment_id, parent_id, level)
    workers = max(1, cfg.workers or 1)
    outcome = StudyOutcome(experiment_id, parent_id, study_name)
    try:
        if workers == 1:
            ran = _work(*args)
        else:
            with worker_pool(workers) as pool:
                ran = [r for f in [pool.submit(_work, *args) for _ in range(workers)] for r in f.result()]
    except KeyboardInterrupt:
        # this worker's cells stop beating: another worker (or a re-run after the grace period) retries them
        client.set_terminated(parent_id, "KILLED")
        raise
    # the study as a whole (all workers): the latest run of each cell
    latest = latest_runs(client, experiment_id, parent_id)
    mine = {r.run_id for r in ran}
    for cell in cells:
        run = latest.get(cell.config_hash)
        if run is None:
            outcome.results.append(CellResult(cell.key, "", "FAILED", error="never run (queue entry lost?)"))
        elif run.info.run_id in mine:
            outcome.results.append([r for r in ran if r.run_id == run.info.run_id][-1])
        elif run.info.status == "FINISHED":
            outcome.skipped.append(cell.key)
        else:
            outcome.results.append(CellResult(cell.key, run.info.run_id, "FAILED",
                                              error=run.data.tags.get("error", run.info.status)))
    outcome.seconds = time.perf_counter() - start
    finish_parent(client, outcome, len(cells), "ablation (queue)")
    return outcome
