"""Races between queue workers (experiments/runtime/optuna_storage.py, experiments/runtime/claims.py), each set up
on a real SQLite MLflow store and Optuna RDB storage: a trial failed as stale must not overrule a
run that is FINISHED or that a live process holds; a process waiting for a dead holder's cell
takes it over even when the queue has marked the run FAILED; a worker whose trial another worker
failed as stale (a late heartbeat) keeps working instead of crashing. The PostgreSQL soak test
(tests/integration/test_postgres_soak.py) met these by chance; here each is forced."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

HOST = socket.gethostname()


@pytest.fixture
def store(tmp_path: Path):
    from experiments.runtime.tracking import Client, get_or_create_experiment

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = Client(uri)
    return uri, client, get_or_create_experiment(client, "ablation")


def _queue(tmp_path: Path, grace: float = 60):
    import optuna

    optuna.logging.set_verbosity(optuna.logging.WARNING)
    storage = optuna.storages.RDBStorage(f"sqlite:///{tmp_path / 'queue.db'}", heartbeat_interval=1,
                                         grace_period=grace)
    return optuna.create_study(study_name="q", storage=storage)


def _dead_pid() -> int:
    proc = subprocess.Popen([sys.executable, "-c", "pass"])
    proc.wait()
    return proc.pid


def _claimed(client, run_id: str, n: int, holder: str, beat: str | None = None) -> None:
    client.log_param(run_id, f"claim.{n}", holder)
    client.set_tag(run_id, "claim.beat", beat or f"{n}:{time.time():.0f}")


def test_a_stale_trial_fails_only_its_dead_workers_runs_and_is_requeued(store, tmp_path):
    from experiments.runtime.optuna_storage import RetryDeadTrial

    uri, client, exp = store
    finished, held, dead = (client.create_run(exp).info.run_id for _ in range(3))
    client.set_terminated(finished, "FINISHED")  # the seed a pack finished before its worker died
    _claimed(client, held, 1, f"{HOST}:{os.getpid()}:live")  # this process: alive, beating
    _claimed(client, dead, 1, f"{HOST}:{_dead_pid()}:gone")
    study = _queue(tmp_path)
    trial = study.ask()
    trial.set_user_attr("mlflow_run_ids", [finished, held, dead])
    trial.set_user_attr("worker", "vm:1")
    frozen = study._storage.get_trial(trial._trial_id)

    RetryDeadTrial(max_retry=3, uri=uri, grace=60)(study, frozen)

    assert client.get_run(finished).info.status == "FINISHED"
    assert client.get_run(held).info.status == "RUNNING" and "error" not in client.get_run(held).data.tags
    gone = client.get_run(dead)
    assert gone.info.status == "FAILED" and gone.data.tags["error"].startswith("worker vm:1 died")
    retried = [t for t in study.get_trials(deepcopy=False) if t.system_attrs.get("failed_trial") == trial.number]
    assert len(retried) == 1 and retried[0].state.name == "WAITING"


@pytest.mark.parametrize("released", [False, True], ids=["holder-died", "holder-gave-up"])
def test_a_waiter_takes_over_a_dead_holders_failed_run_but_not_a_released_one(store, released, monkeypatch):
    import experiments.runtime.claims as claims
    from experiments.runtime.claims import Claimed, acquire, latest_claim

    uri, client, exp = store
    run_id = client.create_run(exp).info.run_id
    # a holder on another host (its process cannot be checked): live until its beat is `grace` old
    _claimed(client, run_id, 1, "elsewhere:7:a")
    waiting = threading.Event()
    real_sleep = claims.time.sleep

    def waiter_sleeps(seconds: float) -> None:  # acquire sleeps once it has seen the holder and waits for it
        waiting.set()
        real_sleep(seconds)

    monkeypatch.setattr(claims.time, "sleep", waiter_sleeps)

    def holder_stops() -> None:  # while this process waits for it, however slow the machine
        waiting.wait(timeout=60)
        if released:  # its own attempt failed: it says so and gives up its claim
            client.set_terminated(run_id, "FAILED")
            client.set_tag(run_id, "claim.beat", "1:done")
        else:  # killed: its beat goes stale, and the queue marks the run FAILED for it
            client.set_tag(run_id, "error", "worker elsewhere:7 died (no heartbeat); the trial was re-queued")
            client.set_terminated(run_id, "FAILED")

    stopper = threading.Thread(target=holder_stops)
    stopper.start()
    got = acquire(client, run_id, "reacher/ac-lstm/seed0", f"{HOST}:{os.getpid()}:w", beat=0.2, grace=1.5,
                  wait=True)
    stopper.join()

    if released:  # reported as failed, not trained again
        assert isinstance(got, Claimed) and got.kind == "failed" and "in another process" in got.result.error
        assert latest_claim(client.get_run(run_id))[0] == 1
    else:  # the dead holder's cell is this process's now
        assert got == 2
        run = client.get_run(run_id)
        assert latest_claim(run) == (2, f"{HOST}:{os.getpid()}:w")
        assert run.data.tags["worker"] == f"{HOST}:{os.getpid()}"


def test_a_worker_whose_trial_was_failed_as_stale_goes_on_with_the_queue(tmp_path):
    from optuna.trial import TrialState

    from experiments.runtime.optuna_storage import drain

    study = _queue(tmp_path)
    for _ in range(2):
        study.enqueue_trial({})
    ran: list[int] = []

    def objective(trial) -> float:
        ran.append(trial.number)
        if trial.number == 0:  # another worker's staleness check while this one worked on
            study._storage.set_trial_state_values(trial._trial_id, TrialState.FAIL)
        return 0.0

    drain(study, lambda: study.optimize(objective, n_trials=1, catch=(Exception,)), poll=0.1, what="cell")

    assert ran == [0, 1]
    assert [t.state for t in study.get_trials(deepcopy=False)] == [TrialState.FAIL, TrialState.COMPLETE]


def test_other_errors_of_a_worker_still_stop_it(tmp_path):
    from experiments.runtime.optuna_storage import drain

    study = _queue(tmp_path)
    study.enqueue_trial({})

    def run_one() -> None:
        raise ValueError("Cannot parse the queue entry")

    with pytest.raises(ValueError, match="Cannot parse"):
        drain(study, run_one, poll=0.1)


def test_a_stale_trial_is_requeued_even_when_one_of_its_runs_cannot_be_marked(store, tmp_path):
    from experiments.runtime.optuna_storage import RetryDeadTrial

    uri, client, exp = store
    dead = client.create_run(exp).info.run_id
    _claimed(client, dead, 1, f"{HOST}:{_dead_pid()}:gone")
    study = _queue(tmp_path)
    trial = study.ask()
    trial.set_user_attr("mlflow_run_ids", ["0" * 32, dead])  # the first: no such run (the store refuses it)
    frozen = study._storage.get_trial(trial._trial_id)

    RetryDeadTrial(max_retry=3, uri=uri, grace=60)(study, frozen)

    assert client.get_run(dead).info.status == "FAILED"
    assert [t.state.name for t in study.get_trials(deepcopy=False)
            if t.system_attrs.get("failed_trial") == trial.number] == ["WAITING"]


def test_only_cells_ended_by_their_own_error_or_finished_count_as_settled(store):
    from experiments.runtime.cell_queue import unsettled_hashes

    uri, client, exp = store
    parent = client.create_run(exp).info.run_id

    def cell_run(config_hash: str, status: str | None, beat: str | None = None) -> None:
        run_id = client.create_run(exp, tags={"mlflow.parentRunId": parent, "config_hash": config_hash}).info.run_id
        _claimed(client, run_id, 1, f"elsewhere:7:{config_hash}", beat)
        if status:
            client.set_terminated(run_id, status)

    cell_run("finished", "FINISHED", "1:done")
    cell_run("own-error", "FAILED", "1:done")  # its holder gave up the claim: the cell's own failure
    cell_run("queue-failed", "FAILED", "1:100")  # failed by the queue for a holder that stopped beating
    cell_run("running", None)  # its entry ended while its holder went on (or was killed)
    cell_run("killed", "KILLED", "1:done")

    hashes = ["finished", "own-error", "queue-failed", "running", "killed", "never-run"]
    assert unsettled_hashes(client, exp, parent, hashes) == ["queue-failed", "running", "killed", "never-run"]


def test_the_last_worker_out_runs_what_the_queue_lost_before_it_stops(tmp_path):
    from experiments.runtime.optuna_storage import drain

    study = _queue(tmp_path)
    lost = ["cell-a"]  # no entry holds it: found by refill once the queue is empty
    ran: list[str] = []

    def refill() -> int:
        for cell in lost:
            study.enqueue_trial({}, user_attrs={"cell": cell})
        n, lost[:] = len(lost), []
        return n

    def objective(trial) -> float:
        ran.append(trial.user_attrs["cell"])
        return 0.0

    drain(study, lambda: study.optimize(objective, n_trials=1, catch=(Exception,)), poll=0.1, refill=refill)

    assert ran == ["cell-a"]


def test_a_holders_finished_result_stands_over_the_queues_late_failure(store):
    from experiments.cell_run import CellResult
    from experiments.runtime.claims import settle_finished

    uri, client, exp = store
    run_id = client.create_run(exp).info.run_id
    client.set_terminated(run_id, "FAILED")  # the queue, reading a stale beat just as this process finished

    settle_finished(client, run_id, "reacher", CellResult("reacher/lstm/seed0", run_id, "FINISHED",
                                                          metrics={"reacher/success_rate": 0.5}))

    run = client.get_run(run_id)
    assert run.info.status == "FINISHED" and run.data.metrics["success_rate"] == 0.5
