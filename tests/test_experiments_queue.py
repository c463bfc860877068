"""`ablation --worker`: two worker commands share a cell queue (Optuna RDB storage on
SQLite here; PostgreSQL in tests/integration); one is killed with SIGKILL mid-cell. Its cell
must be failed by heartbeat, re-queued, and resumed by the survivor in the same MLflow run
from its checkpoint: every cell FINISHED once, no duplicate runs, nothing left RUNNING."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow


def _start(args: list[str], cwd: Path, log: Path) -> subprocess.Popen:
    env = {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{cwd / 'mlflow.db'}"}
    return subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env, stdout=open(log, "w"),
                            stderr=subprocess.STDOUT, start_new_session=True)


def test_worker_killed_mid_cell_is_retried_by_the_other(tmp_path):
    import optuna
    from optuna.trial import TrialState

    args = ["ablation", "--profile", "smoke", "--worker", "--study-name", "q", "--set", "train.iters=150",
            "--set", "train.val_every=0", "--set", "eval.figures=0", "--set", "eval.rollouts=2",
            "--set", "sweep.heartbeat=1", "--set", "sweep.grace_period=4"]
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    survivor = _start(args, tmp_path, tmp_path / "survivor.log")
    time.sleep(1.0)  # the first command creates the stores; the second joins (races are handled, but slower)
    victim = _start(args, tmp_path, tmp_path / "victim.log")
    killed_run = None
    try:
        deadline = time.monotonic() + 240
        while killed_run is None and time.monotonic() < deadline and victim.poll() is None:
            time.sleep(0.3)
            try:
                runs = client.search_runs([client.get_experiment_by_name("ablation").experiment_id],
                                          "tags.role = 'cell'")
            except Exception:  # store not created yet
                continue
            for run in runs:
                if run.data.tags.get("worker", "").endswith(f":{victim.pid}") and \
                        int(run.data.tags.get("checkpoint_iteration", 0)) >= 5:
                    os.killpg(victim.pid, signal.SIGKILL)
                    killed_run = run
                    break
        assert killed_run is not None, (tmp_path / "victim.log").read_text()[-3000:]
        victim.wait()
        rc = survivor.wait(timeout=300)
        out = (tmp_path / "survivor.log").read_text()
        assert rc == 0, out[-4000:]
    finally:
        for p in (victim, survivor):
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert "2 cell(s) run, 0 skipped" in out or "1 cell(s) run, 1 skipped" in out, out[-2000:]

    exp = client.get_experiment_by_name("ablation")
    cells = client.search_runs([exp.experiment_id], "tags.role = 'cell'")
    assert len(cells) == 2 and {r.info.status for r in cells} == {"FINISHED"}  # one run per cell, no duplicates
    resumed = client.get_run(killed_run.info.run_id)
    assert int(resumed.data.tags["resumed_from_iteration"]) >= int(killed_run.data.tags["checkpoint_iteration"])
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

    again = _start(args, tmp_path, tmp_path / "again.log")
    assert again.wait(timeout=120) == 0
    assert "0 cell(s) run, 2 skipped" in (tmp_path / "again.log").read_text()
