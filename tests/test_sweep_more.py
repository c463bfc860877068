"""Sweeps beyond the default TPE run (tests/test_experiments_e2e.py has pruning and continuation):
the grid sampler covers its grid exactly once, a sweep killed mid-trial on the journal file leaves
a RUNNING trial that the next sweep marks FAIL (and its MLflow run FAILED) and re-queues with the
same parameters before it continues with two worker processes (exit 0, parent FINISHED once the
retry completes), and a sweep whose trials all fail exits with code 1."""

from __future__ import annotations

import optuna
import pytest
from cli_helpers import run_cli, run_cli_in_process
from mlflow.tracking import MlflowClient
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend

pytestmark = pytest.mark.slow


def _study(store, name: str):
    return optuna.load_study(study_name=name, storage=JournalStorage(JournalFileBackend(str(store / "optuna.journal"))))


def _trial_runs(client: MlflowClient) -> dict[int, object]:
    exp = client.get_experiment_by_name("sweep")
    return {int(r.data.tags["trial"]): r for r in client.search_runs([exp.experiment_id], "tags.role = 'trial'")}


def test_grid_sampler_covers_its_grid_exactly_once(tmp_path):
    proc = run_cli_in_process(["sweep", "--profile", "smoke", "--workers", "1", "--sampler", "grid", "--space",
                               "feedback", "--trials", "3", "--study-name", "grid"], tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    trials = _study(tmp_path, "grid").trials
    assert sorted(t.params["feedback"] for t in trials) == ["component_mean", "mixture_mean", "sample"]
    assert all(set(t.params) == {"feedback"} for t in trials)  # --space: nothing else is swept
    runs = _trial_runs(MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}"))
    for t in trials:
        params = runs[t.number].data.params
        assert params["trial.feedback"] == params["train.feedback"] == t.params["feedback"]


def test_journal_sweep_recovers_a_killed_sweeps_trial_and_runs_two_workers(tmp_path):
    from experiments.sweeps.runner import MlflowTrialLink

    args = ["sweep", "--profile", "smoke", "--sampler", "random", "--study-name", "j"]
    first = run_cli_in_process([*args, "--workers", "1", "--trials", "1"], tmp_path)
    assert first.returncode == 0, first.stdout + first.stderr[-3000:]
    # what a sweep killed mid-trial leaves on the journal: a RUNNING trial linked to a RUNNING run
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("sweep")
    parent = client.search_runs([exp.experiment_id], "tags.role = 'parent'")[0]
    study = _study(tmp_path, "j")
    stale = study.ask()
    stale_run = MlflowTrialLink(uri, exp.experiment_id, parent.info.run_id, {}).start(stale)
    assert client.get_run(stale_run).info.status == "RUNNING"

    again = run_cli([*args, "--workers", "2", "--trials", "3"], tmp_path)
    # the killed trial is FAIL and re-queued with its parameters: once the retry completes, a success
    assert again.returncode == 0, again.stdout + again.stderr[-3000:]
    assert f"trial {stale.number} was left RUNNING by a killed sweep; marking it FAIL and re-queueing it" \
        in again.stderr
    trials = _study(tmp_path, "j").trials
    states = {t.number: t.state.name for t in trials}
    assert states.pop(stale.number) == "FAIL"
    assert len(states) == 3 and set(states.values()) <= {"COMPLETE", "PRUNED"}, states
    run = client.get_run(stale_run)
    assert run.info.status == "FAILED" and run.data.tags["trial_state"] == "FAIL"
    new = [t for t in trials if t.number > stale.number]
    assert len(new) == 2 and len({t.user_attrs["worker"] for t in new}) == 2  # one trial in each process
    assert new[0].params != new[1].params  # each process's sampler has its own seed (sweep.seed + worker)
    runs = _trial_runs(client)
    assert sorted(runs) == sorted(t.number for t in trials)  # one MLflow run per trial, none left RUNNING
    assert {r.info.status for n, r in runs.items() if n != stale.number} <= {"FINISHED", "KILLED"}
    assert client.get_run(parent.info.run_id).info.status == "FINISHED"


def test_a_sweep_whose_trials_fail_exits_with_code_1(tmp_path):
    proc = run_cli(["sweep", "--profile", "smoke", "--workers", "1", "--trials", "1", "--study-name", "bad",
                    "--set", "train.lr=1e30"], tmp_path)  # the loss overflows at once
    assert proc.returncode == 1, proc.stdout + proc.stderr[-3000:]
    assert "1 trial(s) FAILED" in proc.stdout
    (trial,) = _study(tmp_path, "bad").trials
    assert trial.state.name == "FAIL"
    run = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}").get_run(trial.user_attrs["mlflow_run_id"])
    assert run.info.status == "FAILED" and "diverged" in run.data.tags["error"]
