"""A study moved between machines: `reports export --with-checkpoints` writes a snapshot (an export with each
unfinished cell's resume checkpoint and every kept checkpoint's weights), `reports import` reads it into a store in
another folder, and the same study command there resumes every cell where it stopped, to the same models and numbers
as a study that was never stopped; a snapshot of that store carries the imported models on."""

from __future__ import annotations

import signal

import pytest
import torch
from cli_helpers import kill_at_checkpoints, run_cli, run_cli_in_process
from mlflow.tracking import MlflowClient

pytestmark = pytest.mark.slow

# an auto-conditioned MDN pack of two seeds (the campaign's kind of cell), 2N = 100 iterations, stopped at N = 50
ARGS = ["ablation", "--profile", "smoke", "--variants", "ac-lstm-mdn", "--seeds", "2", "--pack", "2", "--workers",
        "1", "--study-name", "moved", "--set", "train.iters=100", "--set", "train.checkpoint_every=50",
        "--set", "keep_checkpoints=50", "--set", "train.val_every=0", "--set", "eval.figures=0",
        "--set", "eval.rollouts=2"]


def _client(store) -> MlflowClient:
    return MlflowClient(f"sqlite:///{store / 'mlflow.db'}")


def _cells(client: MlflowClient) -> dict[str, object]:
    runs = client.search_runs([client.get_experiment_by_name("ablation").experiment_id], "tags.role = 'cell'")
    return {r.data.tags["seed"]: r for r in runs}


def _weights(client: MlflowClient, run_id: str, tmp) -> dict[str, torch.Tensor]:
    from stm.training.checkpoint import load_checkpoint

    return load_checkpoint(client.download_artifacts(run_id, "checkpoint_at/100/model.pt", str(tmp)))["model"]


def test_a_snapshot_imported_elsewhere_resumes_to_the_uninterrupted_models(tmp_path):
    here, there, straight = (tmp_path / d for d in ("here", "there", "straight"))
    for d in (here, there, straight):
        d.mkdir()
    marks, code = kill_at_checkpoints(ARGS, here, 2, tmp_path / "killed.log")
    assert sorted(it for _, it in marks) == [50, 50] and code == -signal.SIGKILL

    snap = run_cli_in_process(["export", "--study", "moved", "--with-checkpoints", "--out", str(tmp_path / "snap")],
                              here, module="reports")
    assert snap.returncode == 0, snap.stderr[-3000:]
    files = {p.relative_to(tmp_path / "snap" / "moved").as_posix().split("/", 2)[-1]
             for p in (tmp_path / "snap" / "moved").rglob("*.pt")}
    # per seed: where it stands, and the checkpoint it kept as its weights alone
    assert files == {"checkpoint/model.pt", "weights_at/50/weights.pt"}
    refused = run_cli(["export", "--study", "moved", "--with-checkpoints", "--out", "reports/studies"], here,
                      module="reports")
    assert refused.returncode == 2 and "stays out of reports/studies" in refused.stderr

    imported = run_cli_in_process(["import", str(tmp_path / "snap" / "moved")], there, module="reports")
    assert imported.returncode == 0, imported.stderr[-3000:]
    for store in (there, straight):  # in this process, both: the resume and the reference need no process of their own
        done = run_cli_in_process(ARGS, store)
        assert done.returncode == 0, done.stderr[-3000:]

    moved, uninterrupted = _cells(_client(there)), _cells(_client(straight))
    assert sorted(moved) == ["0", "1"]  # the imported runs, resumed: no new ones
    for seed, run in moved.items():
        run, ref = _client(there).get_run(run.info.run_id), _client(straight).get_run(uninterrupted[seed].info.run_id)
        assert run.info.status == "FINISHED" and run.data.tags["resumed_from_iteration"] == "50"
        losses = [(m.step, m.value) for m in _client(there).get_metric_history(run.info.run_id, "train/loss")]
        assert losses == [(m.step, m.value) for m in _client(straight).get_metric_history(ref.info.run_id,
                                                                                          "train/loss")]
        mine, theirs = _weights(_client(there), run.info.run_id, tmp_path), _weights(
            _client(straight), ref.info.run_id, tmp_path / "ref")
        assert mine.keys() == theirs.keys()
        assert all(torch.equal(mine[k], theirs[k]) for k in mine)  # bit for bit: same code, same machine
        assert run.data.metrics["reacher/success_rate"] == ref.data.metrics["reacher/success_rate"]

    again = run_cli_in_process(["export", "--study", "moved", "--with-checkpoints", "--out", str(tmp_path / "again")],
                               there, module="reports")
    assert again.returncode == 0, again.stderr[-3000:]
    carried = {p.relative_to(tmp_path / "again" / "moved").as_posix().split("/", 2)[-1]
               for p in (tmp_path / "again" / "moved").rglob("*.pt")}
    assert carried == {"weights_at/50/weights.pt", "weights_at/100/weights.pt"}  # finished: no resume checkpoint
