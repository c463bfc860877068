"""Every training task through the pipeline: tiny circle and pick-and-place cells trained and
evaluated by the experiments CLI (pick-place's model also on stacking and on changing goals),
then `python -m reports` on that store, with the reports' selection flags (--experiment, --study).
The numbers are checked against the per-episode rollouts the cells logged, and the report's
against the store."""

from __future__ import annotations

import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pandas as pd
import pytest
from cli_helpers import run_cli_in_process
from mlflow.tracking import MlflowClient
from oracles import drawn_colours, wilson

pytestmark = pytest.mark.slow
ROLLOUTS = 3


@dataclass(frozen=True)
class TasksStore:
    path: Path
    client: MlflowClient
    cells: dict  # training task -> its FINISHED cell run
    report: Path  # the ablation study's report folder
    index: str  # its index.html


@pytest.fixture(scope="module")
def tasks_store(tmp_path_factory) -> TasksStore:
    store = tmp_path_factory.mktemp("tasks-store")
    abl = run_cli_in_process(["ablation", "--profile", "smoke", "--tasks", "circle", "pick-place", "--variants",
                              "ac-lstm-mdn", "--workers", "1", "--study-name", "tasks", "--set",
                              "per_task.pick-place.data.n_demos=4", "--set", f"eval.rollouts={ROLLOUTS}"], store)
    assert abl.returncode == 0, abl.stdout + abl.stderr[-3000:]
    sweep = run_cli_in_process(["sweep", "--profile", "smoke", "--task", "circle", "--trials", "1", "--workers", "1",
                                "--study-name", "circle-sweep"], store)
    assert sweep.returncode == 0, sweep.stdout + sweep.stderr[-3000:]
    rep = run_cli_in_process(["--out", str(store / "out"), "--study", "tasks"], store, module="reports")
    assert rep.returncode == 0, rep.stdout + rep.stderr[-3000:]
    assert "ablation study 'tasks'" in rep.stdout and "sweep study" not in rep.stdout  # --study selects one
    client = MlflowClient(f"sqlite:///{store / 'mlflow.db'}")
    exp = client.get_experiment_by_name("ablation")
    cells = {r.data.tags["task"]: r for r in client.search_runs([exp.experiment_id], "tags.role = 'cell'")}
    folder = store / "out" / "tasks"
    return TasksStore(store, client, cells, folder, (folder / "index.html").read_text())


def _rollouts(ts: TasksStore, task: str, eval_task: str, tmp: Path) -> dict[str, np.ndarray]:
    local = ts.client.download_artifacts(ts.cells[task].info.run_id, f"rollouts/{eval_task}.npz", str(tmp))
    with np.load(local) as z:
        return {k: z[k] for k in z.files}


def test_both_tasks_trained_and_evaluated_on_every_task_they_serve(tasks_store):
    assert set(tasks_store.cells) == {"circle", "pick-place"}
    for run in tasks_store.cells.values():
        assert run.info.status == "FINISHED" and run.data.metrics["train/iterations"] == 10
    served = {task: {f.path for f in tasks_store.client.list_artifacts(run.info.run_id, "rollouts")}
              for task, run in tasks_store.cells.items()}
    assert served["circle"] == {"rollouts/circle.npz", "rollouts/ik_timing.json"}
    assert served["pick-place"] == {"rollouts/pick-place.npz", "rollouts/stack.npz",
                                    "rollouts/pick-place-changing-goal.npz", "rollouts/ik_timing.json"}


@pytest.mark.parametrize("task,eval_task", [("pick-place", "pick-place"), ("pick-place", "stack"),
                                            ("pick-place", "pick-place-changing-goal"), ("circle", "circle")])
def test_logged_success_is_the_mean_of_the_logged_rollouts(tasks_store, tmp_path, task, eval_task):
    z = _rollouts(tasks_store, task, eval_task, tmp_path)
    metrics = tasks_store.cells[task].data.metrics
    assert z["success"].shape == (ROLLOUTS,) and set(np.unique(z["success"])) <= {0.0, 1.0}
    assert metrics[f"{eval_task}/n_rollouts"] == ROLLOUTS
    assert metrics[f"{eval_task}/success_rate"] == pytest.approx(z["success"].mean())
    assert metrics[f"{eval_task}/success_ci_high"] == pytest.approx(wilson(int(z["success"].sum()), ROLLOUTS)[1])
    if eval_task != "circle":
        assert metrics[f"{eval_task}/final_distance_mean"] == pytest.approx(z["final_distance"].mean())


def test_stacking_and_changing_goal_episodes_are_what_they_claim(tasks_store, tmp_path):
    place = _rollouts(tasks_store, "pick-place", "pick-place", tmp_path)
    stack = _rollouts(tasks_store, "pick-place", "stack", tmp_path)
    switch = _rollouts(tasks_store, "pick-place", "pick-place-changing-goal", tmp_path)
    assert stack["tip"].shape[1] > 2 * place["tip"].shape[1]  # a tower of several blocks: several placements
    metrics = tasks_store.cells["pick-place"].data.metrics
    assert 0 <= metrics["stack/blocks_in_tower_mean"] <= metrics["stack/n_blocks_mean"]  # a tower of its blocks
    assert (place["switch_step"] == -1).all() and (switch["switch_step"] > 0).all()
    assert (switch["switch_step"] < switch["tip"].shape[1]).all()
    assert np.isfinite(switch["new_goal"]).all()
    assert np.linalg.norm(switch["new_goal"] - switch["goal"], axis=1).min() > 0
    # the expert's path after the switch, for the episodes drawn in figures (smoke: eval.figures = 2)
    assert np.isfinite(switch["expert_tip"]).any(axis=(1, 2)).tolist() == [True, True, False]


def test_circle_is_evaluated_per_radius_seen_and_unseen(tasks_store, tmp_path):
    z = _rollouts(tasks_store, "circle", "circle", tmp_path)
    assert sorted(z["radius"]) == [0.05, 0.075, 0.10]  # smoke: radii 5 and 10 cm, unseen 7.5 cm, one rollout each
    np.testing.assert_allclose(z["center"], np.repeat([[0.60, 0.16, 0.00]], ROLLOUTS, axis=0))
    metrics = tasks_store.cells["circle"].data.metrics
    table = pd.read_csv(tasks_store.report / "circle_table.csv").set_index("radius_cm")
    for tag, cm in (("r5", 5.0), ("r7.5", 7.5), ("r10", 10.0)):
        assert metrics[f"circle/{tag}/n_rollouts"] == 1
        assert table.loc[cm, "rmse_mean"] == pytest.approx(metrics[f"circle/{tag}/radial_rmse"])
        assert table.loc[cm, "maxerr_mean"] == pytest.approx(metrics[f"circle/{tag}/max_radial_error_pct"])
    assert metrics["circle/radial_rmse_mean"] == pytest.approx(
        np.mean([metrics[f"circle/{t}/radial_rmse"] for t in ("r5", "r7.5", "r10")]))


def test_report_tables_are_the_stores_numbers_and_its_figures_are_drawn(tasks_store):
    table = pd.read_csv(tasks_store.report / "success_table.csv").set_index("eval_task")
    metrics = tasks_store.cells["pick-place"].data.metrics
    for e in ("pick-place", "stack", "pick-place-changing-goal"):
        assert table.loc[e, "status"] == "ok"
        assert table.loc[e, "mean"] == pytest.approx(metrics[f"{e}/success_rate"])
        assert table.loc[e, "n"] == metrics[f"{e}/n_rollouts"]
        assert table.loc[e, "ci_high"] == pytest.approx(metrics[f"{e}/success_ci_high"])
    every = pd.read_csv(tasks_store.report / "metrics_table.csv").set_index(["metric", "task"])
    circle = tasks_store.cells["circle"].data.metrics
    for key in ("circle/success_rate", "circle/radial_rmse_mean", "circle/r7.5/radial_rmse"):
        assert every.loc[(key, "circle"), "mean"] == pytest.approx(circle[key]), key
    for fig in ("circles", "changing_goal", "tip_paths", "success_bars", "training_curves"):
        assert drawn_colours(tasks_store.report / f"{fig}.png") > 10, fig  # drawn, not a blank canvas
    # the only gaps are the reacher panels (no reacher cell in this study)
    gaps = dict(re.findall(r"<li>figure <b>(\w+)</b> panels without data: ([^<]*)</li>", tasks_store.index))
    assert set(gaps) == {"success_bars", "changing_goal"}, gaps
    panels = [p for listed in gaps.values() for p in listed.split(", ")]
    assert all("reacher" in p and "pick-place" not in p for p in panels), panels


def test_report_experiment_flag_builds_only_that_kind(tasks_store, tmp_path):
    out = tmp_path / "out"
    proc = run_cli_in_process(["--out", str(out), "--experiment", "sweep", "--no-log-artifacts"], tasks_store.path,
                              module="reports")
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    assert "sweep study 'circle-sweep'" in proc.stdout and "ablation study" not in proc.stdout
    assert sorted(p.name for p in out.iterdir() if p.is_dir()) == ["circle-sweep"]
    assert (out / "circle-sweep" / "index.html").exists()
