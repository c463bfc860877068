"""The placeholders over several studies, on real smoke ablations of reacher's LSTM (6 straight demonstrations;
4 demonstrations, half of them switching goal) and of its a.c. LSTM (6 straight ones): {{ data_scaling(...) }}
(reports.analyses.data_scaling) as one curve, {{ lever(...) }} (reports.analyses.levers) telling the two apart by their
settings, {{ goal_switch(...) }} (reports.analyses.goal_switch) from their changing-goal rollouts."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
from cli_helpers import render_results, run_cli_in_process
from mlflow import MlflowClient

from experiments.stats import pct

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def store(tmp_path_factory) -> Path:
    store = tmp_path_factory.mktemp("scaling")
    for name, n, variant, switches in (("demos6", 6, "lstm", []), ("demos6-ac", 6, "ac-lstm", []),
                                       ("demos4", 4, "lstm", ["--set", "per_task.reacher.data.goal_switches=0.5"])):
        proc = run_cli_in_process(["ablation", "--profile", "smoke", "--variants", variant, "--workers", "1",
                                   "--study-name", name, "--set", f"per_task.reacher.data.n_demos={n}", "--set",
                                   "eval.rollouts=2", "--set", "eval.figures=0", *switches], store)
        assert proc.returncode == 0, proc.stderr[-3000:]
    return store


def _success(store: Path, study: str, task: str) -> float:
    """The evaluated task's success rate logged by the study's one reacher run."""
    client = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    runs = client.search_runs([e.experiment_id for e in client.search_experiments()],
                              f"tags.study_name = '{study}' and tags.task = 'reacher'")
    (run,) = [r for r in runs if f"{task}/success_rate" in r.data.metrics]
    return run.data.metrics[f"{task}/success_rate"]


def test_one_curve_from_two_studies(store, tmp_path):
    template = '{{ provenance }}\n\n{{ data_scaling("reacher", "demos6", "demos4") }}\n'
    assert render_results(store, tmp_path, template) == 0
    text = (tmp_path / "RESULTS.md").read_text()
    lines = text.splitlines()
    start = next(i for i, line in enumerate(lines) if line.startswith("| task"))
    table = [[c.strip() for c in line.strip().strip("|").split("|")] for line in lines[start:]
             if line.startswith("|") and "---" not in line]
    assert table[0] == ["task", "variant", "demos", "success", "per seed", "seed-level 95%",
                        "Wilson 95% (rollouts independent)", "rollouts", "seeds"]
    rows = {tuple(c[:3]): c[3:] for c in table[1:]}
    assert list(rows) == [("reacher", "LSTM", "4"), ("reacher", "LSTM", "6"), ("changing-goal reacher", "LSTM", "4"),
                          ("changing-goal reacher", "LSTM", "6")]  # by task, variant, then demonstrations
    for task, label in (("reacher", "reacher"), ("reacher-changing-goal", "changing-goal reacher")):
        for n in (4, 6):
            rate = pct(_success(store, f"demos{n}", task))
            # one seed: its rate is the mean; no seed-level interval; 2 rollouts
            assert rows[(label, "LSTM", str(n))][:3] == [rate, rate, "–"]
            assert rows[(label, "LSTM", str(n))][4:] == ["2", "1"]
    assert "Studies: demos6, demos4" in text
    link = re.search(r"!\[Success vs number of demonstrations \(reacher: 2 studies\)\]\((figures/[^)]+\.png)\)", text)
    assert link and (tmp_path / link.group(1)).stat().st_size > 0
    assert "demos4" in text.split("| task")[0] and "demos6" in text.split("| task")[0]  # provenance lists both


def test_each_study_sits_at_its_own_number_of_demonstrations(store):
    from reports.analyses.data_scaling import scaling_rows
    from reports.data.store import Store
    from reports.results.selection import Selection

    selection = Selection(Store(f"sqlite:///{store / 'mlflow.db'}"))
    agg = scaling_rows([selection.pick(name, ("ablation",)) for name in ("demos6", "demos4")], "reacher")
    assert sorted(set(zip(agg["n_demos"], agg["study"], strict=True))) == [(4, "demos4"), (6, "demos6")]
    assert set(agg["eval_task"]) == {"reacher", "reacher-changing-goal"} and set(agg["n"]) == {2}
    assert scaling_rows([selection.pick("demos4", ("ablation",))], "circle").empty  # no runs of that task


def test_studies_of_other_variants_share_a_number_of_demonstrations(store):
    """A variant trained later in a study of its own joins the curve at the same count; one variant twice at
    one count is an error (test_the_same_study_twice_is_one_line)."""
    from reports.analyses.data_scaling import DataScalingError, scaling_rows
    from reports.data.store import Store
    from reports.results.selection import Selection

    selection = Selection(Store(f"sqlite:///{store / 'mlflow.db'}"))
    pick = lambda name: selection.pick(name, ("ablation",))  # noqa: E731
    agg = scaling_rows([pick("demos6"), pick("demos4"), pick("demos6-ac")], "reacher")
    assert sorted(set(zip(agg["n_demos"], agg["variant"], agg["study"], strict=True))) == [
        (4, "lstm", "demos4"), (6, "ac-lstm", "demos6-ac"), (6, "lstm", "demos6")]
    with pytest.raises(DataScalingError, match="variant lstm"):
        scaling_rows([pick("demos6"), pick("demos6")], "reacher")


@pytest.mark.parametrize(("placeholder", "message"), [
    ("data_scaling", "both trained reacher on 4 demonstrations"),
    ("lever", "names study 'demos4' twice"),
])
def test_the_same_study_twice_is_one_line(store, tmp_path, capsys, placeholder, message):
    assert render_results(store, tmp_path, f'{{{{ {placeholder}("reacher", "demos4", "demos4") }}}}\n') == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1, err
    assert not (tmp_path / "RESULTS.md").exists()


def test_a_lever_table_and_figure_from_two_real_studies(store, tmp_path):
    assert render_results(store, tmp_path, '{{ provenance }}\n\n{{ lever("reacher", "demos6", "demos4") }}\n') == 0
    text = (tmp_path / "RESULTS.md").read_text()
    table = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.split("| task")[1].splitlines()
             if line.startswith("|") and "---" not in line]
    six, four = "goal_switches=0, n_demos=6", "goal_switches=0.5, n_demos=4"
    assert [r[:3] for r in table] == [["reacher", "LSTM", six], ["reacher", "LSTM", four],
                                      ["changing-goal reacher", "LSTM", six], ["changing-goal reacher", "LSTM", four]]
    assert all(r[-2:] == ["2", "1"] for r in table)  # 2 rollouts, 1 seed
    link = re.search(r"!\[Success by setting \(reacher: 2 studies\)\]\((figures/reacher_lever_demos4\.png)\)", text)
    assert link and (tmp_path / link.group(1)).stat().st_size > 0
    assert "demos4" in text.split("| task")[0] and "demos6" in text.split("| task")[0]  # provenance lists both


def test_the_failures_anatomy_from_the_real_rollouts(store, tmp_path):
    """{{ goal_switch(...) }} reads the changing-goal rollouts artifacts of the same two studies."""
    assert render_results(store, tmp_path, '{{ goal_switch("reacher", "demos6", "demos4") }}\n') == 0
    text = (tmp_path / "RESULTS.md").read_text()
    rows = [[c.strip() for c in line.strip().strip("|").split("|")] for line in text.splitlines()
            if line.startswith("| LSTM")]
    assert [r[:2] for r in rows] == [["LSTM", "goal_switches=0, n_demos=6"], ["LSTM", "goal_switches=0.5, n_demos=4"]]
    assert all(r[-2:] == ["2", "1"] for r in rows)  # 2 episodes, 1 seed
    assert (tmp_path / "figures" / "reacher_goal_switch_demos4.png").stat().st_size > 0
