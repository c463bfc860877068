"""Soak on PostgreSQL: four `ablation --worker` commands (as on four hosts) share one cell queue
(Optuna RDB storage) and one MLflow tracking server, both on PostgreSQL. The first worker starts
alone and holds at its first checkpoint (the fault hook, experiments/cell_run.py), the three others
join, and the first is killed with SIGKILL where it holds: so at least one worker is always
caught mid-cell, however fast the cells train. After that, every minute one worker caught
training a cell is killed (if any still is), and a fresh one takes each victim's place. At the
end every cell is FINISHED exactly once (one run per cell, its steps logged once), no run is
left RUNNING and nothing is left in the queue. Two to four minutes."""

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

WORKERS = 4
KILL_EVERY = 60.0  # seconds
MAX_KILLS = 3
STUDY = "it-soak"


def _worker(args: list[str], cwd: Path, env: dict[str, str], log: Path) -> subprocess.Popen:
    return subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env,
                            stdout=open(log, "w"), stderr=subprocess.STDOUT, start_new_session=True)


def test_four_workers_one_killed_every_minute(postgres, mlflow_server, tmp_path):
    import optuna
    from mlflow.tracking import MlflowClient
    from optuna.trial import TrialState

    queue = postgres.url("optuna")
    env = {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": mlflow_server.url}
    # 16 cells (4 variants x 4 seeds) of a few hundred iterations each: minutes of work for four workers
    args = ["ablation", "--profile", "smoke", "--worker", "--queue", queue, "--study-name", STUDY,
            "--variants", "lstm,ac-lstm,lstm-mdn,ac-lstm-mdn", "--seeds", "4",
            "--set", "train.iters=400", "--set", "train.checkpoint_every=20", "--set", "train.val_every=0",
            "--set", "eval.figures=0", "--set", "eval.rollouts=2", "--set", "sweep.heartbeat=1",
            "--set", "sweep.grace_period=5", "--set", "sweep.max_retry=5"]
    client = MlflowClient(mlflow_server.url)
    signals = tmp_path / "held.signals"
    procs = [_worker(args, tmp_path, {**env, SIGNAL_FILE_ENV: str(signals), HOLD_ENV: "1"}, tmp_path / "w0.log")]
    killed: list[str] = []
    victims_pids: set[int] = set()
    try:
        held = wait_for_signals(signals, 1, procs[0], log=tmp_path / "w0.log")  # the whole pack signals at once
        procs += [_worker(args, tmp_path, env, tmp_path / f"w{i}.log") for i in range(1, WORKERS)]
        os.killpg(procs[0].pid, signal.SIGKILL)
        killed.append(held[0][0])
        victims_pids.add(procs[0].pid)
        procs.append(_worker(args, tmp_path, env, tmp_path / f"w{len(procs)}.log"))  # a fresh host joins
        deadline = time.monotonic() + 600
        next_kill = time.monotonic() + KILL_EVERY
        while time.monotonic() < deadline and any(p.poll() is None for p in procs):
            time.sleep(1.0)
            if len(killed) >= MAX_KILLS or time.monotonic() < next_kill:
                continue
            exp = client.get_experiment_by_name("ablation")
            runs = client.search_runs([exp.experiment_id], "tags.role = 'cell' and attributes.status = 'RUNNING'")
            live = {p.pid: p for p in procs if p.poll() is None}
            victims = [r for r in runs if int(r.data.tags.get("checkpoint_iteration", 0)) >= 20
                       and int(r.data.tags.get("worker", ":0").rsplit(":", 1)[1]) in live]
            if not victims:
                continue
            pid = int(victims[0].data.tags["worker"].rsplit(":", 1)[1])
            os.killpg(pid, signal.SIGKILL)
            killed.append(victims[0].info.run_id)
            victims_pids.add(pid)
            procs.append(_worker(args, tmp_path, env, tmp_path / f"w{len(procs)}.log"))  # a fresh host joins
            next_kill = time.monotonic() + KILL_EVERY
        for i, p in enumerate(procs):
            if p.pid not in victims_pids:
                assert p.wait(timeout=300) == 0, (tmp_path / f"w{i}.log").read_text()[-3000:]
    finally:
        for p in procs:
            if p.poll() is None:
                os.killpg(p.pid, signal.SIGKILL)
            p.wait()
    assert killed, "no worker was ever caught training a cell"

    exp = client.get_experiment_by_name("ablation")
    parents = client.search_runs([exp.experiment_id], f"tags.role = 'parent' and tags.study_name = '{STUDY}'")
    assert len(parents) == 1 and parents[0].info.status == "FINISHED"
    cells = client.search_runs([exp.experiment_id], f"tags.`mlflow.parentRunId` = '{parents[0].info.run_id}'")
    hashes = [r.data.tags["config_hash"] for r in cells]
    assert len(cells) == 16 and len(set(hashes)) == 16  # one run per cell
    assert {r.info.status for r in cells} == {"FINISHED"}  # nothing left RUNNING
    for run in cells:
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
        assert len(steps) == len(set(steps)) and max(steps) == 400, run.data.tags["worker"]
    for run_id in killed:  # the killed cells were resumed in their own run from a checkpoint
        assert int(client.get_run(run_id).data.tags["resumed_from_iteration"]) >= 20
    entries = optuna.load_study(study_name=f"ablation-cells:{STUDY}", storage=queue).get_trials(deepcopy=False)
    assert not [t for t in entries if t.state in (TrialState.RUNNING, TrialState.WAITING)]
    # one FAIL per kill; a starved worker's late heartbeat may fail (and re-queue) a live one's entry too,
    # which the checks above show costs nothing (tests/test_queue_races.py forces that case)
    assert [t.state for t in entries].count(TrialState.FAIL) >= len(killed)
