"""End to end on the smoke profile, into temporary MLflow/Optuna stores: a parallel ablation
study with its runs, params, metrics and artifacts (the session's smoke store, see conftest.py);
a re-run that skips every cell; a cell killed with SIGKILL at its first checkpoint that resumes
from its checkpoint artifact; a failing cell marked FAILED with its error; a 4-trial sweep with
pruning that a re-run continues."""

from __future__ import annotations

import queue
import re
import signal
import subprocess
import sys
import threading
from pathlib import Path

import numpy as np
import pytest
from cli_helpers import cli_env, kill_at_checkpoints, run_cli_in_process
from mlflow.tracking import MlflowClient
from oracles import drawn_colours, wilson

pytestmark = pytest.mark.slow


def _children(client: MlflowClient, exp_id: str, parent_id: str):
    return client.search_runs([exp_id], f"tags.`mlflow.parentRunId` = '{parent_id}'")


def test_ablation_smoke_end_to_end(smoke_store, tmp_path):
    client = MlflowClient(smoke_store.uri)
    exp = client.get_experiment_by_name("ablation")
    parents = client.search_runs([exp.experiment_id], "tags.role = 'parent'")
    assert len(parents) == 1
    parent = parents[0]
    assert parent.info.status == "FINISHED"
    assert parent.data.tags["kind"] == "ablation" and parent.data.tags["profile"] == "smoke"
    assert parent.data.tags["study_name"] == "smoke"

    children = _children(client, exp.experiment_id, parent.info.run_id)
    assert sorted(r.data.tags["variant"] for r in children) == ["ac-lstm-mdn", "lstm"]
    for run in children:
        assert run.info.status == "FINISHED"
        tags, params, metrics = run.data.tags, run.data.params, run.data.metrics
        assert {tags["task"], tags["seed"], tags["profile"]} == {"reacher", "0", "smoke"}
        assert len(tags["config_hash"]) == 16
        assert params["train.iters"] == "10" and params["model.hidden_size"] == "16"
        assert params["git_commit"] and params["version.torch"] and params["version.mlflow"]
        for task in ("reacher", "reacher-changing-goal"):
            # the logged metrics are the statistics of the logged per-episode outcomes
            local = client.download_artifacts(run.info.run_id, f"rollouts/{task}.npz", str(tmp_path))
            with np.load(local) as z:
                success, final = z["success"], z["final_distance"]
                assert z["tip"].shape[0] == 4 and z["tip"].shape[2] == 3 and np.isfinite(z["goal"]).all()
                if task == "reacher-changing-goal":
                    assert (z["switch_step"] > 0).all() and np.isfinite(z["new_goal"]).all()
                    assert not np.allclose(z["goal"], z["new_goal"])
            assert success.shape == final.shape == (4,) and set(np.unique(success)) <= {0.0, 1.0}
            assert np.array_equal(success == 1.0, final < 0.05)  # the 5 cm success radius
            assert metrics[f"{task}/n_rollouts"] == 4
            assert metrics[f"{task}/success_rate"] == pytest.approx(success.mean())
            assert metrics[f"{task}/final_distance_mean"] == pytest.approx(final.mean())
            low, high = wilson(int(success.sum()), 4)
            assert metrics[f"{task}/success_ci_low"] == pytest.approx(low, abs=1e-9)
            assert metrics[f"{task}/success_ci_high"] == pytest.approx(high, abs=1e-9)
        for key in ("time/train_seconds", "time/rollout_seconds", "time/generation_seconds_per_traj",
                    "time/physics_seconds"):
            assert metrics[key] > 0.0
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
        assert steps == [5, 10]  # log_every = 5, logged in batches, no duplicates
        assert [m.step for m in client.get_metric_history(run.info.run_id, "val/metric")] == [5, 10]
        assert metrics["train/iterations"] == 10
        artifacts = {f.path for d in ("checkpoint", "config", "figures", "rollouts")
                     for f in client.list_artifacts(run.info.run_id, d)}
        assert {"checkpoint/model.pt", "config/config.json", "figures/reacher_rollouts.png",
                "figures/reacher_rollouts.pdf", "figures/reacher-changing-goal_rollouts.png", "rollouts/reacher.npz",
                "rollouts/reacher-changing-goal.npz", "rollouts/ik_timing.json"} <= artifacts
        png = Path(client.download_artifacts(run.info.run_id, "figures/reacher_rollouts.png", str(tmp_path)))
        assert drawn_colours(png) > 10  # paths, markers, axes and text: not a blank canvas
    # the report's success table (experiments.stats.success_table): what n counts is in its columns
    out = smoke_store.stdout
    assert re.search(r"\| task +\| variant +\| success +\| per seed +\| seed-level 95% +\| Wilson 95% \(rollouts "
                     r"independent\) +\| rollouts +"
                     r"\| seeds +\|", out) and re.search(r"\| reacher-changing-goal +\| lstm +\|", out)
    assert f"#/experiments/{exp.experiment_id}/runs" in out
    assert "2 cell(s) run, 0 skipped" in out


def test_rerun_skips_every_finished_cell(smoke_store):
    client = MlflowClient(smoke_store.uri)
    exp_id = client.get_experiment_by_name("ablation").experiment_id
    before = {r.info.run_id: r.info.end_time for r in client.search_runs([exp_id])}
    proc = run_cli_in_process(["ablation", "--profile", "smoke", "--workers", "2"], smoke_store.path)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "0 cell(s) run, 2 skipped" in proc.stdout
    after = {r.info.run_id: r.info.end_time for r in client.search_runs([exp_id]) if r.data.tags["role"] == "cell"}
    assert after == {k: v for k, v in before.items() if k in after} and len(after) == 2  # no cell ran again


def test_cell_killed_at_its_checkpoint_resumes_from_it(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    args = ["ablation", "--profile", "smoke", "--variants", "lstm", "--workers", "1", "--study-name", "killed",
            "--set", "train.iters=100", "--set", "train.checkpoint_every=50", "--set", "train.val_every=0",
            "--set", "eval.figures=0", "--set", "eval.rollouts=2"]
    marks, returncode = kill_at_checkpoints(args, tmp_path, 1, tmp_path / "killed.log")
    (run_id, iteration), = marks
    assert iteration == 50 and returncode == -signal.SIGKILL
    killed = client.get_run(run_id)
    assert killed.info.status == "RUNNING"  # SIGKILL: nobody marked it
    assert killed.data.tags["checkpoint_iteration"] == "50"
    assert [m.step for m in client.get_metric_history(run_id, "train/loss")] == list(range(5, 51, 5))

    done = run_cli_in_process(args, tmp_path)  # the resume needs no process of its own
    assert done.returncode == 0, done.stderr[-3000:]
    run = client.get_run(run_id)
    assert run.info.status == "FINISHED"
    assert run.data.tags["resumed_from_iteration"] == "50"
    assert run.data.metrics["train/iterations"] == 100
    steps = [m.step for m in client.get_metric_history(run_id, "train/loss")]
    assert steps == list(range(5, 101, 5))  # continued after 50, nothing logged twice
    cells = client.search_runs([run.info.experiment_id], "tags.role = 'cell'")
    assert [r.info.run_id for r in cells] == [run_id]


def test_failed_cell_is_marked_with_its_error(tmp_path):
    from experiments.cell_run import run_cell
    from experiments.cells import build_cells
    from experiments.runtime.tracking import Client, get_or_create_experiment
    from experiments.study_config import load_profile

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cell = build_cells(load_profile("smoke", ["train.iters=2", "train.val_every=0"], variants=["lstm"]))[0]
    bad = {**cell.to_dict(), "eval_tasks": ["no-such-task", "reacher"]}
    client = Client(uri)
    run_id = client.create_run(get_or_create_experiment(client, "ablation")).info.run_id
    result = run_cell(bad, uri, run_id)
    assert result.status == "FAILED" and "no-such-task" in result.error
    run = client.get_run(run_id)
    assert run.info.status == "FAILED" and "no-such-task" in run.data.tags["error"]


def test_sweep_with_pruning_continues_to_n_trials(tmp_path):
    import optuna

    # validation every 2 iterations: 5 intermediate values per trial for the median pruner
    args = ["sweep", "--profile", "smoke", "--workers", "1", "--set", "train.val_every=2", "--study-name", "s4"]
    proc = run_cli_in_process([*args, "--trials", "4"], tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    journal = tmp_path / "optuna.journal"
    assert journal.exists()
    storage = optuna.storages.JournalStorage(optuna.storages.journal.JournalFileBackend(str(journal)))
    study = optuna.load_study(study_name="s4", storage=storage)
    states = [t.state.name for t in study.trials]
    assert len(states) == 4 and set(states) <= {"COMPLETE", "PRUNED"}, (states, proc.stderr[-3000:])
    assert "PRUNED" in states and "COMPLETE" in states, [(t.params, t.intermediate_values) for t in study.trials]
    assert all(t.intermediate_values for t in study.trials)

    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("sweep")
    parent = client.search_runs([exp.experiment_id], "tags.role = 'parent'")[0]
    trials = _children(client, exp.experiment_id, parent.info.run_id)
    assert len(trials) == 4
    by_number = {int(r.data.tags["trial"]): r for r in trials}
    for t in study.trials:
        run = by_number[t.number]
        assert t.user_attrs["mlflow_run_id"] == run.info.run_id
        assert run.info.status == {"COMPLETE": "FINISHED", "PRUNED": "KILLED"}[t.state.name]
        assert set(t.params) == {k.removeprefix("trial.") for k in run.data.params if k.startswith("trial.")}
    assert parent.data.metrics["best_value"] == pytest.approx(study.best_value)
    figures = {f.path for f in client.list_artifacts(parent.info.run_id, "figures")}
    assert "figures/optimization_history.png" in figures

    again = run_cli_in_process([*args, "--trials", "5"], tmp_path)
    assert again.returncode == 0, again.stderr[-3000:]
    study = optuna.load_study(study_name="s4", storage=storage)
    assert len(study.trials) == 5
    assert len(_children(client, exp.experiment_id, parent.info.run_id)) == 5


def test_sweep_failure_rate_objective_is_one_minus_the_physics_success(tmp_path):
    import optuna

    args = ["sweep", "--profile", "smoke", "--workers", "1", "--trials", "1", "--study-name", "fr",
            "--set", "sweep.objective=failure_rate", "--set", "sweep.eval_rollouts=3"]
    proc = run_cli_in_process(args, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    backend = optuna.storages.journal.JournalFileBackend(str(tmp_path / "optuna.journal"))
    trial = optuna.load_study(study_name="fr", storage=optuna.storages.JournalStorage(backend)).trials[0]
    run = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}").get_run(trial.user_attrs["mlflow_run_id"])
    assert trial.value == pytest.approx(1.0 - run.data.metrics["reacher/success_rate"])


def _lines(stream) -> queue.Queue:
    """A process's output lines, read by a thread: a test waits for one with a timeout."""
    lines: queue.Queue = queue.Queue()

    def pump():
        for line in stream:
            lines.put(line)
        lines.put(None)  # end of output

    threading.Thread(target=pump, daemon=True).start()
    return lines


def test_ui_serves_the_store_and_stops_cleanly(smoke_store):
    import socket
    import time
    import urllib.request

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    # one server worker (MLflow's --workers, 4 by default): each imports all of MLflow, and serving one test's
    # requests needs none of them; the server still runs in a process group of its own that `ui` stops
    proc = subprocess.Popen([sys.executable, "-m", "experiments", "ui", "--port", str(port)], cwd=smoke_store.path,
                            env=cli_env(smoke_store.path, MLFLOW_WORKERS="1"), stdout=subprocess.PIPE,
                            stderr=subprocess.DEVNULL, text=True, start_new_session=True)
    try:
        lines = _lines(proc.stdout)
        first = [lines.get(timeout=120) for _ in range(2)]
        assert first[0] and first[0].startswith("MLflow UI over sqlite:///"), first
        assert first[1] and f"ablation: http://127.0.0.1:{port}/#/experiments/" in first[1] \
            and first[1].rstrip().endswith("/runs"), first
        deadline, status = time.monotonic() + 120, None
        while status != 200:  # the server takes a while to listen: bounded retries on refused connections
            assert time.monotonic() < deadline and proc.poll() is None, "the UI never answered /health"
            try:
                status = urllib.request.urlopen(f"http://127.0.0.1:{port}/health", timeout=5).status
            except OSError:
                time.sleep(0.5)
        url = f"http://127.0.0.1:{port}/api/2.0/mlflow/experiments/get-by-name?experiment_name=ablation"
        assert b'"ablation"' in urllib.request.urlopen(url, timeout=10).read()
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.wait(timeout=60)
    # `ui` returns only once its server's process group is empty (experiments/ui.py): nothing to wait for
    leftovers = subprocess.run(["ps", "-eo", "args"], capture_output=True, text=True).stdout
    assert f"--port {port}" not in leftovers
