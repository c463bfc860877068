"""Study configs, overrides, validation, hashing, the CLI's exit code 2, Wilson intervals and
the tracking helpers (fast; no training)."""

from __future__ import annotations

import math
import os
import subprocess
import sys
from pathlib import Path

import pytest

from experiments.cells import build_cells
from experiments.runtime.tracking import MetricBuffer, flatten, last_logged_step, tracking_uri, with_retries
from experiments.stats import run_success_metrics, wilson_interval
from experiments.study_config import ConfigError, available_profiles, load_profile, parse_override

REPO = Path(__file__).resolve().parents[1]


def test_profiles_exist_and_load():
    assert {"smoke", "quick", "paper"} <= set(available_profiles())
    smoke = load_profile("smoke")
    assert smoke.profile == "smoke" and smoke.seeds >= 1 and smoke.tasks
    assert smoke.resolved_study_name() == "smoke"


def test_paper_profile_has_the_paper_sizes():
    cfg = load_profile("paper")
    m, t = cfg.task_config("reacher").model, cfg.task_config("reacher").train
    assert (m.hidden_size, m.num_layers, m.mixtures, t.iters) == (64, 3, 3, 5000)
    assert (t.u, t.v) == (5, 5)
    m, t = cfg.task_config("pick-place").model, cfg.task_config("pick-place").train
    assert (m.hidden_size, m.num_layers, m.mixtures, t.iters) == (128, 3, 20, 30000)


def test_overrides_apply_and_rename_the_study():
    cfg = load_profile("smoke", ["train.iters=7", "model.sigma_min=1e-2", "eval.circle_radii=[0.05, 0.2]"])
    assert cfg.train["iters"] == 7 and cfg.model["sigma_min"] == 0.01
    assert cfg.eval.circle_radii == (0.05, 0.2)
    assert cfg.resolved_study_name().startswith("smoke-") and cfg.resolved_study_name() != "smoke"
    # selecting cells (tasks/variants/seeds/workers) does not change the study
    assert load_profile("smoke", seeds=3, workers=2).resolved_study_name() == "smoke"


def test_eval_split_stack_restart_and_success_are_options_off_the_hashes_at_their_defaults():
    """eval.split, eval.stack_restart and eval.success: at their defaults ("test", "place_pose", "strict") absent
    from the cells' and the study's hashes (earlier studies keep theirs: test_cell_keys_and_hashes_match_the_recorded_
    ones); otherwise another study, one on the validation episodes named so."""
    base = load_profile("smoke")
    assert (base.eval.split, base.eval.stack_restart, base.eval.success) == ("test", "place_pose", "strict")
    assert not {"split", "stack_restart", "success"} & set(build_cells(base)[0].resolved["eval"])
    assert load_profile("smoke", ["eval.success=placed"]).study_hash() != base.study_hash()
    validation = load_profile("smoke", ["eval.split=validation"])
    assert validation.resolved_study_name().startswith("smoke-") and validation.resolved_study_name().endswith(
        "-validation") and validation.study_hash() != base.study_hash()
    assert build_cells(validation)[0].resolved["eval"]["split"] == "validation"
    start = load_profile("smoke", ["eval.stack_restart=start"])
    assert build_cells(start)[0].resolved["eval"]["stack_restart"] == "start"
    assert not start.resolved_study_name().endswith("-validation") and start.study_hash() != base.study_hash()
    for override, allowed in (("eval.split=train", "validation"), ("eval.stack_restart=home", "place_pose"),
                              ("eval.success=loose", "placed")):
        with pytest.raises(ConfigError, match=allowed):
            load_profile("smoke", [override])


def test_parse_override_reads_toml_values():
    assert parse_override("train.iters=20") == (["train", "iters"], 20)
    assert parse_override("train.lr=1e-4") == (["train", "lr"], 1e-4)
    assert parse_override("train.detach_feedback=true") == (["train", "detach_feedback"], True)
    assert parse_override("train.feedback=sample") == (["train", "feedback"], "sample")
    assert parse_override("variants=[\"lstm\",\"ac-lstm\"]") == (["variants"], ["lstm", "ac-lstm"])
    with pytest.raises(ConfigError, match="FIELD=VALUE"):
        parse_override("train.iters")


@pytest.mark.parametrize("override, field, allowed", [
    ("train.foo=1", "train.foo", "iters"),
    ("train.iters=abc", "train.iters", "integer"),
    ("model.head=gru", "model.head", "deterministic"),
    ("train.feedback=argmax", "train.feedback", "mixture_mean"),
    ("eval.feedback=x", "eval.feedback", "component_mean"),
    ("eval.rollouts=0", "eval.rollouts", ">= 1"),
    ("variants=[\"gru\"]", "variants", "ac-lstm-mdn"),
    ("tasks=[\"nope\"]", "tasks", "reacher"),
    ("sweep.sampler=cmaes", "sweep.sampler", "tpe"),
    ("sweep.space=[\"m\",\"lr\"]", "sweep.space", "sigma_min"),
    ("bogus=1", "bogus", "variants"),
])
def test_bad_values_name_the_field_and_the_allowed_values(override, field, allowed):
    with pytest.raises(ConfigError) as info:
        load_profile("smoke", [override])
    msg = str(info.value)
    assert msg.startswith(field) and allowed in msg and "\n" not in msg


def test_per_task_data_options_reach_the_cells_and_are_checked():
    cfg = load_profile("smoke", ["per_task.reacher.data.n_demos=90"])
    cells = {c.task: c for c in build_cells(cfg)}
    assert cells["reacher"].data == {"n_demos": 90} and cfg.data_options("reacher") == {"n_demos": 90}
    base = {c.key: c.config_hash for c in build_cells(load_profile("smoke"))}
    assert base[cells["reacher"].key] != cells["reacher"].config_hash  # other data: another cell
    assert all(base[c.key] == c.config_hash for c in cells.values() if c.task != "reacher")
    with pytest.raises(ConfigError, match=r"^per_task.reacher.data.n_demo: unknown field; allowed: n_demos"):
        load_profile("smoke", ["per_task.reacher.data.n_demo=90"])
    with pytest.raises(ConfigError, match=r"^per_task.reacher.data.n_demos: expected an integer"):
        load_profile("smoke", ["per_task.reacher.data.n_demos=many"])
    with pytest.raises(ConfigError, match=r"^per_task.reacher.data: "):
        load_profile("smoke", ["per_task.reacher.data.start_joint_range=-1.0"])


def test_unknown_profile():
    with pytest.raises(ConfigError, match="profile: unknown profile 'huge'; allowed: .*smoke"):
        load_profile("huge")


def test_cells_and_hashes():
    cfg = load_profile("smoke", seeds=2)
    cells = build_cells(cfg)
    assert len(cells) == len(cfg.tasks) * len(cfg.variants) * 2
    assert len({c.config_hash for c in cells}) == len(cells)
    again = build_cells(load_profile("smoke", seeds=2))
    assert [c.config_hash for c in cells] == [c.config_hash for c in again]
    changed = build_cells(load_profile("smoke", ["train.iters=11"], seeds=2))
    assert not {c.config_hash for c in cells} & {c.config_hash for c in changed}
    by_variant = {c.variant: c for c in cells if c.seed == 0}
    assert by_variant["lstm"].train.v == 0 and by_variant["lstm"].model.head == "deterministic"
    assert by_variant["ac-lstm-mdn"].train.v > 0 and by_variant["ac-lstm-mdn"].model.head == "mdn"
    assert cells[0].eval_tasks[0] == cells[0].task


def test_wilson_matches_the_closed_form():
    z = 1.959963984540054
    for k, n in [(0, 20), (7, 20), (20, 20), (1, 3), (50, 50), (31, 50)]:
        p = k / n
        d = 1 + z * z / n
        centre = (p + z * z / (2 * n)) / d
        half = z * math.sqrt(p * (1 - p) / n + z * z / (4 * n * n)) / d
        low, high = wilson_interval(k, n)
        assert low == pytest.approx(centre - half, abs=1e-9) and high == pytest.approx(centre + half, abs=1e-9)
    s = run_success_metrics([1.0, 0.0, 1.0, 1.0])
    assert s["success_rate"] == 0.75 and s["n_rollouts"] == 4 and s["success_ci_low"] < 0.75 < s["success_ci_high"]
    assert all(math.isnan(v) for v in wilson_interval(0, 0))


def test_flatten():
    assert flatten({"a": {"b": 1, "c": [1, 2]}, "d": "x"}) == {"a.b": "1", "a.c": "1,2", "d": "x"}


def test_retries_only_on_lock_contention():
    calls = {"n": 0}

    def flaky():
        calls["n"] += 1
        if calls["n"] < 3:
            raise RuntimeError("(sqlite3.OperationalError) database is locked")
        return "ok"

    assert with_retries(flaky, base_delay=0.001)() == "ok" and calls["n"] == 3

    def broken():
        calls["n"] += 1
        raise ValueError("no such run")

    calls["n"] = 0
    with pytest.raises(ValueError):
        with_retries(broken, base_delay=0.001)()
    assert calls["n"] == 1


def test_tracking_uri_default_and_env(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    monkeypatch.delenv("MLFLOW_TRACKING_URI", raising=False)
    assert tracking_uri() == "sqlite:///mlflow.db"  # relative: no path of this machine in what it writes
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "sqlite:///sub/x.db")
    assert tracking_uri() == "sqlite:///sub/x.db"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://tracking:5000")
    assert tracking_uri() == "http://tracking:5000"


@pytest.mark.slow
def test_metric_buffer_batches(tmp_path):
    from experiments.runtime.tracking import Client, get_or_create_experiment

    client = Client(f"sqlite:///{tmp_path / 'm.db'}")
    exp = get_or_create_experiment(client, "unit")
    run = client.create_run(exp).info.run_id
    buf = MetricBuffer(client, run, max_pending=1000, flush_seconds=3600)
    for i in range(1, 31):
        buf.add(i, {"train/loss": 1.0 / i})
    assert client.get_metric_history(run, "train/loss") == []  # nothing written until a flush
    buf.flush()
    hist = client.get_metric_history(run, "train/loss")
    assert [m.step for m in hist] == list(range(1, 31))
    resumed = MetricBuffer(client, run, flush_seconds=0.0, skip_through=last_logged_step(client, run, ["train/loss"]))
    for i in range(25, 41):  # steps 25..30 are recomputed after a resume: not logged twice
        resumed.add(i, {"train/loss": 1.0 / i})
    assert [m.step for m in client.get_metric_history(run, "train/loss")] == list(range(1, 41))


def _cli(args: list[str], cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    env.pop("MLFLOW_TRACKING_URI", None)
    return subprocess.run([sys.executable, "-m", "experiments", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=120)


@pytest.mark.parametrize("args, field", [
    (["ablation", "--profile", "smoke", "--variants", "gru"], "variants"),
    (["ablation", "--profile", "smoke", "--tasks", "juggling"], "tasks"),
    (["ablation", "--profile", "smoke", "--set", "train.iters=-5"], "train.iters"),
    (["ablation", "--profile", "nope"], "profile"),
    (["sweep", "--profile", "smoke", "--space", "m,lr"], "sweep.space"),
    (["sweep", "--profile", "smoke", "--set", "train.val_every=0"], "train.val_every"),
])
def test_cli_rejects_bad_configs_with_exit_2_before_writing(tmp_path, args, field, monkeypatch, capsys):
    """In this process (the command line's own start-up is checked below and in test_cli_codes.py)."""
    from experiments.cli import main

    (tmp_path / "mlflow.db").write_bytes(b"")  # an existing (empty) store must stay untouched
    before = sorted(p.name for p in tmp_path.iterdir())
    monkeypatch.chdir(tmp_path)
    assert main(args) == 2
    stderr = capsys.readouterr().err
    err_lines = [ln for ln in stderr.splitlines() if ln.startswith("error:")]
    assert len(err_lines) == 1 and err_lines[0].startswith(f"error: {field}") and "allowed" in err_lines[0]
    assert sorted(p.name for p in tmp_path.iterdir()) == before
    assert (tmp_path / "mlflow.db").read_bytes() == b""


def test_sweep_study_names_separate_different_settings():
    from experiments.sweeps.runner import study_name

    base = study_name(load_profile("smoke"))
    assert base == "reacher-ac-lstm-mdn-smoke"
    assert study_name(load_profile("smoke", ["sweep.trials=9"])) == base  # a re-run continues it
    assert study_name(load_profile("smoke", ["train.iters=9"])) != base
    assert study_name(load_profile("smoke", ["sweep.space=[\"m\"]"])) != base
    assert study_name(load_profile("smoke", ["sweep.study_name=x"])) == "x"


def test_cell_keys_and_hashes_match_the_recorded_ones():
    """A re-run on an existing store skips cells whose config hash it finds FINISHED: the keys
    and hashes of every profile (recorded on main 991f874, tests/data/cell_hashes.json) must not
    move, or every cell of every existing study would be retrained. The paper profile's entry was
    re-recorded on 1 Dec 2026 when that profile became the headline protocol, quick's
    the same day when its pick-and-place iterations rose to 2,000 and on 2 Dec when its rollouts per
    seed went from 50 to 40. The paper entry again on 6 Dec, when the profile judged pick-and-place on the block
    (eval.success = placed, chosen on validation episodes): its hashes are those `--set eval.success=placed` gave
    before (the pick-and-place v2 studies' cells keep theirs); the earlier paper studies' strict cells resume
    with `--set eval.success=strict` and their --study-name."""
    import json

    recorded = json.loads((REPO / "tests" / "data" / "cell_hashes.json").read_text())
    configs = {p: load_profile(p) for p in ("smoke", "quick", "results", "paper")}
    configs["smoke+train.iters=7+per_task.reacher.data.n_demos=90+seeds=2"] = load_profile(
        "smoke", ["train.iters=7", "per_task.reacher.data.n_demos=90"], seeds=2)
    for name, cfg in configs.items():
        got = {"study_name": cfg.resolved_study_name(), "study_hash": cfg.study_hash(),
               "cells": {c.key: c.config_hash for c in build_cells(cfg)}}
        assert got == recorded[name], name


@pytest.mark.slow
def test_a_profile_file_that_does_not_parse_is_one_line_naming_the_file_and_line(tmp_path, monkeypatch, capsys):
    """A TOML syntax error was a 30-line tomllib traceback and exit 1."""
    bad = tmp_path / "mine.toml"
    bad.write_text('tasks = ["reacher"]\nseeds = \n')
    from experiments.cli import main

    proc = _cli(["ablation", "--profile", str(bad)], tmp_path)  # the command line, from its start-up
    assert proc.returncode == 2, proc.stderr
    outputs = [proc.stderr]
    monkeypatch.chdir(tmp_path)
    for command in ("sweep", "smoothing", "idm"):  # the same path in this process: seconds less each
        assert main([command, "--profile", str(bad)]) == 2
        outputs.append(capsys.readouterr().err)
    for err in outputs:
        lines = [ln for ln in err.splitlines() if ln.strip() and not ln.startswith("pybullet build time")]
        assert len(lines) == 1 and "mine.toml" in lines[0] and "line 2" in lines[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mine.toml"]


def test_a_profile_can_be_any_toml_file(tmp_path):
    from experiments.control_studies import load_config

    own = tmp_path / "tiny.toml"
    own.write_text((REPO / "experiments" / "profiles" / "smoke.toml").read_text().replace("seeds = 1", "seeds = 3"))
    cfg = load_profile(str(own))
    assert (cfg.profile, cfg.seeds, cfg.resolved_study_name()) == ("tiny", 3, "tiny")
    smoke = {c.key.replace("seed0", "s"): c.config_hash for c in build_cells(load_profile("smoke"))}
    assert {c.key.replace("seed0", "s"): c.config_hash for c in build_cells(cfg) if c.seed == 0} == smoke
    assert load_config("smoothing", str(own), []).study.iters == 50
    with pytest.raises(ConfigError, match=r"^profile: .*nowhere.toml: "):
        load_profile(str(tmp_path / "nowhere.toml"))
    clash = tmp_path / "smoke.toml"
    clash.write_text(own.read_text())
    with pytest.raises(ConfigError, match="built-in profile"):  # its studies would mix with smoke's
        load_profile(str(clash))


def test_the_study_name_tells_studies_of_other_tasks_and_variants_apart():
    """Studies with different --variants shared one parent run (and overwrote its status)."""
    base = load_profile("smoke").resolved_study_name()
    lstm = load_profile("smoke", variants=["lstm"]).resolved_study_name()
    ac = load_profile("smoke", variants=["ac-lstm-mdn"]).resolved_study_name()
    assert base == "smoke" and len({base, lstm, ac}) == 3
    assert load_profile("smoke", variants=["ac-lstm-mdn", "lstm"]).resolved_study_name() == base  # same cells
    assert load_profile("smoke", tasks=["reacher", "circle"]).resolved_study_name() not in (base, lstm, ac)
    assert load_profile("smoke", seeds=3).resolved_study_name() == base  # more seeds continue the study
    # the cells themselves do not change: a cell FINISHED in one study has the same hash in another
    assert build_cells(load_profile("smoke", variants=["lstm"]))[0].config_hash == \
        {c.key: c.config_hash for c in build_cells(load_profile("smoke"))}["reacher/lstm/seed0"]


def test_set_applies_to_every_task_and_wins_over_the_profiles_per_task_values(caplog):
    """`--set train.u=3` on quick was shadowed by per_task u = 1 of reacher and pick-place."""
    with caplog.at_level("WARNING", logger="experiments.study_config"):
        cfg = load_profile("quick", ["train.u=3"], variants=["ac-lstm-mdn"])
    assert {t: cfg.task_config(t).train.u for t in cfg.tasks} == {t: 3 for t in cfg.tasks}
    assert all(c.train.u == 3 for c in build_cells(cfg))
    warnings = [r.getMessage() for r in caplog.records]
    assert len(warnings) == 1 and "per_task.reacher.train.u = 1" in warnings[0] and "pick-place" in warnings[0]
    assert cfg.task_config("reacher").train.v == 9  # only the field given on the command line
    # a per_task value given on the command line is the command line's, whatever the order
    cfg = load_profile("quick", ["per_task.reacher.train.u=2", "train.u=3"])
    assert (cfg.task_config("reacher").train.u, cfg.task_config("circle").train.u) == (2, 3)
    # the study name follows: a study where the override changed nothing stays the profile's
    assert load_profile("quick", ["train.log_every=10"]).resolved_study_name() == "quick"


def test_a_variant_that_contradicts_the_schedule_fails_with_the_config():
    """Checked when the config is resolved (the CLI no longer builds the cells twice to find out)."""
    with pytest.raises(ConfigError, match=r"^train.v: variant 'ac-lstm-mdn' uses auto-conditioning"):
        load_profile("smoke", ["train.v=0"])
    with pytest.raises(ConfigError, match=r"^per_task.reacher.train.v: variant 'ac-lstm' "):
        load_profile("quick", ["per_task.reacher.train.v=0"], variants=["ac-lstm"])
    assert load_profile("smoke", ["train.v=0"], variants=["lstm"]).task_config("reacher").train.v == 0


def test_eval_feedback_takes_every_rollout_feedback_and_train_feedback_only_the_trainable():
    from typing import get_args

    from experiments.eval_sweep_config import RolloutFeedback
    from stm.rollout import FEEDBACKS

    assert set(get_args(RolloutFeedback)) == set(FEEDBACKS)
    assert load_profile("smoke", ["eval.feedback=segment_component"]).eval.feedback == "segment_component"
    with pytest.raises(ConfigError, match=r"^train.feedback: 'segment_component' is not allowed"):
        load_profile("smoke", ["train.feedback=segment_component"])
