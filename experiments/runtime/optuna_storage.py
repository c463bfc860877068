"""The Optuna storage of sweeps and of the ablation cell queue: opening it, heartbeats, dead
workers, and the one drain loop both use (run what dead workers left, wait for the others).

Default sweep storage: a JournalFileBackend file `optuna.journal` next to mlflow.db (safe for
several processes on one host; no heartbeats). An RDB storage (postgresql://, sqlite:///)
beats a heartbeat every `sweep.heartbeat` s per trial; a trial without a beat for
`sweep.grace_period` s is marked FAIL by whichever worker looks next, its MLflow run FAILED,
and it is re-queued with the same parameters (`sweep.max_retry` times).
"""

from __future__ import annotations

import logging
import os
import socket
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import tenacity
from mlflow.entities import Metric

from experiments.runtime.backend_internals import is_schema_race, told_after_failed_as_stale
from experiments.runtime.claims import is_live
from experiments.runtime.store_check import redact
from experiments.runtime.tracking import Client, schema_lock, set_tags, sqlite_path, store_dir
from experiments.study_config import SweepConfig

log = logging.getLogger(__name__)
JOURNAL_NAME = "optuna.journal"
JOURNAL_PREFIX = "journal:"


def storage_spec(storage: str | None, uri: str) -> str:
    """The storage a sweep uses: `storage` (an RDB URL), else the journal file beside the store."""
    return storage or f"{JOURNAL_PREFIX}{store_dir(uri) / JOURNAL_NAME}"


def has_heartbeat(spec: str) -> bool:
    """RDB storages beat heartbeats (open_storage turns them on); the journal file does not."""
    return not spec.startswith(JOURNAL_PREFIX)


def open_storage(spec: str, sweep: SweepConfig | None = None, uri: str | None = None):
    """The Optuna storage; an RDB one beats heartbeats and retries dead workers' trials when
    `sweep` is given (their MLflow runs, in store `uri`, are marked FAILED)."""
    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if not has_heartbeat(spec):
        path = Path(spec.removeprefix(JOURNAL_PREFIX))
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    kwargs = {}
    if sweep is not None:
        kwargs = {"heartbeat_interval": sweep.heartbeat, "grace_period": sweep.grace_period,
                  "heartbeat_stale_trial_callback": RetryDeadTrial(sweep.max_retry, uri, sweep.grace_period)}
    db = sqlite_path(spec)
    with warnings.catch_warnings():  # heartbeats are marked experimental in Optuna
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        if db is None:  # a server database: processes creating its schema at once race (a unique-key error
            # in the loser's CREATE); the schema then exists, so the loser's retry just opens it
            return tenacity.retry(retry=tenacity.retry_if_exception(is_schema_race), reraise=True,
                                  stop=tenacity.stop_after_attempt(5),
                                  wait=tenacity.wait_random_exponential(multiplier=0.2, max=3))(
                optuna.storages.RDBStorage)(spec, **kwargs)
        with schema_lock(db):  # processes creating a fresh SQLite schema at once would race
            return optuna.storages.RDBStorage(spec, **kwargs)


def fail_dead_trials(study) -> None:
    """Optuna's heartbeat check (marked experimental): FAIL, and re-queue, the trials of dead workers."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)


def worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


def trials_in(study, *states: str) -> list:
    """The study's trials in these states (names of optuna.trial.TrialState)."""
    from optuna.trial import TrialState

    return study.get_trials(deepcopy=False, states=tuple(TrialState[s] for s in states))


def retry_callback(max_retry: int):
    """Optuna's callback that re-queues a failed trial with the same parameters (marked experimental)."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback(max_retry=max_retry)


def retried_trial_number(frozen) -> int | None:
    """The trial that a re-queued trial retries, None for a first attempt (recorded by the retry callback)."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback.retried_trial_number(frozen)


def retry_history(frozen) -> list[int]:
    """The trials that a re-queued trial retries, the first attempt first."""
    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RetryHeartbeatStaleTrialCallback.retry_history(frozen)


class RetryDeadTrial:
    """Called by Optuna for a trial whose worker stopped beating: mark its MLflow runs FAILED with
    the reason, then re-queue it with the same parameters (RetryHeartbeatStaleTrialCallback).

    A run is left alone when it is FINISHED or another live process holds its claim
    (experiments/runtime/claims.py): the trial's worker may only have been waiting for that process, or
    beaten late while it trained; the holder settles the run itself."""

    def __init__(self, max_retry: int, uri: str | None, grace: float):
        self.retry = retry_callback(max_retry)
        self.uri = uri
        self.grace = grace

    def __call__(self, study, frozen) -> None:
        log.warning("trial %d: its worker %s stopped beating; marked FAIL and re-queued", frozen.number,
                    frozen.user_attrs.get("worker", "?"))
        # the runs first: a worker that pops the re-queued trial must not find its fresh claim overruled
        # a queue entry of a packed cell group holds several runs (experiments/runtime/cell_queue.py)
        for run_id in frozen.user_attrs.get("mlflow_run_ids") or [frozen.user_attrs.get("mlflow_run_id")]:
            try:
                self._fail_run(run_id, frozen)
            except Exception:  # e.g. the tracking server unreachable a moment: the re-queue below matters more
                log.exception("trial %d: could not mark run %s FAILED", frozen.number, run_id)
        self.retry(study, frozen)

    def _fail_run(self, run_id: str | None, frozen) -> None:
        if not (run_id and self.uri):
            return
        client = Client(self.uri)
        run = client.get_run(run_id)
        if run.info.status == "FINISHED" or is_live(run, self.grace):
            log.info("run %s of trial %d: %s; left as it is", run_id, frozen.number,
                     "FINISHED" if run.info.status == "FINISHED" else "held by a live process")
            return
        # what the dead worker reported to Optuna may not have reached MLflow (metrics are batched)
        now = int(time.time() * 1000)
        client.log_batch(run_id, metrics=[Metric("val/metric", float(v), now, int(step))
                                          for step, v in sorted(frozen.intermediate_values.items())])
        set_tags(client, run_id, {"trial_state": "FAIL", "error": f"worker {frozen.user_attrs.get('worker', '?')} "
                                  "died (no heartbeat); the trial was re-queued with the same parameters"})
        client.set_terminated(run_id, "FAILED")


def drain(study, run_one: Callable[[], None], poll: float, what: str = "trial",
          refill: Callable[[], int] | None = None) -> None:
    """The loop every worker ends with (RDB storages): fail the trials of dead workers (they are
    re-queued as WAITING), run WAITING ones one at a time with `run_one`, and return once no
    trial is WAITING or RUNNING and `refill` (the queue's own check against what it should hold)
    queues nothing more, so that the last worker out sees the whole study."""
    announced = False
    while True:
        fail_dead_trials(study)
        if trials_in(study, "WAITING"):
            try:
                run_one()
            except (ValueError, AssertionError) as exc:
                if not told_after_failed_as_stale(exc):
                    raise
                log.warning("a %s of this worker was failed as stale by another while it ran (a late "
                            "heartbeat) and re-queued; its results stand", what)
            continue
        running = trials_in(study, "RUNNING")
        if not running:
            if refill is not None and refill():
                continue
            return
        if not announced:
            log.info("waiting for %d %s(s) held by other workers: %s", len(running), what,
                     ", ".join(f"{t.user_attrs.get('cell', t.number)} ({t.user_attrs.get('worker', '?')})"
                               for t in running))
            announced = True
        time.sleep(poll)


def describe(spec: str) -> str:
    """The storage for logs and tags: passwords hidden."""
    return redact(spec)
