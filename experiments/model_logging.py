"""A cell's trained STM as an MLflow model named "model" on its run, so that
`mlflow.pytorch.load_model(f"runs:/{run_id}/model")` returns the torch module (stm.model.STM)
that stm.rollout.generate unrolls (README, "Use a trained model").

Saved as a pickle, not as torch.export's pt2 (MLflow's default): an exported program keeps
forward() only, and a rollout also calls normalize, predict and denormalize. The pickle names
the STM class by its import path, so loading needs this project installed; the requirements
pin it and its dependencies at the versions that trained the model. The resume checkpoint
(experiments/cell_run.py) is a separate artifact and stays the one that training resumes from.
"""

from __future__ import annotations

import logging
import os
from contextlib import contextmanager
from importlib import metadata

import numpy as np
from mlflow.entities import LoggedModelStatus

from experiments.runtime.backend_internals import pinned_tracking_uri
from experiments.runtime.tracking import with_retries

log = logging.getLogger(__name__)

TRACKING_URI_ENV = "MLFLOW_TRACKING_URI"

MODEL_NAME = "model"
# what a loaded model needs to import and run (the project and what stm/ and envs/ import)
REQUIREMENTS = ("acrmdn", "torch", "numpy", "pybullet", "pytorch-kinematics", "mlflow")


def pinned_requirements() -> list[str]:
    """`name==version` of each requirement as installed here; a package missing from this
    environment is listed unpinned."""
    out = []
    for name in REQUIREMENTS:
        try:
            out.append(f"{name}=={metadata.version(name)}")
        except metadata.PackageNotFoundError:
            out.append(name)
    return out


def _run_models(client, run) -> list:
    return list(client.search_logged_models(
        experiment_ids=[run.info.experiment_id],
        filter_string=f"source_run_id = '{run.info.run_id}' AND name = '{MODEL_NAME}'"))


def logged_model_id(client, run_id: str) -> str | None:
    """The id of the run's READY model named MODEL_NAME, if one was logged (a resumed cell keeps it)."""
    found = _run_models(client, client.get_run(run_id))
    return next((m.model_id for m in found if m.status == LoggedModelStatus.READY), None)


def example_input(model) -> np.ndarray:
    """A (1, 2, D) batch of normalised states: the mean state twice (what forward() takes)."""
    return np.zeros((1, 2, model.dim), dtype=np.float32)


def log_stm(model, client, run_id: str) -> str:
    """Log `model` (a trained stm.model.STM) as the run's MLflow model; returns its model id.
    Does nothing where the run has one already (a resumed cell retrains to the same weights)."""
    import mlflow
    import torch
    from mlflow.models import infer_signature

    run = client.get_run(run_id)
    found = _run_models(client, run)
    for m in found:
        if m.status == LoggedModelStatus.READY:
            log.info("run %s already has its MLflow model %s", run_id, m.model_id)
            return m.model_id
    for m in found:  # left PENDING or FAILED by a killed attempt: runs:/.../model must not find it
        client.delete_logged_model(m.model_id)
    model = model.cpu().eval()
    x = example_input(model)
    with torch.no_grad():
        raw, _ = model(torch.from_numpy(x))
    signature = infer_signature(x, raw.numpy())
    # created here in the run's experiment: log_model alone would put it in the fluent API's
    # current experiment (the default one) with its artifacts under the working directory
    note = (f"Trained STM of run `{run.info.run_name}`. Load it with "
            f"`mlflow.pytorch.load_model(\"runs:/{run_id}/{MODEL_NAME}\")` where this project is installed; "
            "roll it out with `stm.rollout.generate` (README: Use a trained model).")
    created = client.create_logged_model(run.info.experiment_id, name=MODEL_NAME, source_run_id=run_id,
                                         params=dict(run.data.params), model_type="stm",
                                         tags={"mlflow.note.content": note})
    with _fluent_tracking_uri(client.tracking_uri), _quiet(("mlflow.pytorch", "mlflow.models.model")):
        # MLflow's own client inside log_model: retried like ours on SQLite lock contention
        info = with_retries(mlflow.pytorch.log_model)(
            model, name=MODEL_NAME, model_id=created.model_id, run_id=run_id, signature=signature,
            input_example=x, pip_requirements=pinned_requirements(), serialization_format="pickle",
            metadata={"class": f"{type(model).__module__}.{type(model).__qualname__}",
                      "forward": "normalised states (B, T, D) -> head outputs (B, T, out), (h, c)",
                      "rollout": "stm.rollout.generate(model, task, episodes)",
                      "git_commit": run.data.params.get("git_commit", "")})  # the acrmdn code it needs
    return info.model_id


@contextmanager
def _fluent_tracking_uri(uri: str):
    """log_model reaches the store through the fluent API's process-wide URI: set it for the call,
    then put back what was there before: the global as it was (unset unless someone had pinned it;
    restoring the *resolved* URI would pin it) and MLFLOW_TRACKING_URI, which set_tracking_uri
    also writes (later in-process code and subprocesses read it)."""
    import mlflow

    pinned, env = pinned_tracking_uri(), os.environ.get(TRACKING_URI_ENV)
    mlflow.set_tracking_uri(uri)
    try:
        yield
    finally:
        mlflow.set_tracking_uri(pinned)  # None: unset, back to the environment variable or the default
        if env is None:
            os.environ.pop(TRACKING_URI_ENV, None)
        else:
            os.environ[TRACKING_URI_ENV] = env


@contextmanager
def _quiet(loggers: tuple[str, ...]):
    """Two warnings MLflow prints for every such model and that are expected here: pickle is
    chosen on purpose (see the module docstring), and its check of the input example as a
    REST serving request fails because forward() returns (head outputs, (h, c)), which
    MLflow's generic pyfunc server does not take (the model is for rollouts in Python)."""
    saved = [(logging.getLogger(n), logging.getLogger(n).level) for n in loggers]
    for lg, _ in saved:
        lg.setLevel(logging.ERROR)
    try:
        yield
    finally:
        for lg, level in saved:
            lg.setLevel(level)
