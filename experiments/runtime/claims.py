"""A claim on a cell's MLflow run, so that two commands of the same study (started at once,
or a re-run while the first is still going) never train one cell twice.

The claim is the run's param `claim.<n>` = holder id. MLflow params are immutable and keyed by
(run, key), so of two processes logging `claim.<n+1>` at once exactly one succeeds, on SQLite,
PostgreSQL and through a tracking server alike. A claimant first writes the tag `claim.beat` =
"<n>:<unix time>", then the param, then the tag `worker` = its host:pid; the holder beats the
tag every `beat` seconds while it trains and writes "<n>:done" when it stops. A claim is live
while the beat is fresh (younger than `grace`) and, on this host, its holder's process exists
(so a re-run after a kill -9 takes over at once); a newer claim may be taken only when none is
live. A loser either returns at once (`wait=False`) or waits for the holder: the cell FINISHED
by it is reported as done by another process, FAILED by it (released) as failed, and a holder
that died is taken over (the cell resumes from its checkpoint).
"""

from __future__ import annotations

import logging
import os
import socket
import threading
import time
import uuid
from dataclasses import dataclass
from typing import Any

from experiments.cells import Cell
from experiments.runtime.backend_internals import lost_param_race
from experiments.runtime.tracking import Client, log_metrics, set_tags

log = logging.getLogger(__name__)
CLAIM = "claim."
BEAT_TAG = "claim.beat"


@dataclass
class Claimed:
    """How a cell went for this process: "ran" (result is ours), "held" (another live process
    has it; wait=False), "done" (FINISHED by another), "failed" (another process ran it and it
    did not finish: result carries its error)."""

    kind: str
    result: Any = None


def holder_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}:{uuid.uuid4().hex[:8]}"


def _process_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    try:  # a zombie (exited, not reaped: its parent died too) is gone for our purpose
        with open(f"/proc/{pid}/stat") as f:
            return f.read().rsplit(")", 1)[1].split()[0] != "Z"
    except OSError:
        return True


def latest_claim(run) -> tuple[int, str]:
    """(n, holder) of the run's newest claim; (0, "") if never claimed."""
    claims = [(int(k.removeprefix(CLAIM)), v) for k, v in run.data.params.items()
              if k.startswith(CLAIM) and k.removeprefix(CLAIM).isdigit()]
    return max(claims, default=(0, ""))


def _gone(holder: str) -> bool:
    """A holder on this host whose process no longer exists (on another host: never known)."""
    host, _, rest = holder.partition(":")
    pid = rest.split(":")[0]
    return host == socket.gethostname() and pid.isdigit() and not _process_alive(int(pid))


def is_live(run, grace: float, now: float | None = None) -> bool:
    """Whether some process holds the run: a fresh beat, and its holder not known to be gone."""
    n, holder = latest_claim(run)
    beat_n, _, beat = run.data.tags.get(BEAT_TAG, "").partition(":")
    if not beat or beat == "done":
        return False
    if beat_n == str(n) and _gone(holder):
        return False
    return (now or time.time()) - float(beat) < grace


def try_claim(client: Client, run_id: str, grace: float, me: str) -> int:
    """Take the next claim on the run; its number, or 0 when another process holds a live one."""
    from mlflow.exceptions import MlflowException

    run = client.get_run(run_id)
    if is_live(run, grace):
        return 0
    n = latest_claim(run)[0] + 1
    # the beat first: a claimant that dies before its param leaves only a beat that goes stale
    set_tags(client, run_id, {BEAT_TAG: f"{n}:{time.time():.0f}"})
    try:
        client.log_param(run_id, f"{CLAIM}{n}", me)
    except MlflowException as exc:
        if not lost_param_race(exc):
            raise
        return 0  # another process took claim n first
    # who trains the cell now (host:pid): set by the holder only, never by a process waiting for it
    set_tags(client, run_id, {"worker": me.rsplit(":", 1)[0]})
    return n


def released(run) -> bool:
    """Whether the run's newest claim was given up by its holder (a holder that died never says so)."""
    return run.data.tags.get(BEAT_TAG, "") == f"{latest_claim(run)[0]}:done"


class Beat:
    """The holder's beat on its claim, in a thread, until `release`."""

    def __init__(self, client: Client, run_id: str, n: int, every: float):
        self.client, self.run_id, self.n, self.every = client, run_id, n, every
        self.stopped = threading.Event()
        self.thread = threading.Thread(target=self._run, name="claim-beat", daemon=True)
        self.thread.start()

    def _run(self) -> None:
        while not self.stopped.wait(self.every):
            try:
                set_tags(self.client, self.run_id, {BEAT_TAG: f"{self.n}:{time.time():.0f}"})
            except Exception as exc:  # a missed beat; the next one may get through
                log.warning("claim beat on run %s failed: %s", self.run_id, str(exc).splitlines()[0][:300])

    def release(self) -> None:
        self.stopped.set()
        self.thread.join()
        try:
            set_tags(self.client, self.run_id, {BEAT_TAG: f"{self.n}:done"})
        except Exception:  # the beat goes stale instead: same effect after `grace`
            log.warning("could not release the claim on run %s", self.run_id)


def acquire(client: Client, run_id: str, key: str, me: str, beat: float, grace: float, wait: bool) -> Claimed | int:
    """The number of the claim this process took on the run, or how the cell went without it
    ("done", "held" when not `wait`, "failed"; see Claimed)."""
    from experiments.cell_run import CellResult

    announced = False
    while True:
        run = client.get_run(run_id)
        if run.info.status == "FINISHED":
            return Claimed("done")
        # FAILED by a holder that gave up its claim: the cell's own failure. FAILED by the queue for a
        # holder that died (experiments/runtime/optuna_storage.py): taken over below, like any dead holder's cell.
        if announced and run.info.status == "FAILED" and released(run):
            error = run.data.tags.get("error") or run.info.status
            return Claimed("failed", CellResult(key, run_id, "FAILED", error=f"in another process: {error}"))
        n = try_claim(client, run_id, grace, me)
        if n:
            return n
        if not wait:
            return Claimed("held")
        if not announced:
            log.info("cell %s is being trained by %s; waiting for it", key, latest_claim(run)[1] or "another process")
            announced = True
        time.sleep(beat)


def claimed_cell(cell: Cell, uri: str, run_id: str, progress: bool, level: int, threads: int | None,
                 beat: float, grace: float, wait: bool) -> Claimed:
    """Run the cell in its run if this process wins the claim (see the module docstring)."""
    from experiments.cell_run import run_cell

    logging.basicConfig(level=level, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    client = Client(uri, create=False)
    n = acquire(client, run_id, cell.key, holder_id(), beat, grace, wait)
    if isinstance(n, Claimed):
        return n
    beater = Beat(client, run_id, n, beat)
    try:
        res = run_cell(cell, uri, run_id, progress, level, threads)
    finally:
        beater.release()
    settle_finished(client, run_id, cell.task, res)
    return Claimed("ran", res)


def settle_finished(client: Client, run_id: str, task: str, res) -> None:
    """After the claim's release: a FINISHED result stands (the queue may have marked the run FAILED
    meanwhile, for a beat that came late while this process worked: experiments/runtime/optuna_storage.py),
    and its headline metrics are logged."""
    if res.status != "FINISHED":
        return
    if client.get_run(run_id).info.status != "FINISHED":
        log.warning("run %s was marked FAILED while this process finished it (a late beat); FINISHED stands",
                    run_id)
        client.set_terminated(run_id, "FINISHED")
    log_headline(client, run_id, task, res.metrics)


def log_headline(client: Client, run_id: str, task: str, metrics: dict[str, float]) -> None:
    """The cell's main results under names without a task prefix, so that the MLflow runs table
    shows them in one column for every cell: its training task's success rate and the mean of
    the task's primary error metric."""
    from envs.tasks import TASKS

    primary = f"{TASKS[task].primary_metric}_mean" if task in TASKS else "final_distance_mean"
    names = {"success_rate": f"{task}/success_rate", primary: f"{task}/{primary}",
             "train_seconds": "time/train_seconds"}
    log_metrics(client, run_id, {k: metrics[v] for k, v in names.items() if v in metrics})
