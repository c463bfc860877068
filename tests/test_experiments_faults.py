"""Faults on one machine: Ctrl-C during a study, a corrupt checkpoint artifact, a
NaN loss in one cell, a tracking server that is down and a SQLite store that is locked at
start, a sweep killed mid-trial and re-run (it exits 0 once the retry completes). Process
and concurrency faults: tests/test_experiments_concurrency.py. (A cell killed with SIGKILL
mid-training: tests/test_experiments_e2e.py; a damaged dataset cache: tests/test_datasets.py;
foreign checkpoints: tests/test_stm_train.py.)"""

from __future__ import annotations

import logging
import math
import os
import signal
import sqlite3
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from cli_helpers import held_env, run_cli_in_process, wait_for_signals
from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
FAST = ["--set", "eval.figures=0", "--set", "eval.rollouts=2", "--set", "train.val_every=0"]


def _env(store: Path, **extra: str) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}",
            **extra}


def _cells(client: MlflowClient):
    exp = client.get_experiment_by_name("ablation")
    return client.search_runs([exp.experiment_id], "tags.role = 'cell'") if exp else []


@pytest.mark.slow
@pytest.mark.parametrize("sigint", [signal.SIG_DFL, signal.SIG_IGN], ids=["terminal", "background"])
def test_ctrl_c_marks_running_cells_killed_and_a_rerun_resumes(tmp_path, sigint):
    """`terminal`: a study in a terminal's foreground. `background`: started by a shell with `&`, which
    ignores SIGINT for it (`kill -INT -- -PGID` then stops it as Ctrl-C does; before, only its workers saw
    the signal, and the main process recorded their exit as FAILED cells)."""
    args = [sys.executable, "-m", "experiments", "ablation", "--profile", "smoke", "--workers", "2",
            "--study-name", "intr", "--set", "train.iters=100", "--set", "train.checkpoint_every=50",
            "--set", 'variants=["ac-lstm", "ac-lstm-mdn"]', *FAST]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    signals, log = tmp_path / "signals", tmp_path / "study.log"
    # both cells signal their first checkpoint (iteration 50) and hold there: the Ctrl-C comes at a known
    # point, never racing the training. SIGINT set explicitly in the child: a test run started in the
    # background (`cmd &`, as CI runners may) inherits SIGINT ignored
    with open(log, "w") as out:
        proc = subprocess.Popen(args, cwd=tmp_path, env=held_env(tmp_path, signals), stdout=out,
                                stderr=subprocess.STDOUT, text=True, start_new_session=True,
                                preexec_fn=lambda: signal.signal(signal.SIGINT, sigint))
        try:
            held = wait_for_signals(signals, 2, proc, log=log)
            os.killpg(proc.pid, signal.SIGINT)  # what Ctrl-C in a terminal does: the whole group
            proc.wait(timeout=120)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    err = log.read_text()
    assert sorted(i for _, i in held) == [50, 50]
    assert proc.returncode == 130, err[-3000:]
    assert "re-run the same command to resume" in err
    runs = {r.info.run_id: r for r in _cells(client)}
    assert runs.keys() == {run_id for run_id, _ in held}
    assert {r.info.status for r in runs.values()} == {"KILLED"}, {r.info.status for r in runs.values()}
    parent = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'parent'")
    assert parent[0].info.status == "KILLED"
    if sigint == signal.SIG_IGN:
        return  # what the Ctrl-C left is the same either way: one re-run, below, shows it resumes

    # the re-run in this process, the cells in it too: the resume is the cells' own (experiments/cell_run.py),
    # the same in a worker; three more processes would only add their start-up
    workers = args.index("--workers") + 1
    again = run_cli_in_process([*args[3:workers], "1", *args[workers + 1:]], tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    after = {r.info.run_id: r for r in _cells(client)}
    assert after.keys() == runs.keys()  # resumed in the same runs, none added
    for run in after.values():
        assert run.info.status == "FINISHED"
        assert run.data.tags["resumed_from_iteration"] == "50"
        assert run.data.metrics["train/iterations"] == 100


def _smoke_cell(*overrides: str, variant: str = "lstm"):
    from experiments.cells import build_cells
    from experiments.study_config import load_profile

    return build_cells(load_profile("smoke", ["train.val_every=0", "eval.figures=0", "eval.rollouts=2",
                                              *overrides], variants=[variant]))[0]


class _NotAWeight:  # a pickled object: torch.load(weights_only=True) must refuse to build it
    def __reduce__(self):
        return (os.system, ("echo pwned",))


def _truncated(path: Path) -> str:
    path.write_bytes(b"PK\x03\x04 truncated zip")  # what a checkpoint cut off mid-upload looks like
    return "cannot read checkpoint"


def _other_version(path: Path) -> str:
    import torch

    torch.save({"format_version": 999, "iteration": 5}, path)
    return "format version 999"


def _code_inside(path: Path) -> str:
    import torch

    torch.save({"format_version": 1, "iteration": 5, "x": _NotAWeight()}, path)
    return "cannot read checkpoint"


@pytest.mark.slow
@pytest.mark.parametrize("damage", [_truncated, _other_version, _code_inside])
def test_unusable_checkpoint_artifact_is_retrained_with_one_warning(tmp_path, caplog, damage):
    from experiments.cell_run import run_cell
    from experiments.runtime.tracking import Client, get_or_create_experiment

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cell = _smoke_cell()
    client = Client(uri)
    run_id = client.create_run(get_or_create_experiment(client, "ablation")).info.run_id
    bad = tmp_path / "ckpt" / "model.pt"
    bad.parent.mkdir()
    reason = damage(bad)
    client.log_artifact(run_id, str(bad), "checkpoint")
    with caplog.at_level(logging.WARNING, logger="experiments.cell_run"):
        result = run_cell(cell.to_dict(), uri, run_id)
    assert result.status == "FINISHED", result.error
    warns = [r.getMessage() for r in caplog.records
             if r.levelno >= logging.WARNING and r.name == "experiments.cell_run"]
    assert len(warns) == 1 and "retraining from scratch" in warns[0] and "\n" not in warns[0]
    assert reason in warns[0], warns[0]
    run = client.get_run(run_id)
    assert "checkpoint_discarded" in run.data.tags and "resumed_from_iteration" not in run.data.tags
    assert run.data.metrics["train/iterations"] == 10
    steps = [m.step for m in client.get_metric_history(run_id, "train/loss")]
    assert steps == [5, 10]


@pytest.mark.slow
def test_nan_loss_fails_its_cell_with_the_iteration_and_the_study_goes_on(tmp_path, monkeypatch):
    import stm.training.loop as st
    from experiments.ablation import run_study
    from experiments.study_config import load_profile

    original = st.unroll
    calls = {"mdn": 0}

    def poisoned(view, *a, **k):  # the MDN variant's 4th batch gives a NaN loss
        raw = original(view, *a, **k)
        if view.is_mdn:
            calls["mdn"] += 1
            if calls["mdn"] == 4:
                return raw * math.nan
        return raw

    monkeypatch.setattr(st, "unroll", poisoned)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    cfg = load_profile("smoke", ["train.val_every=0", "eval.figures=0", "eval.rollouts=2"],
                       variants=["ac-lstm-mdn", "lstm"], workers=1, study_name="nan")
    outcome = run_study(cfg, progress=False)
    by_variant = {r.key.split("/")[1]: r for r in outcome.results}
    assert by_variant["ac-lstm-mdn"].status == "FAILED"
    assert "TrainingDiverged" in by_variant["ac-lstm-mdn"].error and "iteration 4" in by_variant["ac-lstm-mdn"].error
    assert by_variant["lstm"].status == "FINISHED"  # the study went on after the failure
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = {r.data.tags["variant"]: r for r in _cells(client)}
    assert runs["ac-lstm-mdn"].info.status == "FAILED" and "iteration 4" in runs["ac-lstm-mdn"].data.tags["error"]
    assert runs["lstm"].info.status == "FINISHED"
    parent = client.get_run(outcome.parent_run_id)
    assert parent.info.status == "FAILED" and parent.data.tags["failed_cells"] == "1"


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.slow
def test_tracking_server_down_gives_one_clear_error_after_bounded_retries(tmp_path):
    env = {**_env(tmp_path), "MLFLOW_TRACKING_URI": f"http://127.0.0.1:{_free_port()}",
           "ACRMDN_STORE_ATTEMPTS": "3", "ACRMDN_STORE_DELAY": "0.1"}
    start = time.monotonic()
    proc = subprocess.run([sys.executable, "-m", "experiments", "ablation", "--profile", "smoke"], cwd=tmp_path,
                          env=env, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: MLflow tracking server http://127.0.0.1:") and "after 3 tries" in last
    assert proc.stderr.count("not ready") == 2  # one line per retry
    assert time.monotonic() - start < 60
    assert not list(tmp_path.iterdir())  # nothing written


def _mlflow_store(tmp_path: Path) -> MlflowClient:
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    client.create_experiment("existing")
    return client


@pytest.mark.slow
def test_locked_sqlite_store_gives_one_clear_error_and_stays_untouched(tmp_path):
    client = _mlflow_store(tmp_path)
    before = [e.name for e in client.search_experiments()]
    lock = sqlite3.connect(tmp_path / "mlflow.db", isolation_level=None)
    lock.execute("BEGIN EXCLUSIVE")  # another writer holding the store
    try:
        env = {**_env(tmp_path), "ACRMDN_STORE_ATTEMPTS": "2", "ACRMDN_STORE_DELAY": "0.1"}
        proc = subprocess.run([sys.executable, "-m", "experiments", "ablation", "--profile", "smoke"], cwd=tmp_path,
                              env=env, capture_output=True, text=True, timeout=120)
    finally:
        lock.execute("ROLLBACK")
        lock.close()
    assert proc.returncode == 3, proc.stderr[-2000:]
    assert "Traceback" not in proc.stderr
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("error: MLflow store ") and "locked" in last
    assert [e.name for e in client.search_experiments()] == before
    assert not client.search_runs([e.experiment_id for e in client.search_experiments()])


@pytest.mark.slow
def test_store_locked_for_a_moment_is_waited_for(tmp_path):
    from experiments.runtime.store_check import wait_for_stores

    _mlflow_store(tmp_path)
    lock = sqlite3.connect(tmp_path / "mlflow.db", isolation_level=None, check_same_thread=False)
    lock.execute("BEGIN EXCLUSIVE")
    timer = threading.Timer(0.6, lambda: (lock.execute("ROLLBACK"), lock.close()))
    timer.start()
    start = time.monotonic()
    wait_for_stores(f"sqlite:///{tmp_path / 'mlflow.db'}", attempts=6, delay=0.2)
    timer.join()
    assert time.monotonic() - start >= 0.5  # it did wait for the lock, then went on


@pytest.mark.slow
def test_sweep_that_recovers_from_a_killed_trial_exits_0_with_its_parent_finished(tmp_path):
    import optuna
    from optuna.trial import TrialState

    args = [sys.executable, "-m", "experiments", "sweep", "--profile", "smoke", "--workers", "1", "--trials", "1",
            "--study-name", "rec", "--set", "train.iters=400", "--set", "train.val_every=20"]
    journal = tmp_path / "optuna.journal"
    proc = subprocess.Popen(args, cwd=tmp_path, env=_env(tmp_path), stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL, start_new_session=True)
    killed = False
    try:
        deadline = time.monotonic() + 240
        while time.monotonic() < deadline and proc.poll() is None and not killed:
            time.sleep(0.3)
            if not journal.exists():
                continue
            storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
            try:
                trials = optuna.load_study(study_name="rec", storage=storage).get_trials(deepcopy=False)
            except KeyError:  # not created yet
                continue
            if trials and trials[0].state == TrialState.RUNNING and trials[0].intermediate_values:
                os.killpg(proc.pid, signal.SIGKILL)
                killed = True
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert killed, "the trial finished or never validated before the kill"
    again = subprocess.run(args, cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True, timeout=400)
    # before: exit 1 and the parent FAILED although the killed trial's retry completed the sweep
    assert again.returncode == 0, again.stderr[-3000:]
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    trials = optuna.load_study(study_name="rec", storage=storage).get_trials(deepcopy=False)
    assert [t.state for t in trials] in ([TrialState.FAIL, TrialState.COMPLETE], [TrialState.FAIL, TrialState.PRUNED])
    assert trials[1].params == trials[0].params and trials[1].system_attrs["failed_trial"] == 0
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    parent = client.search_runs([client.get_experiment_by_name("sweep").experiment_id], "tags.role = 'parent'")[0]
    assert parent.info.status == "FINISHED"
    assert "**sweep `rec`**" in parent.data.tags["mlflow.note.content"]
