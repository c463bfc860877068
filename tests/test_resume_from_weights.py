"""`ablation --resume-from-weights`: a cell whose run has no resume checkpoint but kept weights (an imported export
with models, weights_at/<N>/weights.pt) resumes at N with a fresh optimiser and random streams seeded from (seed, N),
tagged so; without the flag it trains from scratch with a warning naming the flag; a real checkpoint wins. The
checkpoint made of a weights file loads through the ordinary resume path, and resuming from it twice gives the same
model bit for bit."""

from __future__ import annotations

import logging
import signal

import pytest
import torch
from cli_helpers import kill_at_checkpoints, run_in_process
from mlflow.tracking import MlflowClient
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from experiments.weights_resume import RESUMED_TAG, checkpoint_from_weights
from stm.config import ModelConfig, TrainConfig
from stm.training.checkpoint import check_resumable, load_checkpoint, save_checkpoint
from stm.training.loop import train
from stm.training.weights import weights_bytes

STUDY = "halfway"
# one LSTM cell of 20 iterations, its checkpoint at 10 kept (and its first one: the study is killed there)
ARGS = ["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "1", "--workers", "1", "--study-name", STUDY,
        "--set", "train.iters=20", "--set", "train.checkpoint_every=10", "--set", "keep_checkpoints=10",
        "--set", "train.val_every=0", "--set", "train.step_kernel=python", "--set", "eval.figures=0",
        "--set", "eval.rollouts=2"]
TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)


def _uri(store) -> str:  # absolute: MLflow keeps one engine per URI in a process, whatever the working directory
    return f"sqlite:///{store / 'mlflow.db'}"


def _client(store) -> MlflowClient:
    return MlflowClient(_uri(store))


def _cell(store):
    client = _client(store)
    [run] = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'cell'")
    return client, run


@pytest.fixture(scope="module")
def exports(tmp_path_factory):
    """The study killed at its checkpoint at 10 of 20, exported with its models (weights at 10, no checkpoint) and as
    a snapshot (its resume checkpoint too)."""
    here = tmp_path_factory.mktemp("here")
    marks, code = kill_at_checkpoints(ARGS, here, 1, here / "killed.log")
    assert [it for _, it in marks] == [10] and code == -signal.SIGKILL
    out = tmp_path_factory.mktemp("exports")
    for kind, flags in (("models", ["--with-models", "--models-at", "10"]), ("snapshot", ["--with-checkpoints"])):
        code, err = run_in_process("reports", ["export", "--study", STUDY, "--tracking-uri", _uri(here), "--out",
                                               str(out / kind), *flags], here)
        assert code == 0, err[-3000:]
    assert not list((out / "models").rglob("checkpoint/model.pt"))
    return out


def _study(store, *flags: str) -> str:
    """The study command run in `store` in this process (a subprocess would import torch and MLflow again): its
    stderr with the log lines."""
    with pytest.MonkeyPatch.context() as env:
        env.setenv("MLFLOW_TRACKING_URI", _uri(store))
        code, err = run_in_process("experiments", [*ARGS, *flags], store, log_level=logging.INFO)
    assert code == 0, err[-3000:]
    return err


def _imported(exports, kind: str, store):
    store.mkdir()
    code, err = run_in_process("reports", ["import", str(exports / kind / STUDY), "--tracking-uri", _uri(store)], store)
    assert code == 0, err[-3000:]
    return store


@pytest.mark.slow
def test_an_imported_export_with_models_resumes_from_its_kept_weights(exports, tmp_path):
    store = _imported(exports, "models", tmp_path / "there")
    err = _study(store, "--resume-from-weights")
    assert "resumes from its kept weights at iteration 10" in err and "(from 10)" in err
    client, run = _cell(store)  # the imported run, resumed: no new one
    assert run.info.status == "FINISHED" and run.data.tags[RESUMED_TAG] == "10 (fresh optimiser and random streams)"
    assert "resumed_from_iteration" not in run.data.tags
    steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
    assert steps == [5, 10, 15, 20]  # the imported ones, then the resumed run's from after 10
    seconds = {m.step: m.value for m in client.get_metric_history(run.info.run_id, "train/seconds")}
    assert seconds[15] > seconds[10]  # its clock goes on from the seconds logged at 10
    assert run.data.metrics["train/iterations"] == 20


@pytest.mark.slow
def test_without_the_flag_the_cell_trains_from_scratch_and_names_the_flag(exports, tmp_path):
    store = _imported(exports, "models", tmp_path / "there")
    err = _study(store)
    assert "no resume checkpoint, models kept at 10; --resume-from-weights resumes from 10 with a fresh " \
           "optimiser" in err and "(from 0)" in err
    _, run = _cell(store)
    assert run.info.status == "FINISHED" and RESUMED_TAG not in run.data.tags


@pytest.mark.slow
def test_a_resume_checkpoint_wins_over_the_flag(exports, tmp_path):
    store = _imported(exports, "snapshot", tmp_path / "there")
    err = _study(store, "--resume-from-weights")
    assert "resumes from its checkpoint at iteration 10" in err and "kept weights" not in err
    _, run = _cell(store)
    assert run.data.tags["resumed_from_iteration"] == "10" and RESUMED_TAG not in run.data.tags


@pytest.fixture(scope="module")
def toy_weights(tmp_path_factory):
    """A tiny model trained 3 iterations, as its weights file."""
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    folder = tmp_path_factory.mktemp("weights")
    cfg = TrainConfig(iters=3, batch_size=2, u=1, v=1, phi_mode="free", step_kernel="python")  # no C++ build
    train(TINY, cfg, task, task.demos(0), checkpoint_path=folder / "model.pt")
    (folder / "weights.pt").write_bytes(weights_bytes(load_checkpoint(folder / "model.pt")))
    return task, cfg, folder / "weights.pt"


def test_a_checkpoint_made_of_weights_resumes_deterministically(toy_weights, tmp_path):
    task, cfg, weights_file = toy_weights
    weights = load_checkpoint(weights_file)
    longer = TrainConfig(**{**cfg.to_dict(), "iters": 6})
    models = []
    for k in range(2):  # the same weights resumed twice: the same model
        path = tmp_path / str(k) / "model.pt"
        path.parent.mkdir()
        save_checkpoint(checkpoint_from_weights(weights, longer.lr, longer.seed), path)
        result = train(TINY, longer, task, task.demos(0), checkpoint_path=path)
        assert result.iterations == 6 and len(result.history["train/loss"]) == 3  # from 3 on, no history before
        models.append(result.model.state_dict())
    assert all(torch.equal(models[0][k], models[1][k]) for k in models[0])
    assert not all(torch.equal(models[0][k], weights["model"][k]) for k in models[0])  # it did train on

    payload = checkpoint_from_weights(weights, cfg.lr, cfg.seed)
    assert payload["optimizer"]["state"] == {} and payload["iteration"] == 3 and payload["seconds"] == 0.0
    other_seed = checkpoint_from_weights(weights, cfg.lr, cfg.seed + 1)
    assert not torch.equal(payload["rng"]["batch"], other_seed["rng"]["batch"])
    with pytest.raises(ValueError, match="another model config"):  # weights of another cell's model: refused
        check_resumable(payload, ModelConfig(hidden_size=16, num_layers=2, mixtures=2), cfg, task, weights_file)


def test_a_fresh_adam_state_loads_as_the_initial_one(toy_weights):
    from stm.packed import PackedAdam

    _, cfg, weights_file = toy_weights
    payload = checkpoint_from_weights(load_checkpoint(weights_file), cfg.lr, cfg.seed)
    params = [torch.zeros(2, 3), torch.zeros(2, 4)]
    opt = PackedAdam(params, [cfg.lr, cfg.lr])
    opt.exp_avg[0][1], opt.steps[1] = 1.0, 5.0  # slot 1 as a previous run left it
    opt.load_model_state(1, payload["optimizer"])
    assert opt.steps[1] == 0 and not opt.exp_avg[0][1].any() and opt.lr[1] == cfg.lr
