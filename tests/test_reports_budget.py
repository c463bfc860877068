"""The training-budget table (reports.study_report.tables.budget_table): the iterations each cell got, from the
runs' own params, metrics and checkpoint tags, for finished, still-training and queued runs."""

from __future__ import annotations

import shutil

import pytest
from mlflow.tracking import MlflowClient

from experiments.runtime.tracking import PARENT_TAG
from experiments.weights_resume import RESUMED_TAG
from reports.data.store import Store
from reports.study_report.tables import budget_table


@pytest.mark.slow
def test_budget_table_reports_each_seeds_iterations_and_status(smoke_store, tmp_path):
    shutil.copy2(smoke_store.path / "mlflow.db", tmp_path / "mlflow.db")  # artifacts stay where they are
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.get_experiment_by_name("ablation").experiment_id
    cells = client.search_runs([exp], "tags.role = 'cell'")
    parent = cells[0].data.tags[PARENT_TAG]
    # a seed stopped after its checkpoint at iteration 5 (RUNNING, resumable), one resumed from its weights kept
    # at 5 and stopped at 8, and a queued seed
    stopped = client.create_run(exp, tags={PARENT_TAG: parent, "task": "reacher", "variant": "lstm", "seed": "7",
                                           "role": "cell", "checkpoint_iteration": "5"})
    client.log_param(stopped.info.run_id, "train.iters", "10")
    resumed = client.create_run(exp, tags={PARENT_TAG: parent, "task": "reacher", "variant": "lstm", "seed": "8",
                                           "role": "cell", "checkpoint_iteration": "8", RESUMED_TAG:
                                           "5 (fresh optimiser and random streams)"})
    client.log_param(resumed.info.run_id, "train.iters", "10")
    client.set_terminated(resumed.info.run_id, "KILLED")
    client.create_run(exp, tags={PARENT_TAG: parent, "task": "reacher", "variant": "lstm", "seed": "9",
                                 "role": "cell"})
    study = Store(uri).studies("ablation", None)[0]
    table = budget_table(study)
    rows = {(r[0], r[1]): r for r in table.rows}
    label = {"lstm": "LSTM", "ac-lstm": "a.c. LSTM", "lstm-mdn": "LSTM-MDN", "ac-lstm-mdn": "a.c. LSTM-MDN"}
    for run in cells:
        _, _, planned, reached = rows[run.data.tags["task"], label[run.data.tags["variant"]]]
        assert planned == f"{int(run.data.params['train.iters']):,}"
        assert f"{int(run.data.metrics['train/iterations']):,} (finished)" in reached
    lstm = rows["reacher", "LSTM"][3].split(" / ")
    # seeds 7, 8 and 9, after the finished ones in seed order
    assert lstm[-3:] == ["5 (running)", "8 (killed; from weights at 5)", "0 (queued)"]
    assert any(note.startswith("from weights at N:") for note in table.notes)
