"""reports.analyses.multimodal on a real tiny study: a smoke-sized ablation of both multimodal tasks through the
experiments CLI (two seeds), then the table (success, intervals, mode split) and the mode-coloured paths."""

from __future__ import annotations

import math

import numpy as np
import pytest
from cli_helpers import run_cli_in_process
from oracles import drawn_colours, is_pdf, wilson

from reports.analyses.multimodal import (
    feedback_table,
    mode_paths,
    multimodal_markdown,
    multimodal_table,
    multimodal_tasks,
    rollout_feedback_of,
)
from reports.data.store import Store

TASKS = ("reacher-obstacle-multimodal", "reacher-posture-multimodal")
ROLLOUTS, SEEDS = 4, 2

pytestmark = pytest.mark.slow


@pytest.fixture(scope="module")
def study(tmp_path_factory):
    store = tmp_path_factory.mktemp("mm-store")
    args = ["ablation", "--profile", "smoke", "--tasks", *TASKS, "--seeds", str(SEEDS), "--workers", "1",
            "--study-name", "mm-tiny", "--set", f"eval.rollouts={ROLLOUTS}", "--set", "eval.figures=0",
            "--set", "train.val_every=0"]
    args += [a for t in TASKS for a in ("--set", f"per_task.{t}.data.n_demos=6")]
    done = run_cli_in_process(args, store)
    assert done.returncode == 0, done.stderr[-3000:]
    (found,) = Store(f"sqlite:///{store / 'mlflow.db'}").studies(study="mm-tiny")
    return found


def test_multimodal_tasks_are_found_from_the_logged_mode_rates(study):
    assert multimodal_tasks(study) == {TASKS[0]: ["left", "right"], TASKS[1]: ["j2_pos", "j2_neg"]}


def test_table_rows_are_the_runs_numbers_and_the_rollouts_labels(study):
    table = multimodal_table(study)
    assert list(zip(table["eval_task"], table["variant"], strict=True)) == [
        (t, v) for t in TASKS for v in ("lstm", "ac-lstm-mdn")]
    for row in table.to_dict("records"):
        task = row["eval_task"]
        runs = study.ok[(study.ok["variant"] == row["variant"]) & study.ok[f"metrics.{task}/success_rate"].notna()]
        assert row["n"] == ROLLOUTS * SEEDS and row["seeds"] == SEEDS
        rates = runs[f"metrics.{task}/success_rate"].to_numpy()
        assert row["success"] == pytest.approx(rates.mean())
        low, high = wilson(int(round(rates.sum() * ROLLOUTS)), ROLLOUTS * SEEDS)
        assert (row["ci_low"], row["ci_high"]) == pytest.approx((low, high))
        assert row["seed_low"] <= row["success"] <= row["seed_high"]
        # the split is what the rollouts artifacts label, episode by episode (one-hot: modes + between = 1)
        arrays = [study.rollouts(r, task) for r in runs["run_id"]]
        modes = multimodal_tasks(study)[task]
        for key in [f"mode_{m}" for m in modes] + ["between"]:
            pooled = np.concatenate([a[key] for a in arrays])
            assert pooled.shape == (ROLLOUTS * SEEDS,) and row[key] == pytest.approx(pooled.mean())
        assert sum(row[f"mode_{m}"] for m in modes) + row["between"] == pytest.approx(1.0)
        success = np.concatenate([a["success"] for a in arrays])
        assert success.mean() == pytest.approx(row["success"])
        has_collided = task == TASKS[0]  # the obstacle task labels contact with the pillar; the posture task has none
        assert math.isnan(row["collided"]) != has_collided
    text = multimodal_markdown(table)
    assert f"**{TASKS[0]}**" in text and "| left | right | between | collided |" in text
    assert "| j2_pos | j2_neg | between |" in text


def test_feedback_table_names_each_studys_rollout_feedback(study):
    assert rollout_feedback_of(study) == "component_mean"  # the smoke profile's default, as the runs logged it
    both = feedback_table([study, study])
    assert len(both) == 2 * len(multimodal_table(study)) and set(both["study"]) == {"mm-tiny"}
    assert list(both["variant"][:2]) == ["lstm", "lstm"]  # a variant's rows together, the studies in order
    assert "| feedback | variant |" in multimodal_markdown(both)


def test_mode_paths_draws_demonstrations_and_every_variant(study, tmp_path):
    fig = mode_paths(study, tmp_path)
    assert fig.gap is None and fig.partial == []  # every panel drawn: the rollouts carry their labels
    png, pdf = sorted(fig.paths)[::-1]
    assert png.suffix == ".png" and is_pdf(pdf)
    assert drawn_colours(png) > 50
