"""A cell's trained STM as an MLflow model: logged once per run into the run's experiment,
loadable by mlflow.pytorch.load_model as the trained module, and docs/usage.md's "Use a trained
model" snippet run as written against a smoke study's store."""

from __future__ import annotations

import os
import re
import subprocess
import sys
import textwrap
from importlib import metadata
from pathlib import Path

import mlflow
import numpy as np
import pytest
import torch
import yaml
from mlflow.tracking import MlflowClient

from envs.tasks import get_task
from experiments.model_logging import MODEL_NAME, log_stm, logged_model_id, pinned_requirements
from stm.config import ModelConfig
from stm.model import STM

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture()
def store_run(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    exp = client.create_experiment("ablation", artifact_location=(tmp_path / "mlartifacts").as_uri())
    run = client.create_run(exp, tags={"task": "reacher"})
    client.log_param(run.info.run_id, "seed", "3")
    return client, run.info.run_id, exp


def _tiny_stm() -> STM:
    torch.manual_seed(0)
    task = get_task("reacher")
    return STM(ModelConfig.from_dict({"hidden_size": 8, "num_layers": 1, "head": "mdn", "mixtures": 2}), task.layout)


@pytest.mark.slow
def test_model_is_logged_once_into_the_runs_experiment(store_run, monkeypatch):
    client, run_id, exp = store_run
    model = _tiny_stm()
    before = mlflow.get_tracking_uri()  # the working directory's default store: not the client's
    first = log_stm(model, client, run_id)
    # the fluent API's URI is left as it was: not pinned to the client's store, nor to the resolved default
    assert mlflow.get_tracking_uri() == before != client.tracking_uri
    assert "MLFLOW_TRACKING_URI" not in os.environ
    monkeypatch.chdir(client.tracking_uri.removeprefix("sqlite:///").rsplit("/", 1)[0])
    assert mlflow.get_tracking_uri() != before  # still resolved per call (the default is relative)
    assert log_stm(model, client, run_id) == first  # a resumed cell does not log a second model
    models = client.search_logged_models([exp])
    assert [(m.model_id, m.name, m.source_run_id) for m in models] == [(first, MODEL_NAME, run_id)]
    assert logged_model_id(client, run_id) == first
    assert models[0].params["seed"] == "3"  # the run's params travel with the model
    outputs = client.get_run(run_id).outputs.model_outputs
    assert [o.model_id for o in outputs] == [first]

    monkeypatch.setenv("MLFLOW_TRACKING_URI", client.tracking_uri)  # the fluent API's, for this test only
    loaded = mlflow.pytorch.load_model(f"runs:/{run_id}/{MODEL_NAME}")
    local = Path(mlflow.artifacts.download_artifacts(f"models:/{first}"))
    assert type(loaded) is STM
    for name, value in model.state_dict().items():
        assert torch.equal(loaded.state_dict()[name], value), name

    mlmodel = yaml.safe_load((local / "MLmodel").read_text())
    inputs = yaml.safe_load(mlmodel["signature"]["inputs"])
    assert inputs[0]["tensor-spec"]["shape"][-1] == model.dim
    assert (local / "input_example.json").exists()
    requirements = (local / "requirements.txt").read_text().split()
    assert f"torch=={metadata.version('torch')}" in requirements
    assert any(r.startswith("acrmdn") for r in requirements)


@pytest.mark.slow
def test_a_model_left_unfinished_by_a_killed_attempt_is_replaced(store_run):
    client, run_id, exp = store_run
    stale = client.create_logged_model(exp, name=MODEL_NAME, source_run_id=run_id)  # PENDING, no artifacts
    assert logged_model_id(client, run_id) is None
    new = log_stm(_tiny_stm(), client, run_id)
    assert new != stale.model_id
    assert [m.model_id for m in client.search_logged_models([exp])] == [new]


def test_requirements_are_pinned_to_this_environment():
    pins = dict(r.split("==") for r in pinned_requirements())
    assert pins["torch"] == metadata.version("torch") and pins["mlflow"] == mlflow.__version__


def _usage_snippet() -> str:
    """The snippet of docs/usage.md, "Use a trained model"."""
    text = (REPO / "docs" / "usage.md").read_text()
    section = text.split("## Use a trained model", 1)[1].split("\n## ", 1)[0]
    return re.search(r"```python\n(.*?)```", section, re.S).group(1)


@pytest.mark.slow
def test_usage_snippet_rolls_out_a_trained_cell(smoke_store, tmp_path):
    """On the session's smoke ablation (conftest.py): the snippet reads ./mlflow.db of the folder it runs in."""
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("MLFLOW_TRACKING_URI", None)
    client = MlflowClient(smoke_store.uri)
    (cell,) = client.search_runs([client.get_experiment_by_name("ablation").experiment_id],
                                 "tags.task = 'reacher' and tags.variant = 'ac-lstm-mdn'")
    ckpt = torch.load(client.download_artifacts(cell.info.run_id, "checkpoint/model.pt", str(tmp_path)),
                      weights_only=False)

    # the snippet as a user runs it: a fresh interpreter in the folder that holds mlflow.db; what it made is
    # saved for the checks below
    script = _usage_snippet() + textwrap.dedent("""
        import torch
        torch.save({"run_id": run.info.run_id, "model_type": type(model).__name__, "is_mdn": model.is_mdn,
                    "state": model.state_dict(), "q": rollout.q, "q0": q0, "metrics": metrics,
                    "max_steps": task.max_steps}, SNIPPET_OUT)
    """).replace("SNIPPET_OUT", repr(str(tmp_path / "snippet_out.pt")))
    (tmp_path / "snippet.py").write_text(script)
    ran = subprocess.run([sys.executable, str(tmp_path / "snippet.py")], cwd=smoke_store.path, env=env,
                         capture_output=True, text=True, timeout=600)
    assert ran.returncode == 0, ran.stderr[-3000:]
    assert "final distance" in ran.stdout
    out = torch.load(tmp_path / "snippet_out.pt", weights_only=False)
    assert out["run_id"] == cell.info.run_id
    assert out["model_type"] == STM.__name__ and out["is_mdn"]
    for name, value in ckpt["model"].items():  # the logged model is the trained one
        assert torch.equal(out["state"][name], value), name
    metrics = out["metrics"]
    assert out["q"].shape == (1, out["max_steps"] + 1, 7)
    assert np.allclose(out["q"][0, 0], out["q0"])
    assert set(metrics) >= {"success", "final_distance"} and metrics["final_distance"] > 0
