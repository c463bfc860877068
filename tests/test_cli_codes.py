"""The experiments CLI's exit codes that other tests do not reach: 1 when a cell fails (with the
failure in the summary), and 2 with one line for a bad `--queue` (before anything is written)."""

from __future__ import annotations

import pytest
from cli_helpers import run_cli
from mlflow.tracking import MlflowClient


@pytest.mark.slow
def test_ablation_with_a_failing_cell_exits_with_code_1(tmp_path):
    proc = run_cli(["ablation", "--profile", "smoke", "--variants", "lstm", "--workers", "1", "--study-name", "bad",
                    "--set", "train.lr=1e30", "--set", "eval.figures=0"], tmp_path)  # the loss overflows at once
    assert proc.returncode == 1, proc.stdout + proc.stderr[-3000:]
    assert "0 cell(s) run" not in proc.stdout and "1 failed" in proc.stdout
    assert "FAILED cells:" in proc.stdout and "TrainingDiverged" in proc.stdout
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.get_experiment_by_name("ablation")
    (cell,) = client.search_runs([exp.experiment_id], "tags.role = 'cell'")
    assert cell.info.status == "FAILED" and "non-finite loss" in cell.data.tags["error"]
    (parent,) = client.search_runs([exp.experiment_id], "tags.role = 'parent'")
    assert parent.info.status == "FAILED" and parent.data.tags["failed_cells"] == "1"


@pytest.mark.parametrize("queue,uri,message", [
    ("http://127.0.0.1:1/queue", None, "--queue: unsupported URL 'http://127.0.0.1:1/queue'"),
    ("mysql://db/queue", None, "--queue: unsupported URL 'mysql://db/queue'"),
    (None, "http://127.0.0.1:1", "--queue: required when MLFLOW_TRACKING_URI is not a local sqlite store"),
])
def test_bad_queue_is_one_line_and_exit_code_2(tmp_path, queue, uri, message, monkeypatch, capsys):
    """In this process: the command line's start-up is the failing-cell test's (exit codes come from main)."""
    from experiments.cli import main

    args = ["ablation", "--profile", "smoke", "--worker"] + (["--queue", queue] if queue else [])
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri or f"sqlite:///{tmp_path / 'mlflow.db'}")
    assert main(args) == 2
    stderr = capsys.readouterr().err
    errors = [line for line in stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and errors[0].startswith(f"error: {message}"), stderr
    assert "Traceback" not in stderr and not list(tmp_path.iterdir())  # nothing written


def test_default_queue_lies_next_to_a_local_store(tmp_path):
    from experiments.runtime.cell_queue import resolve_queue
    from experiments.study_config import ConfigError

    assert resolve_queue(None, f"sqlite:///{tmp_path / 'mlflow.db'}") == f"sqlite:///{tmp_path / 'queue.db'}"
    assert resolve_queue("postgresql://h/q") == "postgresql://h/q"
    with pytest.raises(ConfigError, match="required when MLFLOW_TRACKING_URI"):
        resolve_queue(None, "http://tracking:5000")


@pytest.mark.parametrize("value", ["0", "two", "-1"])
def test_bad_workers_variable_is_one_line_and_exit_code_2(tmp_path, value, monkeypatch, capsys):
    from experiments.cli import main

    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("ACRMDN_WORKERS", value)
    assert main(["ablation", "--profile", "smoke"]) == 2
    stderr = capsys.readouterr().err
    assert stderr.strip() == f"error: ACRMDN_WORKERS={value!r}: expected a whole number of worker processes >= 1"
    assert not list(tmp_path.iterdir())  # nothing written


def test_workers_variable_sets_the_default_and_the_flag_wins(monkeypatch):
    import os

    from experiments.cli import build_parser, load_config
    from experiments.runtime.processes import default_workers

    monkeypatch.setenv("ACRMDN_WORKERS", "3")
    assert default_workers() == 3
    monkeypatch.setenv("ACRMDN_WORKERS", "two")  # not read when --workers is given
    assert load_config(build_parser().parse_args(["ablation", "--profile", "smoke", "--workers", "1"])).workers == 1
    monkeypatch.delenv("ACRMDN_WORKERS")
    assert default_workers() == len(os.sched_getaffinity(0))


@pytest.mark.parametrize("args,message", [
    (["ablation", "--device", "tpu"], "--device: unknown device 'tpu'; allowed: auto, cpu, cuda or cuda:N"),
    (["ablation", "--device", "cuda"], "--device: device 'cuda': torch sees no CUDA GPU here"),
    (["sweep", "--device", "cuda:7"], "--device: device 'cuda:7': torch sees no CUDA GPU here"),
    (["ablation", "--set", "device=tpu"], "device: unknown device 'tpu'; allowed: auto, cpu, cuda or cuda:N"),
    (["milestones", "--study", "s", "--device", "tpu"], "--device: unknown device 'tpu'"),
])
def test_bad_device_is_one_line_and_exit_code_2(tmp_path, args, message, monkeypatch, capsys):
    import torch

    from experiments.cli import main

    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)  # as on a machine without a GPU
    monkeypatch.chdir(tmp_path)
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    assert main(args + (["--profile", "smoke"] if args[0] != "milestones" else [])) == 2
    stderr = capsys.readouterr().err
    errors = [line for line in stderr.splitlines() if "error" in line.lower()]
    assert len(errors) == 1 and message in errors[0], stderr
    assert "Traceback" not in stderr and not list(tmp_path.iterdir())  # nothing written


def test_device_reaches_the_cells_and_is_no_part_of_their_hash():
    from experiments.cells import build_cells
    from experiments.study_config import load_profile

    cpu, auto = (load_profile("smoke", device=d) for d in (None, "auto"))
    assert cpu.device == "cpu" and auto.device == "auto"
    assert cpu.study_hash() == auto.study_hash() and cpu.resolved_study_name() == auto.resolved_study_name()
    cells = build_cells(auto)
    assert {c.device for c in cells} == {"auto"}
    assert [c.config_hash for c in cells] == [c.config_hash for c in build_cells(cpu)]
    bf16 = load_profile("smoke", ["train.matmul_dtype=bfloat16"])
    assert {c.train.matmul_dtype for c in build_cells(bf16)} == {"bfloat16"}
    assert bf16.study_hash() != cpu.study_hash()  # it changes results: another study


def test_cell_params_record_the_device_and_the_product_dtype():
    from experiments.cell_run import cell_params
    from experiments.cells import build_cells
    from experiments.study_config import load_profile

    params = cell_params(build_cells(load_profile("smoke", device="auto"))[0])
    assert params["device"] in ("cpu", "cuda") and params["train.matmul_dtype"] == "float32"
