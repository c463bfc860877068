"""Sweeps that discriminate: several training seeds per trial (packed; the objective is
their mean), a grid over m crossed with (u, v) pairs that visits exactly its points, TPE that models
after a third of the trials, and Optuna's parameter importances on the parent run and in the report."""

from __future__ import annotations

import contextlib
import io
import os
from pathlib import Path

import optuna
import pytest
from cli_helpers import run_cli_in_process
from mlflow.tracking import MlflowClient
from optuna.storages import JournalStorage
from optuna.storages.journal import JournalFileBackend

from experiments.study_config import load_profile
from experiments.sweeps.figures import param_importances
from experiments.sweeps.objective import grid_space, suggest, uv_pairs
from experiments.sweeps.runner import check_sweep, make_sampler, planned_trials, study_name

optuna.logging.set_verbosity(optuna.logging.ERROR)
GRID = ["--sampler", "grid", "--space", "m,u,v", "--set", "sweep.grid_m=[1,2]", "--set", "sweep.grid_uv=[[1,1],[2,2]]",
        "--set", "sweep.pruner=none"]


def _study(store: Path, name: str):
    return optuna.load_study(study_name=name, storage=JournalStorage(JournalFileBackend(str(store / "optuna.journal"))))


def _main(argv: list[str], cwd: Path) -> tuple[int, str]:
    from experiments.cli import main

    err, old = io.StringIO(), os.getcwd()
    os.chdir(cwd)
    try:
        with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
            code = main(argv)
    finally:
        os.chdir(old)
    return code, err.getvalue()


@pytest.mark.slow
def test_a_grid_sweep_with_two_seeds_per_trial_and_its_importances(tmp_path):
    proc = run_cli_in_process(["sweep", "--profile", "smoke", "--workers", "1", *GRID, "--set", "sweep.seeds=2",
                               "--study-name", "g"], tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr[-3000:]
    trials = _study(tmp_path, "g").trials
    # the grid: m x the (u, v) pairs, each point once (u and v vary together, never crossed)
    assert sorted((t.params["m"], t.params["uv"]) for t in trials) == [(1, "1/1"), (1, "2/2"), (2, "1/1"), (2, "2/2")]
    assert {t.state.name for t in trials} == {"COMPLETE"}
    client = MlflowClient(f"sqlite:///{tmp_path / 'mlflow.db'}")
    for t in trials:
        run = client.get_run(t.user_attrs["mlflow_run_id"])
        m, p = run.data.metrics, run.data.params
        u, v = t.params["uv"].split("/")
        assert (p["trial.m"], p["trial.u"], p["trial.v"]) == (str(t.params["m"]), u, v)
        assert (p["model.mixtures"], p["train.u"], p["train.v"], p["seeds"]) == (str(t.params["m"]), u, v, "0,1")
        per_seed = [m["objective/seed0"], m["objective/seed1"]]
        assert per_seed[0] != per_seed[1]  # two trainings, not one counted twice
        assert m["objective"] == pytest.approx(t.value) == pytest.approx(sum(per_seed) / 2)
        # objective "val": each seed's last validation metric; the pruner saw their mean at each step
        assert per_seed == [m["seed0/val/metric"], m["seed1/val/metric"]]
        assert t.intermediate_values[max(t.intermediate_values)] == pytest.approx(t.value)

    parent = client.get_run(trials[0].user_attrs["mlflow_run_id"]).data.tags["mlflow.parentRunId"]
    parent = client.get_run(parent)
    importances = {k.removeprefix("importance/"): v for k, v in parent.data.metrics.items()
                   if k.startswith("importance/")}
    assert set(importances) == {"m", "uv"} and sum(importances.values()) == pytest.approx(1.0)
    assert parent.data.tags["importance_evaluator"] == "fANOVA"

    from reports.data.store import Store
    from reports.study_report.sweep_summary import sweep_importance, sweep_table

    (study,) = [s for s in Store(f"sqlite:///{tmp_path / 'mlflow.db'}").studies() if s.kind == "sweep"]
    table = sweep_table(study)
    assert table.title == "Sweep on reacher: all 4 complete grid points" and len(table.rows) == 4
    assert table.columns == ["rank", "trial", "objective", "per seed", "m", "u", "v"]
    note = next(n for n in table.notes if n.startswith("parameter importances (fANOVA"))
    assert f"m {importances['m']:.2f}" in note and f"(u, v) {importances['uv']:.2f}" in note
    assert any(n.startswith("2 training seeds per trial (0..1)") for n in table.notes)
    assert sweep_importance(study, tmp_path / "fig").paths

    # seed 0 of the pack is what seed 0 trained alone gets (train_packed = train)
    alone = run_cli_in_process(["sweep", "--profile", "smoke", "--workers", "1", "--sampler", "grid", "--space",
                                "m,u,v", "--set", "sweep.grid_m=[2]", "--set", "sweep.grid_uv=[[2,2]]", "--set",
                                "sweep.pruner=none", "--study-name", "alone"], tmp_path)
    assert alone.returncode == 0, alone.stdout + alone.stderr[-3000:]
    (single,) = _study(tmp_path, "alone").trials
    packed = next(t for t in trials if (t.params["m"], t.params["uv"]) == (2, "2/2"))
    seed0 = client.get_run(packed.user_attrs["mlflow_run_id"]).data.metrics["objective/seed0"]
    assert single.value == pytest.approx(seed0, rel=1e-4)
    assert "importance_note" not in parent.data.tags  # computed: no note
    lone = [r for r in client.search_runs([parent.info.experiment_id], "tags.role = 'parent'")
            if r.data.tags.get("study_name") == "alone"]
    assert "1 complete trial(s)" in lone[0].data.tags["importance_note"]  # one trial: a note, not a crash


def test_tpe_models_after_a_third_of_the_trials():
    """The default start-up is max(1, trials // 3); two sweeps with one seed but different objectives
    share their random start-up trials and then part (with Optuna's 10 start-up trials, a 9-trial
    sweep never left them: the review's finding)."""
    cfg = load_profile("smoke", ["sweep.trials=9"])
    assert cfg.sweep.tpe_startup is None and cfg.sweep.tpe_startup_trials() == 3
    assert load_profile("smoke", ["sweep.trials=20"]).sweep.tpe_startup_trials() == 6
    assert load_profile("smoke", ["sweep.trials=2"]).sweep.tpe_startup_trials() == 1
    assert load_profile("smoke", ["sweep.tpe_startup=5"]).sweep.tpe_startup_trials() == 5
    space = ("m", "u", "v")
    drawn = []
    for sign in (1, -1):
        study = optuna.create_study(sampler=make_sampler(cfg))
        study.optimize(lambda t, s=sign: s * sum(suggest(t, space).values()), n_trials=9)
        drawn.append([t.params for t in study.trials])
    assert drawn[0][:3] == drawn[1][:3]
    assert drawn[0][3:] != drawn[1][3:]
    # each worker process draws its own values
    other = optuna.create_study(sampler=make_sampler(cfg, worker=1))
    other.optimize(lambda t: sum(suggest(t, space).values()), n_trials=3)
    assert [t.params for t in other.trials] != drawn[0][:3]


def test_the_grid_space_pairs_u_and_v_and_caps_the_trials():
    cfg = load_profile("smoke", ["sweep.sampler=\"grid\"", "sweep.space=[\"m\", \"u\", \"v\"]",
                                 "sweep.grid_uv=[[1, 9], [5, 5], [2, 2]]", "sweep.trials=40"])
    assert grid_space(cfg.sweep) == {"m": [1, 3, 5, 10, 20], "uv": ["1/9", "5/5", "2/2"]}
    assert planned_trials(cfg) == 15
    crossed = load_profile("smoke", ["sweep.sampler=\"grid\"", "sweep.space=[\"m\", \"u\", \"v\"]"])
    assert uv_pairs(crossed.sweep) == () and len(grid_space(crossed.sweep)["v"]) == 5
    assert planned_trials(crossed) == 4  # the smoke profile's trials: fewer than the 100 points
    # the study name: unchanged at the defaults (existing studies continue), new for seeds or another grid
    base = load_profile("smoke")
    assert study_name(base) == "reacher-ac-lstm-mdn-smoke"
    names = {study_name(c) for c in (base, load_profile("smoke", ["sweep.seeds=2"]), cfg, crossed)}
    assert len(names) == 4
    check_sweep(cfg)


@pytest.mark.parametrize("override, field", [
    ("sweep.grid_m=[0, 3]", "sweep.grid_m: 0 is not allowed; allowed: integers 1..20"),
    ("sweep.grid_uv=[1, 9]", "sweep.grid_uv: [1, 9] is not allowed; allowed: a list of [u, v] pairs"),
    ("sweep.grid_uv=[[1, 11]]", "sweep.grid_uv: 11 is not allowed as v of a pair; allowed: integers 0..10"),
    ("sweep.grid_v=[2, 2]", "sweep.grid_v: a value appears twice"),
    ("sweep.seeds=0", "sweep.seeds: 0 is not allowed; allowed: integers >= 1"),
])
def test_a_bad_grid_value_is_a_one_line_error_with_exit_2(tmp_path, monkeypatch, override, field):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    code, err = _main(["sweep", "--profile", "smoke", "--sampler", "grid", "--set", override], tmp_path)
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: {field}"), err
    assert list(tmp_path.iterdir()) == []  # nothing written


def test_pairs_without_v_in_the_space_are_an_error(tmp_path, monkeypatch):
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    code, err = _main(["sweep", "--profile", "smoke", "--sampler", "grid", "--space", "m,u",
                       "--set", "sweep.grid_uv=[[1, 9]]"], tmp_path)
    assert code == 2 and err.startswith("error: sweep.grid_uv: (u, v) pairs need both u and v"), err


def test_importances_or_a_note_why_not():
    def study(values: list[tuple[int, str, float]]):
        s = optuna.create_study()
        for m, uv, value in values:
            s.enqueue_trial({"m": m, "uv": uv})
            s.optimize(lambda t, v=value: (t.suggest_int("m", 1, 20, log=True),
                                           t.suggest_categorical("uv", ["1/9", "5/5"]), v)[-1], n_trials=1)
        return s

    imp, note = param_importances(study([(1, "1/9", 1.0), (1, "5/5", 3.0), (5, "1/9", 1.1), (5, "5/5", 3.2)]), 0)
    assert note == "" and list(imp) == ["uv", "m"] and sum(imp.values()) == pytest.approx(1.0)
    assert imp["uv"] > 3 * imp["m"]
    assert param_importances(study([(1, "1/9", 1.0)]), 0) == (
        {}, "parameter importances need >= 2 complete trials and >= 2 swept parameters; this sweep has 1 "
            "complete trial(s) and 2 parameter(s)")
    imp, note = param_importances(study([(1, "1/9", 2.0), (5, "5/5", 2.0)]), 0)
    assert imp == {} and "same objective" in note


def test_sweep_figures_leave_the_process_style_as_it_was(tmp_path):
    """optuna's matplotlib plots set the ggplot style process-wide; a sweep's figures keep it to themselves, so that
    a figure drawn later in the same process (a report, a notebook) keeps its colours."""
    import matplotlib

    from experiments.sweeps.figures import sweep_figures

    s = optuna.create_study()
    s.optimize(lambda t: (t.suggest_int("m", 1, 20, log=True) - 3) ** 2 + t.suggest_float("u", 0, 1), n_trials=3)
    before = dict(matplotlib.rcParams)
    paths = sweep_figures(s, tmp_path)
    assert {p.stem for p in paths} >= {"optimization_history", "slice"}
    after = dict(matplotlib.rcParams)
    # the style's entries unchanged (sweep_figures chooses the Agg backend, which is not a style)
    assert {k for k in before if before[k] != after[k] and not k.startswith("backend")} == set()
