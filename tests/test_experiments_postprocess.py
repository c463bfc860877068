"""`python -m experiments smoothing|idm` at the smoke profile into a temporary SQLite store: runs,
tags, params, metrics, artifacts; the STM checkpoint source; bad config -> exit 2 before anything is
written; and the report's tables and figures built from that store."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np
import pytest
import torch
from mlflow.tracking import MlflowClient

from experiments.cli import main
from experiments.control_studies import load_config

pytestmark = pytest.mark.slow  # every test runs a study or the CLI


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    """Both smoke studies run once into one store (seconds each)."""
    root = tmp_path_factory.mktemp("postprocess")
    mp = pytest.MonkeyPatch()
    mp.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{root / 'mlflow.db'}")
    mp.setenv("ACRMDN_CACHE", str(root / "cache"))  # IDM datasets: never the shared cache
    mp.chdir(root)
    try:
        assert main(["smoothing", "--profile", "smoke"]) == 0
        assert main(["idm", "--profile", "smoke"]) == 0
        yield root, MlflowClient(f"sqlite:///{root / 'mlflow.db'}")
    finally:
        mp.undo()


def _parent(client: MlflowClient, kind: str):
    exp = client.get_experiment_by_name(kind)
    assert exp is not None, f"no experiment {kind!r}"
    runs = client.search_runs([exp.experiment_id])
    assert len(runs) == 1
    return runs[0]


def _artifacts(client: MlflowClient, run_id: str, folder: str) -> set[str]:
    return {f.path for f in client.list_artifacts(run_id, folder)}


def test_smoothing_study_is_tracked(store):
    _, client = store
    run = _parent(client, "smoothing")
    tags, m, p = run.data.tags, run.data.metrics, run.data.params
    assert run.info.status == "FINISHED"
    assert (tags["kind"], tags["profile"], tags["study_name"], tags["role"]) == \
        ("smoothing", "smoke", "smoothing-smoke", "parent")
    assert tags["skeleton_source"].startswith("stand-in")  # no ablation run in this store
    assert p["iters"] == "50" and p["steps"] == "20" and p["gamma"] == "5.0" and "git_commit" in p
    assert m["gd_goal/mean_sq_jerk"] < 0.1 * m["skeleton/mean_sq_jerk"]  # smoothing removes the jitter
    assert m["gd_goal/goal_error_m"] < m["skeleton/goal_error_m"]  # the goal term pulls the end to the goal
    assert m["skeleton/deviation_rad"] == 0 and m["gd/deviation_rad"] > 0
    assert m["time_exact_s"] > 0 and m["time_gd_s"] > 0
    assert {"figures/smoothing_tip_paths.png", "figures/smoothing_tip_paths.pdf"} <= \
        _artifacts(client, run.info.run_id, "figures")


def test_idm_study_is_tracked(store):
    _, client = store
    run = _parent(client, "idm")
    tags, m, p = run.data.tags, run.data.metrics, run.data.params
    assert run.info.status == "FINISHED"
    assert (tags["kind"], tags["profile"], tags["study_name"]) == ("idm", "smoke", "idm-smoke")
    assert tags["skeleton_source"] == "stand-in:ik-expert"
    assert p["idm.epochs"] == "3" and p["data.episodes"] == "4" and p["real_mass"] == "0.2"
    assert len(tags["data_hash"]) == 16 and "real_dynamics.mass_scale" in tags
    # the position-control reference, recomputed here with pybullet's own forward kinematics
    pos = _position_reference(load_config("idm", "smoke", []).study)
    for name, value in pos.items():
        assert m[f"position/{name}"] == pytest.approx(value, abs=1e-5), name
    for cond in ("sim", "real_sim_idm", "real_finetuned"):
        rmse, max_err, to_pos = (m[f"{cond}/{k}"] for k in ("tip_rmse_vs_plan_m", "max_tip_error_m",
                                                               "tip_rmse_vs_position_m"))
        assert 4 * m[f"{cond}/success_rate"] in (0, 1, 2, 3, 4)  # a fraction of the four plans
        assert 0 < rmse <= max_err  # per plan, an RMS never exceeds the largest error
        # the tip's distance to the position-control path, per step, is within the plan's distance
        # to each: triangle inequality, kept by the RMS (a norm) and by the mean over plans
        assert abs(rmse - pos["tip_rmse_vs_plan_m"]) - 1e-9 <= to_pos <= rmse + pos["tip_rmse_vs_plan_m"] + 1e-9
    assert m["latency_fast_ms"] > 0 and m["data_samples"] > 0
    arts = _artifacts(client, run.info.run_id, "figures") | _artifacts(client, run.info.run_id, "idm")
    assert {"figures/idm_tracking.png", "figures/idm_tracking.pdf", "idm/idm_sim.pt", "idm/idm_finetuned.pt"} <= arts


def _pybullet_tips(qs) -> np.ndarray:
    """The tool tip of each joint vector, read from pybullet after a reset (not the torch FK the study uses)."""
    from envs.sim import Scene

    with Scene(table=False) as scene:
        out = []
        for q in qs:
            scene.robot.reset(q)
            out.append(scene.robot.link_pose(scene.robot.tip)[0])
    return np.array(out)


def _position_reference(cfg) -> dict[str, float]:
    """The IDM study's position condition from its definition: the expert's straight-line plans to the
    four goals, played in position control; RMS and largest tip distance to the plan, final distance to
    the goal, success within the reacher's 5 cm; means over the plans."""
    from stm.control.idm_study import position_playback_tips
    from stm.control.plans import FOUR_GOALS, straight_line_plans

    assert cfg.smoothing_gamma == 0  # the smoke profile plays the plans as they are
    plans = straight_line_plans(FOUR_GOALS, steps=cfg.plan_steps)
    played = position_playback_tips(plans, cfg.step_seconds)
    dist = np.array([np.linalg.norm(tips - _pybullet_tips(plan), axis=-1)
                     for tips, plan in zip(played, plans, strict=True)])
    final = np.linalg.norm(played[:, -1] - FOUR_GOALS, axis=-1)
    return {"tip_rmse_vs_plan_m": float(np.sqrt((dist**2).mean(axis=1)).mean()),
            "max_tip_error_m": float(dist.max(axis=1).mean()), "final_error_m": float(final.mean()),
            "success_rate": float((final < 0.05).mean())}


def test_report_shows_the_studies(store, tmp_path):
    root, _ = store
    from reports.__main__ import main as report_main

    mp = pytest.MonkeyPatch()
    mp.chdir(root)
    try:
        assert report_main(["--out", str(tmp_path), "--no-log-artifacts"]) == 0
    finally:
        mp.undo()
    for study, fig, table in (("smoothing-smoke", "smoothing_tip_paths", "smoothing_table"),
                              ("idm-smoke", "idm_tracking", "idm_table")):
        folder = tmp_path / study
        html = (folder / "index.html").read_text()
        assert f"src='{fig}.png'" in html and "gap:" not in html
        assert (folder / f"{fig}.png").stat().st_size > 1000 and (folder / f"{fig}.pdf").exists()
        md = (folder / f"{table}.md").read_text()
        assert "gap" not in md.split("\n- ")[0]  # every entry of the table has its number
        assert f"{study}/index.html" in (tmp_path / "index.html").read_text()
    assert "gradient descent + goal term" in (tmp_path / "smoothing-smoke" / "smoothing_table.md").read_text()
    assert "IDM fine-tuned on perturbed robot" in (tmp_path / "idm-smoke" / "idm_table.md").read_text()


@pytest.mark.parametrize("argv, field", [
    (["smoothing", "--set", "iters=0"], "iters"),
    (["smoothing", "--set", "gama=1"], "gama"),
    (["smoothing", "--set", "gamma=-1"], "gamma"),
    (["smoothing", "--profile", "huge"], "profile"),
    (["smoothing", "--set", "skeletons=best"], "skeletons"),
    (["idm", "--set", "idm.point=median"], "idm.point"),
    (["idm", "--set", "idm.hidden=1.5"], "idm.hidden"),
    (["idm", "--set", "data.episodes=0"], "data"),
    (["idm", "--set", "real_damping=[2, 1]"], "real_damping"),
    (["idm", "--set", "data.dynamics=1"], "data.dynamics"),
])
def test_bad_config_is_one_line_exit_2_and_writes_nothing(argv, field, tmp_path, monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", f"sqlite:///{tmp_path / 'mlflow.db'}")
    monkeypatch.chdir(tmp_path)
    assert main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {field}"), err
    assert not (tmp_path / "mlflow.db").exists()


def test_overrides_change_the_study_name():
    assert load_config("smoothing", "quick", []).resolved_study_name() == "smoothing-quick"
    other = load_config("smoothing", "quick", ["gamma=2.0"]).resolved_study_name()
    assert other.startswith("smoothing-quick-") and other != "smoothing-quick"
    cfg = load_config("idm", "smoke", ["idm.epochs=1", "plan_steps=10"])
    assert cfg.study.idm.epochs == 1 and cfg.study.plan_steps == 10 and cfg.study.data.episodes == 4  # smoke kept


def _fake_ablation_cell(client: MlflowClient, work: Path) -> str:
    """A FINISHED reacher/ac-lstm-mdn ablation run holding a (small, untrained) STM checkpoint."""
    from envs.tasks.registry import get_task
    from stm.config import ModelConfig, TrainConfig
    from stm.model import STM, layout_to_dict
    from stm.training.checkpoint import FORMAT_VERSION, save_checkpoint

    task = get_task("reacher")
    cfg = ModelConfig(hidden_size=8, num_layers=1, mixtures=2)
    model = STM(cfg, task.layout)
    payload = {"format_version": FORMAT_VERSION, "model": model.state_dict(), "model_config": cfg.to_dict(),
               "train_config": TrainConfig().to_dict(), "layout": layout_to_dict(task.layout), "task": "reacher",
               "iteration": 0}
    path = save_checkpoint(payload, work / "model.pt")
    exp = client.create_experiment("ablation")
    run = client.create_run(exp, tags={"task": "reacher", "variant": "ac-lstm-mdn", "role": "cell"})
    client.log_artifact(run.info.run_id, str(path), "checkpoint")
    client.set_terminated(run.info.run_id, "FINISHED")
    return run.info.run_id


def test_skeletons_from_an_ablation_checkpoint(tmp_path, monkeypatch, capsys):
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    assert main(["smoothing", "--profile", "smoke", "--set", "skeletons=stm"]) == 2  # none in the store yet
    assert "skeletons: 'stm' needs" in capsys.readouterr().err
    assert not (tmp_path / "mlflow.db").exists()  # the error came before anything was written
    client = MlflowClient(uri)
    torch.manual_seed(0)
    run_id = _fake_ablation_cell(client, tmp_path)
    assert main(["smoothing", "--profile", "smoke", "--set", "skeletons=stm"]) == 0
    run = _parent(client, "smoothing")
    assert run.data.tags["skeleton_source"] == f"stm:{run_id}"
    assert run.data.tags["study_name"] == "smoothing-smoke-stm"  # apart from the stand-in's study
    # the skeletons are this checkpoint's plans: their end's distance to the goals, recomputed from the model
    from stm.control.plans import FOUR_GOALS, stm_plans
    from stm.training.checkpoint import load_model

    steps = load_config("smoothing", "smoke", []).study.steps
    plans = stm_plans(load_model(tmp_path / "model.pt"), FOUR_GOALS, horizon=steps)
    expected = np.linalg.norm(_pybullet_tips(plans[:, -1]) - FOUR_GOALS, axis=-1).mean()
    m = run.data.metrics
    assert m["skeleton/goal_error_m"] == pytest.approx(expected, abs=1e-5)
    assert m["gd_goal/goal_error_m"] < m["skeleton/goal_error_m"]  # the goal term pulls the end to the goal


def test_report_of_a_study_without_figures_shows_gaps(tmp_path, monkeypatch):
    """A smoothing run that died before its figures: the report lists the gaps instead of failing."""
    from reports.__main__ import main as report_main

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("smoothing")
    run = client.create_run(exp, tags={"kind": "smoothing", "profile": "smoke", "study_name": "broken",
                                       "role": "parent"})
    client.log_metric(run.info.run_id, "skeleton/mean_sq_jerk", 12.5)
    client.set_terminated(run.info.run_id, "FAILED")
    monkeypatch.chdir(tmp_path)
    assert report_main(["--tracking-uri", uri, "--out", str(tmp_path / "out"), "--no-log-artifacts"]) == 0
    html = (tmp_path / "out" / "broken" / "index.html").read_text()
    assert "smoothing_tip_paths</b>: no figures/smoothing_tip_paths.png" in html and "FAILED" in html
    md = (tmp_path / "out" / "broken" / "smoothing_table.md").read_text()
    assert re.search(r"\| skeleton \(before\) +\| 12\.5 +\| gap +\|", md)


def test_a_failing_study_is_recorded_and_a_rerun_clears_it(tmp_path, monkeypatch, capsys):
    import stm.control.smoothing

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    monkeypatch.setenv("MLFLOW_TRACKING_URI", uri)
    monkeypatch.chdir(tmp_path)
    real = stm.control.smoothing.smoothing_study

    def broken(*args, **kwargs):
        raise RuntimeError("solver exploded")

    monkeypatch.setattr(stm.control.smoothing, "smoothing_study", broken)
    assert main(["smoothing", "--profile", "smoke"]) == 1
    assert "RuntimeError: solver exploded" in capsys.readouterr().err
    run = _parent(MlflowClient(uri), "smoothing")
    assert run.info.status == "FAILED" and run.data.tags["error"] == "RuntimeError: solver exploded"
    monkeypatch.setattr(stm.control.smoothing, "smoothing_study", real)
    assert main(["smoothing", "--profile", "smoke"]) == 0
    run = _parent(MlflowClient(uri), "smoothing")  # the same study's run, now finished
    assert run.info.status == "FINISHED" and run.data.tags["error"] == "" and "gd/mean_sq_jerk" in run.data.metrics


def test_unreachable_store_is_exit_3(monkeypatch, capsys):
    monkeypatch.setenv("MLFLOW_TRACKING_URI", "http://127.0.0.1:1")  # nothing listens on port 1
    monkeypatch.setenv("ACRMDN_STORE_ATTEMPTS", "1")
    assert main(["idm", "--profile", "smoke"]) == 3
    assert capsys.readouterr().err.count("\n") == 1
