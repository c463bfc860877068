"""Scale-out on PostgreSQL: two sweep workers (separate `python -m experiments sweep`
commands, as on two hosts) share an Optuna RDB storage and an MLflow tracking server backed
by PostgreSQL; one is killed with SIGKILL mid-trial. Its trial must be failed by heartbeat,
re-queued and finished by the survivor; every trial must have its MLflow run with metrics
and nothing may be left RUNNING."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from cli_helpers import HOLD_ENV, SIGNAL_FILE_ENV, wait_for_signals

REPO = Path(__file__).resolve().parents[2]
pytestmark = pytest.mark.integration

TRIALS = 6
STUDY = "it-pg"


def _worker(args: list[str], cwd: Path, env: dict[str, str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT, start_new_session=True)


def _stop(proc: subprocess.Popen) -> None:
    if proc.poll() is None:
        os.killpg(proc.pid, signal.SIGKILL)
    proc.wait()


def test_two_workers_one_killed_mid_trial(postgres, mlflow_server, tmp_path):
    import optuna
    from mlflow.tracking import MlflowClient
    from optuna.trial import TrialState

    storage_url = postgres.url("optuna")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": mlflow_server.url}
    # trials of ~100 iterations with validation every 10: long enough to be killed mid-trial;
    # heartbeat 1 s, dead after 4 s without one
    args = ["sweep", "--profile", "smoke", "--workers", "1", "--trials", str(TRIALS), "--storage", storage_url,
            "--study-name", STUDY, "--sampler", "random", "--space", "m,u,v",
            "--set", "train.iters=100", "--set", "train.val_every=10", "--set", "train.log_every=10",
            "--set", "sweep.heartbeat=1", "--set", "sweep.grace_period=4", "--set", "sweep.startup_trials=2"]
    survivor = _worker(args, tmp_path, env, tmp_path / "survivor.log")
    victim = _worker(args, tmp_path, env, tmp_path / "victim.log")
    killed_trial = None
    try:
        deadline = time.monotonic() + 300
        while killed_trial is None and time.monotonic() < deadline and victim.poll() is None:
            time.sleep(0.2)
            try:
                study = optuna.load_study(study_name=STUDY, storage=storage_url)
            except KeyError:  # not created yet
                continue
            for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
                if t.user_attrs.get("worker", "").endswith(f":{victim.pid}") and t.intermediate_values:
                    os.killpg(victim.pid, signal.SIGKILL)
                    killed_trial = t.number
                    break
        assert killed_trial is not None, "the victim never ran a trial past its first validation:\n" + \
            (tmp_path / "victim.log").read_text()[-3000:]
        victim.wait()
        rc = survivor.wait(timeout=400)
        out = (tmp_path / "survivor.log").read_text()
        assert rc == 0, out[-4000:]
    finally:
        _stop(victim)
        _stop(survivor)

    study = optuna.load_study(study_name=STUDY, storage=storage_url)
    trials = study.get_trials(deepcopy=False)
    by_number = {t.number: t for t in trials}
    assert not [t.number for t in trials if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    failed = [t for t in trials if t.state == TrialState.FAIL]
    assert [t.number for t in failed] == [killed_trial], [(t.number, t.state.name) for t in trials]
    retries = [t for t in trials if t.system_attrs.get("failed_trial") == killed_trial]
    assert len(retries) == 1 and retries[0].state in (TrialState.COMPLETE, TrialState.PRUNED)
    assert retries[0].params == by_number[killed_trial].params  # re-queued with the same parameters
    done = [t for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)]
    assert len(done) >= TRIALS and len(done) == len(trials) - 1
    # every logical trial finished exactly once: the killed one through its retry only
    assert len({t.number for t in done}) == len(done) and killed_trial not in {t.number for t in done}

    client = MlflowClient(mlflow_server.url)
    exp = client.get_experiment_by_name("sweep")
    parents = client.search_runs([exp.experiment_id], "tags.role = 'parent'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    runs = client.search_runs([exp.experiment_id], f"tags.`mlflow.parentRunId` = '{parents[0].info.run_id}'")
    assert not [r.info.run_id for r in runs if r.info.status == "RUNNING"]
    by_run = {r.info.run_id: r for r in runs}
    assert len(runs) == len(trials)
    for t in trials:
        run = by_run[t.user_attrs["mlflow_run_id"]]
        assert int(run.data.tags["trial"]) == t.number
        expected = {"COMPLETE": "FINISHED", "PRUNED": "KILLED", "FAIL": "FAILED"}[t.state.name]
        assert run.info.status == expected, (t.number, t.state.name, run.info.status)
        assert "val/metric" in run.data.metrics  # every trial validated at least once before it ended
        if t.state == TrialState.COMPLETE:
            assert run.data.metrics["objective"] == pytest.approx(t.value)
    killed_run = by_run[by_number[killed_trial].user_attrs["mlflow_run_id"]]
    assert "no heartbeat" in killed_run.data.tags["error"]
    assert by_run[retries[0].user_attrs["mlflow_run_id"]].data.tags["retry_of_trial"] == str(killed_trial)


def test_ablation_workers_share_a_cell_queue_and_one_is_killed(postgres, mlflow_server, tmp_path):
    """`ablation --worker --queue postgresql://...` on two "hosts"; the killed worker's cell is
    re-queued by heartbeat and resumed from its checkpoint artifact (served by the tracking
    server) in the same MLflow run."""
    import optuna
    from mlflow.tracking import MlflowClient
    from optuna.trial import TrialState

    queue = postgres.url("optuna")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": mlflow_server.url}
    args = ["ablation", "--profile", "smoke", "--worker", "--queue", queue, "--study-name", "it-queue",
            "--set", "train.iters=150", "--set", "train.val_every=0", "--set", "eval.figures=0",
            "--set", "eval.rollouts=2", "--set", "sweep.heartbeat=1", "--set", "sweep.grace_period=4"]
    client = MlflowClient(mlflow_server.url)
    signals = tmp_path / "signals"
    # both join at once; the victim holds at its cell's first checkpoint (experiments/cell_run.py's test
    # hook) and is killed there, holding the cell
    survivor = _worker(args, tmp_path, env, tmp_path / "a.log")
    victim = _worker(args, tmp_path, {**env, SIGNAL_FILE_ENV: str(signals), HOLD_ENV: "1"}, tmp_path / "b.log")
    try:
        (run_id, iteration), = wait_for_signals(signals, 1, victim, timeout=300, log=tmp_path / "b.log")
        os.killpg(victim.pid, signal.SIGKILL)
        victim.wait()
        killed = client.get_run(run_id)
        assert killed.info.status == "RUNNING" and killed.data.tags["checkpoint_iteration"] == str(iteration)
        assert killed.data.tags["worker"].endswith(f":{victim.pid}")
        assert survivor.wait(timeout=400) == 0, (tmp_path / "a.log").read_text()[-4000:]
    finally:
        _stop(victim)
        _stop(survivor)
    exp = client.get_experiment_by_name("ablation")
    parents = client.search_runs([exp.experiment_id], "tags.role = 'parent' and tags.study_name = 'it-queue'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    cells = client.search_runs([exp.experiment_id], f"tags.`mlflow.parentRunId` = '{parents[0].info.run_id}'")
    assert len(cells) == 2 and {r.info.status for r in cells} == {"FINISHED"}
    resumed = client.get_run(killed.info.run_id)
    assert int(resumed.data.tags["resumed_from_iteration"]) >= int(killed.data.tags["checkpoint_iteration"])
    assert resumed.data.metrics["train/iterations"] == 150
    entries = optuna.load_study(study_name="ablation-cells:it-queue", storage=queue).get_trials(deepcopy=False)
    assert [t.state for t in entries].count(TrialState.FAIL) == 1
    assert not [t for t in entries if t.state in (TrialState.RUNNING, TrialState.WAITING)]
