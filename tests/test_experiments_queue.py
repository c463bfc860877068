"""`ablation --worker`: worker commands share a cell queue (Optuna RDB storage on SQLite here;
PostgreSQL in tests/integration). One is killed with SIGKILL while it holds a cell at that cell's
first checkpoint (experiments/cell_run.py's test hook); the other joins, and the dead worker's cell
must be failed by heartbeat, re-queued, and resumed by the survivor in the same MLflow run from its
checkpoint: every cell FINISHED once, no duplicate runs, nothing left RUNNING."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
from cli_helpers import cli_env, held_env, run_cli_in_process, wait_for_signals
from mlflow.tracking import MlflowClient

pytestmark = pytest.mark.slow


def _start(args: list[str], cwd: Path, log: Path, env: dict[str, str]) -> subprocess.Popen:
    with open(log, "w") as out:
        return subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env, stdout=out,
                                stderr=subprocess.STDOUT, start_new_session=True)


def test_worker_killed_mid_cell_is_retried_by_the_other(tmp_path):
    import optuna
    from optuna.trial import TrialState

    args = ["ablation", "--profile", "smoke", "--worker", "--study-name", "q", "--set", "train.iters=150",
            "--set", "train.val_every=0", "--set", "eval.figures=0", "--set", "eval.rollouts=2",
            "--set", "sweep.heartbeat=1", "--set", "sweep.grace_period=4"]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    signals = tmp_path / "signals"
    # the victim creates the stores and the queue, takes a cell and holds at its first checkpoint
    # (experiments/cell_run.py's test hook); it dies there, holding the cell; then the survivor joins
    victim = _start(args, tmp_path, tmp_path / "victim.log", held_env(tmp_path, signals))
    survivor = None
    try:
        (run_id, iteration), = wait_for_signals(signals, 1, victim, timeout=240, log=tmp_path / "victim.log")
        os.killpg(victim.pid, signal.SIGKILL)
        victim.wait()
        killed_run = client.get_run(run_id)
        assert killed_run.info.status == "RUNNING" and killed_run.data.tags["checkpoint_iteration"] == str(iteration)
        assert killed_run.data.tags["worker"].endswith(f":{victim.pid}")
        survivor = _start(args, tmp_path, tmp_path / "survivor.log", cli_env(tmp_path))
        rc = survivor.wait(timeout=300)
        out = (tmp_path / "survivor.log").read_text()
        assert rc == 0, out[-4000:]
    finally:
        for p in (victim, survivor):
            if p is not None and p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
                p.wait()
    assert "2 cell(s) run, 0 skipped" in out, out[-2000:]  # the other cell, then the dead worker's

    exp = client.get_experiment_by_name("ablation")
    cells = client.search_runs([exp.experiment_id], "tags.role = 'cell'")
    assert len(cells) == 2 and {r.info.status for r in cells} == {"FINISHED"}  # one run per cell, no duplicates
    resumed = client.get_run(killed_run.info.run_id)
    assert resumed.data.tags["resumed_from_iteration"] == str(iteration)
    assert resumed.data.metrics["train/iterations"] == 150
    parents = client.search_runs([exp.experiment_id], "tags.role = 'parent'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"

    study = optuna.load_study(study_name="ablation-cells:q", storage=f"sqlite:///{tmp_path / 'queue.db'}")
    entries = study.get_trials(deepcopy=False)
    failed = [t for t in entries if t.state == TrialState.FAIL]
    assert len(failed) == 1 and failed[0].user_attrs["mlflow_run_id"] == killed_run.info.run_id
    retry = [t for t in entries if t.system_attrs.get("failed_trial") == failed[0].number]
    assert len(retry) == 1 and retry[0].state == TrialState.COMPLETE
    assert not [t for t in entries if t.state in (TrialState.RUNNING, TrialState.WAITING)]

    again = run_cli_in_process(args, tmp_path)  # nothing left to run: no process of its own needed
    assert again.returncode == 0, again.stderr[-3000:]
    assert "0 cell(s) run, 2 skipped" in again.stdout
