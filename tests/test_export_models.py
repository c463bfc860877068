"""Models that travel: `reports export --with-models [--models-at N]` carries each finished cell's final model and
its kept checkpoints' weights (weights alone, deterministic, covered by runs.json's sha256), a plain re-export keeps
them, and a fresh store into which the export is imported evaluates them with `experiments milestones` to the same
rollouts, bit for bit, as the original store evaluates its checkpoints."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import torch
from cli_helpers import run_cli_in_process
from mlflow import MlflowClient

from reports.__main__ import main
from reports.data.export import RUNS_FILE

pytestmark = pytest.mark.slow

STUDY = "travel"
# one auto-conditioned MDN cell, 10 iterations, its checkpoints kept at 5 and 10
# (the Python step kernel: the test is about models, not about building the C++ one)
ARGS = ["ablation", "--profile", "smoke", "--variants", "ac-lstm-mdn", "--seeds", "1", "--workers", "1",
        "--study-name", STUDY, "--set", "keep_checkpoints=5", "--set", "train.val_every=0", "--set",
        "train.step_kernel=python", "--set", "eval.figures=0", "--set", "eval.rollouts=2"]
MODELS = {"weights_at/5/weights.pt", "weights_at/10/weights.pt"}


def _uri(store) -> str:
    return f"sqlite:///{store / 'mlflow.db'}"


def _tree(folder) -> dict[str, bytes]:
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def _export(store, out, *more: str) -> int:
    return main(["export", "--study", STUDY, "--tracking-uri", _uri(store), "--out", str(out), *more])


@pytest.fixture(scope="module")
def trained(tmp_path_factory):
    """The original store and the study's export with its models (final at 10, kept at 5)."""
    here = tmp_path_factory.mktemp("here")
    proc = run_cli_in_process(ARGS, here)
    assert proc.returncode == 0, proc.stderr[-3000:]
    out = tmp_path_factory.mktemp("exports")
    assert _export(here, out, "--with-models", "--models-at", "5") == 0
    return here, out / STUDY


def _rollouts(store, study: str) -> dict[tuple[str, str], tuple[dict, dict[str, np.ndarray]]]:
    """(cell key, iteration) -> (metrics, every rollouts array as "<task>/<name>") of the milestones runs of `study`
    in the store."""
    client = MlflowClient(_uri(store))
    exp = client.get_experiment_by_name("milestones")
    out = {}
    for run in client.search_runs([exp.experiment_id], f"tags.study_name = '{study}' and tags.role = 'cell'"):
        assert run.info.status == "FINISHED", run.data.tags.get("error")
        arrays = {}
        for f in client.list_artifacts(run.info.run_id, "rollouts"):
            if f.path.endswith(".npz"):
                with np.load(client.download_artifacts(run.info.run_id, f.path)) as z:
                    arrays.update({f"{f.path[len('rollouts/'):-len('.npz')]}/{k}": z[k] for k in z.files})
        assert {"reacher/tip", "reacher-changing-goal/tip"} <= arrays.keys()
        key = run.info.run_name.rsplit("@", 1)[0], run.data.tags["iteration"]
        out[key] = ({k: v for k, v in run.data.metrics.items() if not k.startswith("time/")}, arrays)
    return out


def test_export_carries_weights_only_models_deterministically(trained, tmp_path):
    from stm.training.checkpoint import load_checkpoint

    here, folder = trained
    doc = json.loads((folder / RUNS_FILE).read_text())
    assert doc["models"] == {"at": [5]}
    cells = [r for r in doc["runs"] if r["tags"].get("role") == "cell"]
    assert len(cells) == 1
    client = MlflowClient(_uri(here))
    for run in cells:
        assert MODELS | {"config/config.json"} <= set(run["artifacts"])  # listed, so their sha256 is checked
        for it in (5, 10):
            saved = torch.load(folder / "artifacts" / run["run_id"] / f"weights_at/{it}/weights.pt",
                               weights_only=True)
            assert not {"optimizer", "rng", "history"} & set(saved) and saved["iteration"] == it
            ckpt = load_checkpoint(client.download_artifacts(run["run_id"], f"checkpoint_at/{it}/model.pt",
                                                             str(tmp_path / run["run_id"] / str(it))))
            assert saved["model"].keys() == ckpt["model"].keys()
            for k, v in saved["model"].items():
                assert v.dtype == torch.float32 and torch.equal(v, ckpt["model"][k])

    again = tmp_path / "again"
    shutil.copytree(folder, again / STUDY)
    assert _export(here, again) == 0  # plain: the export remembers its models, and gives the same bytes
    assert _tree(again / STUDY) == _tree(folder)


def test_bad_model_choices_are_one_line_and_nothing_is_dropped(trained, tmp_path, capsys):
    here, folder = trained
    assert _export(here, tmp_path / "a", "--with-models", "--models-at", "7") == 2
    assert "kept a checkpoint at iteration 7" in capsys.readouterr().err
    with pytest.raises(SystemExit) as exit_:
        _export(here, tmp_path / "a", "--models-at", "5")
    assert exit_.value.code == 2 and "add --with-models" in capsys.readouterr().err

    earlier = tmp_path / "b" / STUDY  # an export that carries a model the store does not hold
    shutil.copytree(folder, earlier)
    doc = json.loads((earlier / RUNS_FILE).read_text())
    doc["runs"][1]["artifacts"]["weights_at/3/weights.pt"] = "0" * 64
    (earlier / RUNS_FILE).write_text(json.dumps(doc))
    before = _tree(earlier)
    assert _export(here, tmp_path / "b") == 2
    err = capsys.readouterr().err
    assert "carries 1 model(s) the store no longer holds" in err and err.count("\n") == 1, err
    assert _tree(earlier) == before  # nothing written


def test_a_fresh_store_evaluates_the_exported_models_as_the_original_store(trained, tmp_path):
    from experiments.milestones import run_milestones

    here, folder = trained
    there = tmp_path / "there"
    there.mkdir()
    assert main(["import", str(folder), "--tracking-uri", _uri(there)]) == 0
    for store in (here, there):  # every model evaluated anew, final ones included, sampling their mixtures
        counts = run_milestones(STUDY, uri=_uri(store), feedback="sample")  # `milestones --feedback sample`
        assert counts == {"FINISHED": 2, "FAILED": 0, "skipped": 0}
    study = f"{STUDY}-milestones-feedback-sample"
    moved, original = _rollouts(there, study), _rollouts(here, study)
    assert sorted(moved) == sorted(original) and {it for _, it in moved} == {"5", "10"}
    for key, (metrics, arrays) in original.items():
        assert moved[key][0] == metrics, key
        assert arrays.keys() == moved[key][1].keys()
        for name, a in arrays.items():  # bit for bit: the same weights, episodes and sampling seeds
            b = moved[key][1][name]
            assert a.dtype == b.dtype and a.shape == b.shape and a.tobytes() == b.tobytes(), (key, name)
            assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f"), (key, name)

    # with the cells' own feedback, a final model's own (exported) evaluation is copied, as in the original store
    assert run_milestones(STUDY, uri=_uri(there), iterations=[10]) == {"FINISHED": 1, "FAILED": 0, "skipped": 0}
    client = MlflowClient(_uri(there))
    for (cell, _), (_, arrays) in _rollouts(there, f"{STUDY}-milestones").items():
        run = next(r for r in json.loads((folder / RUNS_FILE).read_text())["runs"] if r["run_name"] == cell)
        with np.load(folder / "artifacts" / run["run_id"] / "rollouts/reacher.npz") as z:
            assert all(np.array_equal(arrays[f"reacher/{k}"], z[k], equal_nan=z[k].dtype.kind == "f")
                       for k in z.files)
    assert all(r.data.tags.get("copied") == "1" for r in client.search_runs(
        [client.get_experiment_by_name("milestones").experiment_id], f"tags.study_name = '{STUDY}-milestones'"
        " and tags.role = 'cell'"))
