"""`ablation --pack K`: a cell group's seeds trained as one packed job (experiments/pack.py).
Packed and unpacked studies log the same child runs (params, metric keys and artifact names;
the losses agree to the packed trainer's tolerance); a packed job killed with SIGKILL resumes
every seed from its own checkpoint artifact; a seed whose loss goes non-finite is FAILED with
its reason while the other seed of the pack finishes."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from mlflow.tracking import MlflowClient

REPO = Path(__file__).resolve().parents[1]
pytestmark = pytest.mark.slow
SMALL = ["--set", "eval.rollouts=2", "--set", "eval.figures=1"]


def _env(store: Path) -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO), "MLFLOW_TRACKING_URI": f"sqlite:///{store / 'mlflow.db'}"}


def _cli(args: list[str], store: Path, timeout: int = 400) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "experiments", *args], cwd=store, env=_env(store),
                          capture_output=True, text=True, timeout=timeout)


def _cells(client: MlflowClient) -> dict[str, object]:
    runs = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'cell'")
    return {r.data.tags["seed"]: r for r in runs}


def _artifacts(client: MlflowClient, run_id: str) -> set[str]:
    return {f.path for d in ("checkpoint", "config", "figures", "rollouts") for f in client.list_artifacts(run_id, d)}


def _claimless(params: dict[str, str]) -> dict[str, str]:
    return {k: v for k, v in params.items() if not k.startswith("claim.")}


def test_packed_study_logs_the_same_runs_as_an_unpacked_one(tmp_path):
    stores = {}
    for pack in ("1", "2"):
        store = tmp_path / f"pack{pack}"
        store.mkdir()
        proc = _cli(["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2", "--workers", "1",
                     "--pack", pack, *SMALL], store)
        assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
        assert ("in 1 job(s)" if pack == "2" else "in 2 job(s)") in proc.stderr
        stores[pack] = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    alone, packed = _cells(stores["1"]), _cells(stores["2"])
    assert sorted(alone) == sorted(packed) == ["0", "1"]
    for seed in alone:
        a, p = alone[seed], packed[seed]
        assert p.info.status == "FINISHED"
        assert _claimless(p.data.params) == _claimless(a.data.params)  # hashes, configs, provenance
        assert p.data.tags["config_hash"] == a.data.tags["config_hash"]
        assert set(p.data.metrics) == set(a.data.metrics)
        assert _artifacts(stores["2"], p.info.run_id) == _artifacts(stores["1"], a.info.run_id)
        losses = [[m.value for m in c.get_metric_history(r.info.run_id, "train/loss")]
                  for c, r in ((stores["1"], a), (stores["2"], p))]
        np.testing.assert_allclose(losses[1], losses[0], rtol=1e-4)  # stm's packed equivalence (tests/test_stm_packed)
        assert [m.step for m in stores["2"].get_metric_history(p.info.run_id, "val/metric")] == [5, 10]


def test_killed_packed_job_resumes_every_seed_from_its_checkpoint(tmp_path):
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    args = ["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2", "--pack", "2", "--workers", "1",
            "--study-name", "killed", "--set", "train.iters=1500", "--set", "train.checkpoint_every=50",
            "--set", "train.val_every=0", "--set", "eval.figures=0", "--set", "eval.rollouts=2"]
    proc = subprocess.Popen([sys.executable, "-m", "experiments", *args], cwd=tmp_path, env=_env(tmp_path),
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    killed, deadline = None, time.monotonic() + 300
    try:
        while time.monotonic() < deadline and proc.poll() is None:
            time.sleep(0.3)
            try:
                runs = _cells(client)
            except Exception:  # store not created yet
                continue
            if len(runs) == 2 and all(int(r.data.tags.get("checkpoint_iteration", 0)) >= 50 for r in runs.values()):
                os.killpg(proc.pid, signal.SIGKILL)
                killed = runs
                break
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    assert killed is not None, "training finished or never checkpointed both seeds before the kill"
    at = {seed: int(client.get_run(r.info.run_id).data.tags["checkpoint_iteration"]) for seed, r in killed.items()}
    assert all(client.get_run(r.info.run_id).info.status == "RUNNING" for r in killed.values())
    assert max(at.values()) < 1500

    done = _cli(args, tmp_path)
    assert done.returncode == 0, done.stderr[-3000:]
    for seed, r in killed.items():
        run = client.get_run(r.info.run_id)
        assert run.info.status == "FINISHED"
        assert int(run.data.tags["resumed_from_iteration"]) >= at[seed]
        assert run.data.metrics["train/iterations"] == 1500
        steps = [m.step for m in client.get_metric_history(run.info.run_id, "train/loss")]
        assert steps == sorted(set(steps)) and steps[-1] == 1500  # continued, nothing logged twice
    assert sorted(_cells(client)) == ["0", "1"]  # the same two runs


def test_a_diverging_seed_fails_while_the_other_finishes(tmp_path):
    import dataclasses

    from experiments.cells import build_cells
    from experiments.config import load_profile
    from experiments.pack import run_pack
    from experiments.tracking import Client, get_or_create_experiment

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
