"""{{ lever(...) }} (reports.levers): a lever's studies side by side, each labelled by the settings that set it
apart (read from the runs' params). Pure checks on hand-made studies, then two real smoke ablations of reacher's
LSTM, with and without goal-switch demonstrations, rendered by the RESULTS template."""

from __future__ import annotations

import re
from pathlib import Path

import pandas as pd
import pytest
from cli_helpers import render_results, run_cli

from reports.levers import LeverError, setting_labels, study_settings
from reports.store import Study


def _study(name: str, variants: tuple[str, ...] = ("lstm",), **params: object) -> Study:
    """A finished study of reacher runs (seeds 0, 1 of each variant) with the given params; the variants differ
    in their head, as they do."""
    rows = [{"status": "FINISHED", "task": "reacher", "variant": v, "seed": s, "params.train.seed": str(s),
             "params.model.head": "mdn" if "mdn" in v else "deterministic", "params.eval.figures": "4",
             **{f"params.{k}": v for k, v in params.items()}} for v in variants for s in (0, 1)]
    return Study("ablation", {"run_id": name, "tags.study_name": name}, pd.DataFrame(rows), client=None)


def test_labels_name_only_the_settings_that_differ():
    a = _study("a", **{"data.n_demos": "45", "train.u": "5"})
    b = _study("b", **{"data.n_demos": "45", "data.goal_switches": "0.5", "train.u": "5"})
    c = _study("c", **{"data.n_demos": "150", "data.goal_switches": "0.5", "train.u": "5"})
    # a did not log goal_switches: it ran on the task's default (0)
    assert setting_labels([a, b, c], "reacher") == {("a", "lstm"): "goal_switches=0, n_demos=45",
                                                    ("b", "lstm"): "goal_switches=0.5, n_demos=45",
                                                    ("c", "lstm"): "goal_switches=0.5, n_demos=150"}
    assert setting_labels([a, _study("d", **{"data.n_demos": "45", "train.u": "1"})], "reacher") == {
        ("a", "lstm"): "train.u=5", ("d", "lstm"): "train.u=1"}
    assert setting_labels([a], "reacher") == {("a", "lstm"): "as the first"}
    assert setting_labels([a], "circle") == {}  # no runs of that task
    # the seed and logging cadence differ between runs: never a setting
    settings = study_settings(a, "reacher", "lstm")
    assert "train.seed" not in settings and "eval.figures" not in settings


def test_variants_are_compared_with_their_own_kind():
    """The variants of one study differ in their head; a lever study of the mixture variants only is told apart
    from the headline by its feedback, and the headline's deterministic rows keep a label of their own."""
    head = _study("paper", ("lstm", "lstm-mdn"), **{"eval.feedback": "component_mean"})
    mixture = _study("mixture", ("lstm-mdn",), **{"eval.feedback": "mixture_mean"})
    assert setting_labels([head, mixture], "reacher") == {
        ("paper", "lstm"): "eval.feedback=component_mean", ("paper", "lstm-mdn"): "eval.feedback=component_mean",
        ("mixture", "lstm-mdn"): "eval.feedback=mixture_mean"}


def test_twin_studies_and_runs_that_disagree_are_errors():
    a = _study("a", **{"data.n_demos": "45"})
    with pytest.raises(LeverError, match="'a', 'a2' trained reacher/lstm with the same settings"):
        setting_labels([a, _study("a2", **{"data.n_demos": "45"})], "reacher")
    mixed = _study("m", **{"data.n_demos": "45"})
    mixed.children.loc[1, "params.data.n_demos"] = "90"
    with pytest.raises(LeverError, match="runs of reacher/lstm differ in data.n_demos"):
        study_settings(mixed, "reacher", "lstm")


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    store = tmp_path_factory.mktemp("lever")
    for name, extra in (("straight", []), ("switches", ["--set", "per_task.reacher.data.goal_switches=0.5"])):
        proc = run_cli(["ablation", "--profile", "smoke", "--variants", "lstm", "--workers", "1", "--study-name",
                        name, "--set", "per_task.reacher.data.n_demos=4", "--set", "eval.rollouts=2",
                        "--set", "eval.figures=0", *extra], store)
        assert proc.returncode == 0, proc.stderr[-3000:]
    return store


@pytest.mark.slow
def test_a_lever_table_and_figure_from_two_real_studies(store, tmp_path):
    assert render_results(store, tmp_path, '{{ provenance }}\n\n{{ lever("reacher", "straight", "switches") }}\n') == 0
    text = (tmp_path / "RESULTS.md").read_text()
    table = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.split("| task")[1].splitlines()
             if line.startswith("|") and "---" not in line]
    assert [r[:3] for r in table] == [["reacher", "LSTM", "goal_switches=0"], ["reacher", "LSTM", "goal_switches=0.5"],
                                      ["changing-goal reacher", "LSTM", "goal_switches=0"],
                                      ["changing-goal reacher", "LSTM", "goal_switches=0.5"]]
    assert all(r[-2:] == ["2", "1"] for r in table)  # 2 rollouts, 1 seed
    link = re.search(r"!\[Success by setting \(reacher: 2 studies\)\]\((figures/reacher_lever_switches\.png)\)", text)
    assert link and (tmp_path / link.group(1)).stat().st_size > 0
    assert "straight" in text.split("| task")[0] and "switches" in text.split("| task")[0]  # provenance lists both


@pytest.mark.slow
def test_the_failures_anatomy_from_the_real_rollouts(store, tmp_path):
    """{{ goal_switch(...) }} reads the changing-goal rollouts artifacts of the same two studies."""
    assert render_results(store, tmp_path, '{{ goal_switch("reacher", "straight", "switches") }}\n') == 0
    text = (tmp_path / "RESULTS.md").read_text()
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| LSTM")]
    assert [r[:2] for r in rows] == [["LSTM", "goal_switches=0"], ["LSTM", "goal_switches=0.5"]]
    assert all(r[-2:] == ["2", "1"] for r in rows)  # 2 episodes, 1 seed
    assert (tmp_path / "figures" / "reacher_goal_switch_switches.png").stat().st_size > 0


@pytest.mark.slow
def test_the_same_study_twice_is_one_line(store, tmp_path, capsys):
    assert render_results(store, tmp_path, '{{ lever("reacher", "straight", "straight") }}\n') == 2
    err = capsys.readouterr().err
    assert "names study 'straight' twice" in err and err.count("\n") == 1, err
    assert not (tmp_path / "RESULTS.md").exists()


def test_an_unlogged_train_setting_reads_as_its_default():
    a, b = _study("a", **{"data.n_demos": "45"}), _study("b", **{"data.n_demos": "45", "train.hold_steps": "20"})
    assert setting_labels([a, b], "reacher") == {("a", "lstm"): "train.hold_steps=0",
                                                 ("b", "lstm"): "train.hold_steps=20"}


def test_a_milestones_study_at_several_iterations_is_an_error():
    a = _study("m", **{"data.n_demos": "45"})
    a.children["params.milestone.iteration"] = ["5000", "10000"]
    with pytest.raises(LeverError, match="runs of reacher/lstm at several iterations \\(5000, 10000\\)"):
        study_settings(a, "reacher", "lstm")
