"""`python -m experiments scaling`: each worker count trains the same cells into its own temporary store, and the
figures it reports are the cells' iterations over the arm's wall time (the measurement itself needs idle cores,
so it is run by hand, not here)."""

from __future__ import annotations

import json

import pytest

from experiments.cli import main


def test_one_arm_counts_every_cells_iterations_and_leaves_no_store(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'kept.db'}")
    out = tmp_path / "scaling.json"
    code = main(["scaling", "--profile", "smoke", "--tasks", "reacher", "--variants", "lstm", "ac-lstm",
                 "--seeds", "2", "--iters", "3", "--workers", "1", "--json", str(out)])
    assert code == 0
    result = json.loads(out.read_text())
    (arm,) = result["arms"]
    assert arm["workers"] == 1 and arm["cells"] == 4 and arm["model_iterations"] == 12
    assert arm["speedup"] == 1.0
    assert arm["model_iterations_per_s"] == pytest.approx(12 / arm["seconds"], rel=2e-3)  # both rounded
    assert not (tmp_path / "mlflow.db").exists() and not (tmp_path / "kept.db").exists()  # a temporary store
    assert result["threads_per_process"] == 1


def test_bad_worker_counts_exit_2(capsys):
    assert main(["scaling", "--workers", "1", "1"]) == 2
    assert main(["scaling", "--workers", "0", "2"]) == 2
    assert "distinct counts >= 1" in capsys.readouterr().err


def test_an_unknown_task_is_one_line(capsys):
    assert main(["scaling", "--profile", "smoke", "--tasks", "juggling", "--workers", "1"]) == 2
    assert "juggling" in capsys.readouterr().err
