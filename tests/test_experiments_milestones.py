"""`python -m experiments milestones`: the checkpoints an ablation kept (keep_checkpoints) evaluated like its
final models, as a tracked study; the final model's own evaluation copied, a re-run evaluates nothing twice,
bad selections are one line with exit code 2; the report's success-vs-iterations figure draws from it."""

from __future__ import annotations

import re

import numpy as np
import pytest
from cli_helpers import run_cli, run_cli_in_process
from mlflow.tracking import MlflowClient
from PIL import Image

SMALL = ["--set", "eval.rollouts=3", "--set", "eval.figures=0"]


@pytest.fixture(scope="module")
def kept_store(tmp_path_factory):
    """A smoke study (10 iterations, 2 seeds of lstm) that kept its checkpoints at 5 and 10 iterations."""
    store = tmp_path_factory.mktemp("kept")
    proc = run_cli_in_process(["ablation", "--profile", "smoke", "--variants", "lstm", "--seeds", "2", "--workers", "1",
                               "--set", "keep_checkpoints=5", "--study-name", "kept", *SMALL], store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return store


def _runs(client: MlflowClient, experiment: str) -> list:
    exp = client.get_experiment_by_name(experiment)
    return client.search_runs([exp.experiment_id], "tags.role = 'cell'") if exp else []


@pytest.mark.slow
def test_milestones_evaluate_each_kept_checkpoint_once(kept_store):
    proc = run_cli_in_process(["milestones", "--study", "kept"], kept_store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "4 evaluated, 0 already done, 0 failed" in proc.stdout
    client = MlflowClient(f"sqlite:///{kept_store / 'mlflow.db'}")
    cells = {r.info.run_id: r for r in _runs(client, "ablation")}
    runs = _runs(client, "milestones")
    assert sorted((r.data.tags["seed"], r.data.tags["iteration"]) for r in runs) == \
        [("0", "10"), ("0", "5"), ("1", "10"), ("1", "5")]
    for run in runs:
        assert run.info.status == "FINISHED"
        source = cells[run.data.tags["source_run"]]
        assert run.data.params["train.lr"] == source.data.params["train.lr"]
        assert run.data.params["milestone.iteration"] == run.data.tags["iteration"]
        rollouts = client.download_artifacts(run.info.run_id, "rollouts/reacher.npz")
        with np.load(rollouts) as z:  # the logged rate is the rate of the logged episodes
            assert run.data.metrics["reacher/success_rate"] == pytest.approx(np.mean(z["success"]))
            assert len(z["success"]) == 3 and set(z["seed"]) == {int(run.data.tags["seed"])}
        if run.data.tags["iteration"] == "10":  # the cell's final model: its own evaluation, copied
            assert run.data.tags.get("copied") == "1"
            assert run.data.metrics["reacher/final_distance_mean"] == \
                source.data.metrics["reacher/final_distance_mean"]
        else:  # an intermediate model: other weights than the final one, so other rollouts
            assert "copied" not in run.data.tags
            assert run.data.metrics["reacher/final_distance_mean"] != \
                source.data.metrics["reacher/final_distance_mean"]

    again = run_cli_in_process(["milestones", "--study", "kept"], kept_store)
    assert again.returncode == 0 and "0 evaluated, 4 already done" in again.stdout
    assert len(_runs(client, "milestones")) == 4


@pytest.mark.slow
def test_success_vs_iterations_figure_draws_each_variant(kept_store, tmp_path):
    from reports.analyses.success_vs_iterations import milestone_rows, success_vs_iterations
    from reports.data.store import Store

    if not _runs(MlflowClient(f"sqlite:///{kept_store / 'mlflow.db'}"), "milestones"):
        assert run_cli_in_process(["milestones", "--study", "kept"], kept_store).returncode == 0
    study = Store(f"sqlite:///{kept_store / 'mlflow.db'}").studies("milestones", None)[0]
    agg = milestone_rows(study)
    assert sorted(set(agg["iteration"])) == [5, 10] and set(agg["seeds"]) == {2} and set(agg["n"]) == {6}
    fig = success_vs_iterations(study, tmp_path)
    assert fig.gap is None and [p.suffix for p in fig.paths] == [".png", ".pdf"]
    with Image.open(fig.paths[0]) as im:  # lstm's line is drawn in its colour (tab10's first: 31, 119, 180)
        pixels = np.asarray(im.convert("RGB")).reshape(-1, 3)
    assert (np.abs(pixels.astype(int) - [31, 119, 180]).sum(axis=1) < 12).sum() > 50


@pytest.mark.parametrize(("args", "message", "store"), [
    (["--study", "nope"], "no ablation study named 'nope'", True),
    (["--study", "nope"], "no MLflow store at", False),  # and none is made: an empty one would hide the mistake
    (["--study", "kept", "--rollouts", "0"], "--rollouts must be >= 1", False),
])
@pytest.mark.slow
def test_bad_selection_is_one_line_and_exit_2(tmp_path, args, message, store):
    from experiments.runtime.tracking import Client

    if store:
        Client(f"sqlite:///{tmp_path / 'mlflow.db'}")  # a store without the study
    proc = run_cli(["milestones", *args], tmp_path)
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and message in lines[0], proc.stderr[-2000:]
    assert (tmp_path / "mlflow.db").exists() == store


@pytest.mark.slow
def test_iterations_select_the_kept_checkpoints(kept_store):
    proc = run_cli_in_process(["milestones", "--study", "kept", "--iterations", "10", "--feedback", "component_mean"],
                              kept_store)
    assert proc.returncode == 0, proc.stderr[-3000:]  # a deterministic head: one output whatever the feedback
    assert "'kept-milestones-feedback-component_mean': 2 evaluated, 0 already done" in proc.stdout
    client = MlflowClient(f"sqlite:///{kept_store / 'mlflow.db'}")
    exp = client.get_experiment_by_name("milestones")
    runs = client.search_runs([exp.experiment_id],
                              "tags.study_name = 'kept-milestones-feedback-component_mean' and tags.role = 'cell'")
    assert sorted(r.data.tags["iteration"] for r in runs) == ["10", "10"]
    assert all("copied" not in r.data.tags for r in runs)  # evaluated anew, not copied
    none = run_cli(["milestones", "--study", "kept", "--iterations", "7"], kept_store)
    assert none.returncode == 2 and "at iterations 7" in none.stderr


@pytest.mark.slow
def test_validation_split_evaluates_its_own_episodes_and_stays_out_of_headline_tables(kept_store, tmp_path):
    """--split validation: the kept models (final ones too: their own evaluation was on the test episodes)
    evaluated on the validation episodes (eval seed + 10,000 + seed, 34 per seed and task) as their own study,
    each run tagged with its split; a headline table refuses that study, a comparison quotes it labelled."""
    proc = run_cli_in_process(["milestones", "--study", "kept", "--split", "validation", "--iterations", "10"],
                              kept_store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "'kept-milestones-validation': 2 evaluated, 0 already done, 0 failed" in proc.stdout
    client = MlflowClient(f"sqlite:///{kept_store / 'mlflow.db'}")
    exp = client.get_experiment_by_name("milestones")
    runs = client.search_runs([exp.experiment_id],
                              "tags.study_name = 'kept-milestones-validation' and tags.role = 'cell'")
    assert len(runs) == 2
    for run in runs:
        assert run.data.tags["split"] == "validation" and run.data.params["eval.split"] == "validation"
        assert "copied" not in run.data.tags and run.data.metrics["reacher/n_rollouts"] == 34
        assert run.data.metrics["reacher/episode_seed"] == 20_000 + int(run.data.tags["seed"])

    from reports.data.store import Store, StoreError
    from reports.results.writer import write_results

    store = Store(f"sqlite:///{kept_store / 'mlflow.db'}")
    template = tmp_path / "t.md"
    template.write_text('{{ success_table(study="kept-milestones-validation") }}\n')
    with pytest.raises(StoreError, match="validation episodes"):
        write_results(store, template, tmp_path / "R.md", tmp_path / "fig")
    template.write_text('{{ rate("reacher", "kept-milestones-validation/lstm") }}\n')
    text = write_results(store, template, tmp_path / "R.md", tmp_path / "fig").read_text()
    assert re.search(r"\d+ % \(seed-level 95 % interval .*; 2 seeds; validation episodes\)", text), text


@pytest.mark.slow
def test_cells_without_kept_checkpoints_say_how_to_keep_them(kept_store):
    proc = run_cli(["milestones", "--study", "kept", "--variants", "ac-lstm"], kept_store)  # no such cell
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "keep_checkpoints = N" in lines[0], proc.stderr[-2000:]


@pytest.mark.slow
def test_results_template_names_the_milestones_study(kept_store, tmp_path):
    from reports.data.store import Store
    from reports.results.writer import write_results

    if not _runs(MlflowClient(f"sqlite:///{kept_store / 'mlflow.db'}"), "milestones"):
        assert run_cli_in_process(["milestones", "--study", "kept"], kept_store).returncode == 0
    template = tmp_path / "t.md"
    template.write_text('{{ budget_table(study="kept") }}\n'
                        '{{ success_table(study="kept-milestones") }}\n'
                        '{{ figure("success_vs_iterations", study="kept-milestones") }}\n')
    out = write_results(Store(f"sqlite:///{kept_store / 'mlflow.db'}"), template, tmp_path / "R.md", tmp_path / "fig")
    text = out.read_text()
    assert "| reacher | LSTM | 10 | 10 (finished) / 10 (finished) |" in re.sub(" +", " ", text)
    # the milestones' success table: the tasks its checkpoints were evaluated on, no gap rows for the rest
    assert re.search(r"\| reacher +\| LSTM +\| \d+%", text) and "| pick-and-place" not in text and " gap " not in text
    assert "](fig/kept-milestones_success_vs_iterations.png)" in text
    assert (tmp_path / "fig" / "kept-milestones_success_vs_iterations.png").is_file()


@pytest.fixture(scope="module")
def mdn_store(tmp_path_factory):
    """A smoke study of lstm-mdn (one seed, 10 iterations) that kept its final checkpoint."""
    store = tmp_path_factory.mktemp("kept-mdn")
    proc = run_cli_in_process(["ablation", "--profile", "smoke", "--variants", "lstm-mdn", "--workers", "1",
                               "--set", "keep_checkpoints=10", "--study-name", "mdn", *SMALL], store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return store


@pytest.mark.slow
def test_feedback_evaluates_the_final_models_anew_as_their_own_study(mdn_store, tmp_path):
    proc = run_cli_in_process(["milestones", "--study", "mdn", "--feedback", "sample"], mdn_store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "'mdn-milestones-feedback-sample': 1 evaluated, 0 already done, 0 failed" in proc.stdout
    client = MlflowClient(f"sqlite:///{mdn_store / 'mlflow.db'}")
    (source,) = _runs(client, "ablation")
    (run,) = _runs(client, "milestones")
    assert run.data.tags["study_name"] == "mdn-milestones-feedback-sample" and "copied" not in run.data.tags
    assert run.data.params["eval.feedback"] == "sample" and source.data.params["eval.feedback"] == "component_mean"
    # the same model and episodes, sampled instead of the most likely component's mean: other rollouts
    assert run.data.metrics["reacher/final_distance_mean"] != source.data.metrics["reacher/final_distance_mean"]

    # the lever table puts the two side by side, told apart by their feedback
    from reports.data.store import Store
    from reports.results.writer import write_results

    template = tmp_path / "t.md"
    template.write_text('{{ lever("reacher", "mdn", "mdn-milestones-feedback-sample") }}\n')
    text = write_results(Store(f"sqlite:///{mdn_store / 'mlflow.db'}"), template, tmp_path / "R.md",
                         tmp_path / "fig").read_text()
    assert re.search(r"\| reacher +\| LSTM-MDN +\| eval.feedback=component_mean +\|", text)
    assert re.search(r"\| reacher +\| LSTM-MDN +\| eval.feedback=sample +\|", text)


@pytest.fixture(scope="module")
def stack_store(tmp_path_factory):
    """A smoke pick-place study (lstm, one seed, 4 demonstrations, 10 iterations) that kept its final checkpoint;
    its model is also evaluated on stacking, under the default protocol between the blocks (place_pose)."""
    store = tmp_path_factory.mktemp("kept-stack")
    proc = run_cli_in_process(["ablation", "--profile", "smoke", "--tasks", "pick-place", "--variants", "lstm",
                               "--workers", "1", "--set", "keep_checkpoints=10", "--set",
                               "per_task.pick-place.data.n_demos=4", "--set", "train.step_kernel=python",
                               "--study-name", "stk", *SMALL], store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return store


def test_stack_restart_names_its_study_after_the_other_choices():
    from experiments.milestones import milestones_study_name

    assert milestones_study_name("pickplace-v2", split="validation", stack_restart="start") == \
        "pickplace-v2-milestones-validation-stack-start"
    assert milestones_study_name("p", "sample", "validation", "place_pose") == \
        "p-milestones-validation-feedback-sample-stack-place_pose"


@pytest.mark.slow
def test_stack_restart_evaluates_stacking_alone_under_its_protocol(stack_store, tmp_path):
    """--stack-restart start: the final model evaluated anew (not copied) on stacking alone, with the scripted move
    to a drawn start configuration between the blocks, whose per-episode check the cell's own evaluation lacks."""
    proc = run_cli_in_process(["milestones", "--study", "stk", "--stack-restart", "start"], stack_store)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "'stk-milestones-stack-start': 1 evaluated, 0 already done, 0 failed" in proc.stdout
    client = MlflowClient(f"sqlite:///{stack_store / 'mlflow.db'}")
    (source,) = _runs(client, "ablation")
    (run,) = _runs(client, "milestones")
    assert run.data.tags["study_name"] == "stk-milestones-stack-start" and "copied" not in run.data.tags
    assert run.data.params["eval.stack_restart"] == "start"
    assert source.data.params.get("eval.stack_restart", "place_pose") == "place_pose"
    assert {f.path for f in client.list_artifacts(run.info.run_id, "rollouts")} == {"rollouts/stack.npz"}
    assert {k.split("/")[0] for k in run.data.metrics if "/" in k} <= {"stack", "time"}  # stacking's metrics only
    assert "pick-place/success_rate" in source.data.metrics
    with np.load(client.download_artifacts(run.info.run_id, "rollouts/stack.npz")) as z:
        assert set(np.unique(z["tower_stood_move_1"])) <= {0.0, 1.0} and len(z["tower_stood_move_2"]) == 3
        assert run.data.metrics["stack/success_rate"] == pytest.approx(np.mean(z["success"]))
    with np.load(client.download_artifacts(source.info.run_id, "rollouts/stack.npz")) as z:
        assert "tower_stood_move_1" not in z.files  # place_pose moves nothing between the blocks

    from reports.data.store import Store
    from reports.results.writer import write_results

    template = tmp_path / "t.md"  # its success table: the stacking row, no gap rows for the tasks it skipped
    template.write_text('{{ success_table(study="stk-milestones-stack-start") }}\n')
    text = write_results(Store(f"sqlite:///{stack_store / 'mlflow.db'}"), template, tmp_path / "R.md",
                         tmp_path / "fig").read_text()
    assert "| stacking" in text and "| pick-and-place" not in text and " gap " not in text, text


@pytest.mark.slow
def test_stack_restart_needs_a_cell_that_serves_stacking(kept_store):
    proc = run_cli(["milestones", "--study", "kept", "--stack-restart", "start"], kept_store)  # reacher cells only
    assert proc.returncode == 2
    lines = [ln for ln in proc.stderr.splitlines() if ln.startswith("error:")]
    assert len(lines) == 1 and "evaluated on stack" in lines[0], proc.stderr[-2000:]
