"""{{ lever(...) }} (reports.analyses.levers): a lever's studies side by side, each labelled by the settings that set it
apart (read from the runs' params): checks on hand-made studies (the real ones: test_reports_across_studies)."""

from __future__ import annotations

import pandas as pd
import pytest

from reports.analyses.levers import LeverError, setting_labels, study_settings
from reports.data.store import Study
from reports.results.across import at_iteration


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
    assert setting_labels([a], "reacher") == {("a", "lstm"): "no setting differs"}
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


def test_a_milestones_stage_is_set_beside_a_study_trained_that_long():
    """STUDY@ITERATION: the checkpoints a milestones study kept at that iteration, whose train.iters reads as the
    iteration they trained; a stage the study did not keep is an error that lists the kept ones."""
    from reports.data.store import StoreError

    stages = pd.concat([_study("m", **{"train.iters": "30000", "milestone.iteration": str(it)}).children
                        for it in (5000, 10000)], ignore_index=True)
    milestones = Study("milestones", {"run_id": "m", "tags.study_name": "paper-milestones"}, stages, client=None)
    lever = _study("switches", **{"train.iters": "5000", "data.goal_switches": "0.5"})
    with pytest.raises(LeverError, match="several iterations .5000, 10000.; name one as paper-milestones@ITERATION"):
        setting_labels([milestones, lever], "reacher")
    at5k = at_iteration(milestones, 5000)
    assert at5k.name == "paper-milestones@5000" and len(at5k.children) == 2
    assert study_settings(at5k, "reacher", "lstm")["train.iters"] == "5000"
    assert setting_labels([at5k, lever], "reacher") == {("paper-milestones@5000", "lstm"): "goal_switches=0",
                                                        ("switches", "lstm"): "goal_switches=0.5"}
    with pytest.raises(StoreError, match="no runs at iteration 7000 .kept: 5000, 10000."):
        at_iteration(milestones, 7000)
    with pytest.raises(StoreError, match="kept: none: not a milestones study"):
        at_iteration(lever, 5000)


def test_a_template_names_a_stage_and_provenance_keeps_the_whole_study():
    from reports.results.across import whole_study
    from reports.results.template import Placeholder, ResultsError
    from reports.results.writer import _named_studies

    stages = pd.concat([_study("m", **{"milestone.iteration": str(it)}).children for it in (5000, 10000)],
                       ignore_index=True)
    whole = Study("milestones", {"run_id": "m", "tags.study_name": "paper-milestones"}, stages, client=None)

    class OneStudy:  # a Selection of one stored study
        def pick(self, name, kinds):
            assert name == "paper-milestones"
            return whole

    named = _named_studies(OneStudy(), [Placeholder("lever", ("reacher", "paper-milestones@10000"), 3)])
    assert named["paper-milestones"] is whole and len(named["paper-milestones@10000"].children) == 2
    assert whole_study("paper-milestones@10000") == "paper-milestones"
    for bad, why in (("paper-milestones@ten", "must be a whole number"), ("paper-milestones@1", "no runs at")):
        with pytest.raises(ResultsError, match=why):
            _named_studies(OneStudy(), [Placeholder("lever", ("reacher", bad), 3)])


def test_two_stages_of_one_study_get_their_own_success_tables(tmp_path):
    """NAME@5000 and NAME@10000 share the milestones study's parent run: each table is of its own stage (both
    once read the first stage's), and what the template used is the whole study (its provenance)."""
    from reports.results.template import Placeholder
    from reports.results.writer import Results

    def stage(it: int, rate: float) -> pd.DataFrame:
        return _study("m", **{"milestone.iteration": str(it)}).children.assign(**{
            "metrics.reacher/success_rate": rate, "metrics.reacher/n_rollouts": 4.0, "run_id": [f"{it}-0", f"{it}-1"]})

    stages = pd.concat([stage(5000, 0.25), stage(10000, 0.75)], ignore_index=True)
    whole = Study("milestones", {"run_id": "m", "tags.study_name": "pm"}, stages, client=None)
    named = {"pm": whole, **{f"pm@{it}": at_iteration(whole, it) for it in (5000, 10000)}}
    results = Results(None, [], tmp_path / "RESULTS.md", tmp_path, "command", named)
    assert [results.summary("success", named[f"pm@{it}"])["mean"].tolist() for it in (5000, 10000)] == [[0.25], [0.75]]
    used = results.used([Placeholder("success_table", (), 1, study=f"pm@{it}") for it in (5000, 10000)])
    assert used[1] == [whole]
