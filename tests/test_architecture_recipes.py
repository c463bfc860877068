"""docs/architecture.md's recipes, followed as written: a toy task (one module with a registered
Task subclass) and a toy variant (one registry entry), both defined in a temporary module outside
the package, run through a smoke study in this process (one worker: spawned workers would not
import the temporary module); and a training metric added where the recipe says, reaching every
seed's run of a study whose seeds train as one pack."""

from __future__ import annotations

import importlib
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest
from mlflow import MlflowClient

from envs.tasks.registry import TASKS
from stm.variants import VARIANTS

pytestmark = pytest.mark.slow

TOY_MODULE = textwrap.dedent('''
    from envs.tasks.registry import register
    from envs.tasks.reacher import Reacher
    from stm.variants import VARIANTS, Variant


    @register
    class ToyReach(Reacher):
        """A short reacher with few demonstrations: the task recipe's example."""

        name = "toy-reach"
        model_task = "toy-reach"

        def __init__(self, n_demos: int = 6, min_steps: int = 12, max_steps: int = 16, **kw):
            super().__init__(n_demos=n_demos, min_steps=min_steps, max_steps=max_steps, **kw)


    VARIANTS["toy-ac-lstm"] = Variant("toy-ac-lstm", "deterministic", True,
                                      "the variant recipe's example: a.c. LSTM with u = 1, v = 3",
                                      train_overrides={"u": 1, "v": 3})
''')


@pytest.fixture
def toy_module(tmp_path, monkeypatch):
    (tmp_path / "toy_recipes.py").write_text(TOY_MODULE)
    monkeypatch.syspath_prepend(str(tmp_path))
    tasks, variants = dict(TASKS), dict(VARIANTS)
    sys.modules.pop("toy_recipes", None)
    yield importlib.import_module("toy_recipes")
    sys.modules.pop("toy_recipes", None)
    for registry, before in ((TASKS, tasks), (VARIANTS, variants)):  # the registries as they were
        registry.clear()
        registry.update(before)


def test_a_toy_task_and_a_toy_variant_run_through_a_smoke_study(toy_module, monkeypatch):
    from experiments.cli import main

    assert "toy-reach" in TASKS and "toy-ac-lstm" in VARIANTS
    # the test's own working directory (tests/conftest.py), as an absolute URI: MLflow caches a store per URI
    # string, and a relative one would reach this folder's database from every later test in this process
    uri = f"sqlite:///{Path.cwd() / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    code = main(["ablation", "--profile", "smoke", "--tasks", "toy-reach", "--variants", "lstm", "toy-ac-lstm",
                 "--workers", "1", "--set", "eval.rollouts=2", "--set", "eval.figures=0"])
    assert code == 0

    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("ablation")
    runs = client.search_runs([exp.experiment_id])
    cells = {r.data.tags.get("variant"): r for r in runs if "mlflow.parentRunId" in r.data.tags}
    assert set(cells) == {"lstm", "toy-ac-lstm"}
    for run in cells.values():
        assert run.info.status == "FINISHED"
        assert run.data.params["task"] == "toy-reach"
        assert run.data.metrics["toy-reach/n_rollouts"] == 2
        assert 0.0 <= run.data.metrics["toy-reach/success_rate"] <= 1.0
    # the toy variant's overrides reached its training config; lstm trains teacher-forced (v = 0)
    assert (cells["toy-ac-lstm"].data.params["train.u"], cells["toy-ac-lstm"].data.params["train.v"]) == ("1", "3")
    assert cells["lstm"].data.params["train.v"] == "0"


def test_a_training_metric_reaches_every_seed_of_a_packed_study(monkeypatch):
    """"Add a metric", step 2: a metric added to what the training loop reports
    (stm.training.loop.training_metrics) is in every cell's run of a study of two seeds, which train together as one
    pack; and the training time is logged once per run."""
    import stm.training.loop
    from experiments.cli import main

    reported, packs = stm.training.loop.training_metrics, []
    train_packed = stm.training.loop.train_packed

    def with_toy_metric(history, log_every, seconds):
        return {**reported(history, log_every, seconds), "train/toy_last_loss": history["train/loss"][-1]}

    def recording(model_cfg, train_cfgs, *args, **kwargs):
        packs.append(len(train_cfgs))
        return train_packed(model_cfg, train_cfgs, *args, **kwargs)

    monkeypatch.setattr(stm.training.loop, "training_metrics", with_toy_metric)
    monkeypatch.setattr(stm.training.loop, "train_packed", recording)
    uri = f"sqlite:///{Path.cwd() / 'mlflow.db'}"  # absolute, as in the test above
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    code = main(["ablation", "--profile", "smoke", "--variants", "ac-lstm-mdn", "--seeds", "2", "--workers", "1",
                 "--set", "eval.rollouts=2", "--set", "eval.figures=0"])
    assert code == 0 and packs == [2]

    client = MlflowClient(uri)
    runs = client.search_runs([client.get_experiment_by_name("ablation").experiment_id])
    cells = [r for r in runs if "mlflow.parentRunId" in r.data.tags]
    assert sorted(r.data.tags["seed"] for r in cells) == ["0", "1"]
    for run in cells:
        toy = client.get_metric_history(run.info.run_id, "train/toy_last_loss")
        assert [m.step for m in toy] == [5, 10] and all(np.isfinite(m.value) for m in toy)
        assert len(client.get_metric_history(run.info.run_id, "time/train_seconds")) == 1
