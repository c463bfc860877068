"""`ablation --pack K`: a cell group's seeds trained as one packed job (experiments/pack.py).
Packed and unpacked studies log the same child runs (params, metric keys and artifact names;
the losses agree to the packed trainer's tolerance); a packed job killed with SIGKILL resumes
every seed from its own checkpoint artifact; a seed whose loss goes non-finite is FAILED with
its reason while the other seed of the pack finishes."""

from __future__ import annotations

import signal

import numpy as np
import pytest
from cli_helpers import kill_at_checkpoints, run_cli_in_process
from mlflow.tracking import MlflowClient

SMALL = ["--set", "eval.rollouts=2", "--set", "eval.figures=1"]


def _cells(client: MlflowClient) -> dict[str, object]:
    runs = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'cell'")
    return {r.data.tags["seed"]: r for r in runs}


def _artifacts(client: MlflowClient, run_id: str) -> set[str]:
    return {f.path for d in ("checkpoint", "config", "figures", "rollouts") for f in client.list_artifacts(run_id, d)}


def _claimless(params: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in params.items() if not k.startswith("claim.")}


@pytest.mark.slow
def test_packed_study_logs_the_same_runs_as_an_unpacked_one(tmp_path):
    stores = {}
    for pack in ("1", "2"):
        store = tmp_path / f"pack{pack}"
        store.mkdir()
        keep = ["--set", "keep_checkpoints=5"] if pack == "2" else []  # not hashed: the same cells either way
        proc = run_cli_in_process(["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2",
                                   "--workers", "1", "--pack", pack, *SMALL, *keep], store)
        assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
        assert ("in 1 job(s)" if pack == "2" else "in 2 job(s)") in proc.stderr
        stores[pack] = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    from experiments.model_logging import logged_model_id

    alone, packed = _cells(stores["1"]), _cells(stores["2"])
    assert sorted(alone) == sorted(packed) == ["0", "1"]
    for seed in alone:
        a, p = alone[seed], packed[seed]
        assert p.info.status == "FINISHED"
        assert _claimless(p.data.params) == _claimless(a.data.params)  # hashes, configs, provenance
        assert p.data.tags["config_hash"] == a.data.tags["config_hash"]
        assert set(p.data.metrics) == set(a.data.metrics)
        assert _artifacts(stores["2"], p.info.run_id) == _artifacts(stores["1"], a.info.run_id)
        assert logged_model_id(stores["2"], p.info.run_id) and logged_model_id(stores["1"], a.info.run_id)
        losses = [[m.value for m in c.get_metric_history(r.info.run_id, "train/loss")]
                  for c, r in ((stores["1"], a), (stores["2"], p))]
        np.testing.assert_allclose(losses[1], losses[0], rtol=1e-4)  # stm's packed equivalence (tests/test_stm_packed)
        assert [m.step for m in stores["2"].get_metric_history(p.info.run_id, "val/metric")] == [5, 10]
        kept = {f.path for f in stores["2"].list_artifacts(p.info.run_id, "checkpoint_at")}
        assert kept == {"checkpoint_at/5", "checkpoint_at/10"}  # every 5 of 10 iterations, each seed its own
        assert [f.path for f in stores["2"].list_artifacts(p.info.run_id, "checkpoint_at/5")] == \
            ["checkpoint_at/5/model.pt"]
        assert not stores["1"].list_artifacts(a.info.run_id, "checkpoint_at")


@pytest.mark.slow
def test_killed_packed_job_resumes_every_seed_from_its_checkpoint(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    args = ["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2", "--pack", "2", "--workers", "1",
            "--study-name", "killed", "--set", "train.iters=100", "--set", "train.checkpoint_every=50",
            "--set", "train.val_every=0", "--set", "eval.figures=0", "--set", "eval.rollouts=2"]
    marks, returncode = kill_at_checkpoints(args, tmp_path, 2, tmp_path / "killed.log")
    assert sorted(it for _, it in marks) == [50, 50] and returncode == -signal.SIGKILL
    killed = _cells(client)
    assert sorted(r.info.run_id for r in killed.values()) == sorted(run_id for run_id, _ in marks)
    for r in killed.values():
        assert r.info.status == "RUNNING" and r.data.tags["checkpoint_iteration"] == "50"
        assert [m.step for m in client.get_metric_history(r.info.run_id, "train/loss")] == list(range(5, 51, 5))

    done = run_cli_in_process(args, tmp_path)  # the resume needs no process of its own
    assert done.returncode == 0, done.stderr[-3000:]
    for r in killed.values():
        run = client.get_run(r.info.run_id)
        assert run.info.status == "FINISHED"
        assert run.data.tags["resumed_from_iteration"] == "50" and run.data.metrics["train/iterations"] == 100
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
        assert steps == list(range(5, 101, 5))  # continued, nothing logged twice
    assert sorted(_cells(client)) == ["0", "1"]  # the same two runs


@pytest.mark.slow
def test_a_diverging_seed_fails_while_the_other_finishes(tmp_path):
    import dataclasses

    from experiments.cells import build_cells
    from experiments.pack import run_pack
    from experiments.runtime.tracking import Client, get_or_create_experiment
    from experiments.study_config import load_profile

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    cfg = load_profile("smoke", ["train.val_every=0", "eval.figures=0", "eval.rollouts=2"], variants=["lstm"], seeds=2)
    cells = build_cells(cfg)
    # seed 1 with an absurd learning rate (a per-seed field of a pack): its loss overflows after a step
    cells[1] = dataclasses.replace(cells[1], train=dataclasses.replace(cells[1].train, lr=1e30))
    client = Client(uri)
    exp = get_or_create_experiment(client, "ablation")
    run_ids = [client.create_run(exp).info.run_id for _ in cells]
    results = run_pack([c.to_dict() for c in cells], uri, run_ids)
    assert [r.status for r in results] == ["FINISHED", "FAILED"]
    assert "TrainingDiverged" in results[1].error and "non-finite" in results[1].error
    ok, bad = (client.get_run(run_id) for run_id in run_ids)
    assert ok.info.status == "FINISHED" and ok.data.metrics["train/iterations"] == 10
    assert bad.info.status == "FAILED" and "non-finite" in bad.data.tags["error"]
    assert "reacher/success_rate" not in bad.data.metrics


@pytest.mark.slow
def test_a_queue_worker_trains_a_cell_groups_seeds_as_one_entry(tmp_path):
    import optuna
    from optuna.trial import TrialState

    args = ["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2", "--worker", "--workers", "1",
            "--study-name", "q", "--set", "eval.rollouts=2", "--set", "eval.figures=0"]
    proc = run_cli_in_process(args, tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    assert "2 cell(s) run, 0 skipped" in proc.stdout
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    runs = _cells(client)
    assert sorted(runs) == ["0", "1"] and {r.info.status for r in runs.values()} == {"FINISHED"}
    entries = optuna.load_study(study_name="ablation-cells:q", storage=f"sqlite:///{tmp_path / 'queue.db'}").trials
    assert [t.state for t in entries] == [TrialState.COMPLETE]  # one entry: the pack
    assert sorted(entries[0].user_attrs["config_hashes"]) == sorted(r.data.tags["config_hash"] for r in runs.values())
    assert sorted(entries[0].user_attrs["mlflow_run_ids"]) == sorted(r.info.run_id for r in runs.values())
    again = run_cli_in_process(args, tmp_path)
    assert again.returncode == 0 and "0 cell(s) run, 2 skipped" in again.stdout


def test_pack_is_a_typed_option_outside_every_hash():
    from experiments.cells import build_cells
    from experiments.cli import build_parser, load_config
    from experiments.pack import pack_units
    from experiments.study_config import ConfigError, load_profile

    base = load_profile("smoke", seeds=3)
    packed = load_config(build_parser().parse_args(["ablation", "--profile", "smoke", "--seeds", "3", "--pack", "2"]))
    assert (base.pack, packed.pack) == (0, 2)
    assert packed.study_hash() == base.study_hash() and packed.resolved_study_name() == base.resolved_study_name()
    assert [c.config_hash for c in build_cells(packed)] == [c.config_hash for c in build_cells(base)]
    with pytest.raises(ConfigError, match="pack"):
        load_profile("smoke", pack=-1)
    todo = [(c, str(i)) for i, c in enumerate(build_cells(packed))]  # 2 variants x 3 seeds
    assert [[c.key for c, _ in u] for u in pack_units(todo, 2)] == [
        ["reacher/lstm/seed0", "reacher/lstm/seed1"], ["reacher/lstm/seed2"],
        ["reacher/ac-lstm-mdn/seed0", "reacher/ac-lstm-mdn/seed1"], ["reacher/ac-lstm-mdn/seed2"]]
    assert [len(u) for u in pack_units(todo, 0)] == [3, 3] and [len(u) for u in pack_units(todo, 1)] == [1] * 6
    # no pack size asked for: packs halved while a worker process would idle; an explicit --pack is kept
    assert [len(u) for u in pack_units(todo, 0, workers=2)] == [3, 3]
    assert [len(u) for u in pack_units(todo, 0, workers=3)] == [2, 1, 3]
    assert [len(u) for u in pack_units(todo, 0, workers=4)] == [2, 1, 2, 1]
    assert [len(u) for u in pack_units(todo, 0, workers=9)] == [1] * 6
    assert [len(u) for u in pack_units(todo, 3, workers=4)] == [3, 3]
    assert sorted(c.key for u in pack_units(todo, 0, workers=4) for c, _ in u) == sorted(c.key for c, _ in todo)
