"""End to end: `python -m reports` on a real smoke ablation (the session's, built by the experiments CLI:
conftest.py)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pandas as pd
import pytest
from mlflow import MlflowClient

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_smoke_ablation_report(smoke_store, tmp_path):
    env = {**os.environ, "MLFLOW_TRACKING_URI": smoke_store.uri, "PYTHONPATH": str(ROOT)}
    out = tmp_path / "out"
    report = subprocess.run([sys.executable, "-m", "reports", "--out", str(out)], cwd=smoke_store.path, env=env,
                            capture_output=True, text=True, timeout=300)
    assert report.returncode == 0, report.stderr[-2000:]

    client = MlflowClient(env["MLFLOW_TRACKING_URI"])
    exp = client.get_experiment_by_name("ablation")
    parent = next(r for r in client.search_runs([exp.experiment_id]) if "mlflow.parentRunId" not in r.data.tags)
    folder = out / parent.data.tags["study_name"]
    for table in ("success_table", "circle_table", "train_time_table", "metrics_table"):
        for ext in ("md", "html", "tex", "csv"):
            assert (folder / f"{table}.{ext}").exists()
    index = (folder / "index.html").read_text()
    for fig in ("success_bars", "circles", "compute_time", "train_time", "training_curves", "tip_paths",
                "changing_goal"):
        assert (folder / f"{fig}.png").exists() or f"figure <b>{fig}</b>" in index  # drawn, or listed as a gap

    # the success table's numbers are the runs' logged numbers
    children = [r for r in client.search_runs([exp.experiment_id])
                if r.data.tags.get("mlflow.parentRunId") == parent.info.run_id]
    table = pd.read_csv(folder / "success_table.csv").set_index(["variant", "eval_task"])
    for run in children:
        for task in ("reacher", "reacher-changing-goal"):
            logged = run.data.metrics[f"{task}/success_rate"]
            assert table.loc[(run.data.tags["variant"], task), "mean"] == pytest.approx(logged)
            assert table.loc[(run.data.tags["variant"], task), "n"] == run.data.metrics[f"{task}/n_rollouts"]
    # trajectory figures are drawn exactly when the runs logged their rollouts
    has_rollouts = any(f.path == "rollouts/reacher.npz" for r in children for f in client.list_artifacts(
        r.info.run_id, "rollouts"))
    assert (folder / "tip_paths.png").exists() == has_rollouts
    assert any(f.path == "report/index.html" for f in client.list_artifacts(parent.info.run_id, "report"))
