"""Reports from a real MLflow sqlite store built here per the logging schema (notes/api.md + artifacts.md)."""

from __future__ import annotations

import json
import math
import re
from pathlib import Path

import numpy as np
import pytest
from mlflow import MlflowClient
from mlflow.entities import Metric, Param
from oracles import drawn_colours, is_pdf
from scipy.stats import binomtest

from experiments.stats import wilson_interval
from reports.__main__ import main
from reports.data.store import Store
from reports.study_report.build import build_report
from reports.study_report.tables import success_summary

VARIANTS = ("lstm", "ac-lstm-mdn")
SEEDS = (0, 1)
N_ROLLOUTS = 10
# (variant, seed) -> success rate logged for eval task "reacher" / "reacher-changing-goal"
REACHER = {("lstm", 0): 0.6, ("lstm", 1): 0.8, ("ac-lstm-mdn", 0): 0.9, ("ac-lstm-mdn", 1): 1.0}
CHANGING = {("lstm", 0): 0.3, ("lstm", 1): 0.5, ("ac-lstm-mdn", 0): 0.7, ("ac-lstm-mdn", 1): 0.0}
FAILED = ("ac-lstm-mdn", 1)  # this reacher cell's run FAILED (its logged metrics must not count)
RMSE = {("lstm", 5): 0.02, ("lstm", 10): 0.03, ("ac-lstm-mdn", 5): 0.01, ("ac-lstm-mdn", 10): 0.015}


def _rollouts(rng: np.random.Generator, task: str, b: int = 3, h: int = 12) -> dict[str, np.ndarray]:
    t = np.linspace(0, 1, h + 1)[None, :, None]
    start, goal = rng.uniform(-0.3, 0.3, (b, 1, 3)), rng.uniform(-0.3, 0.3, (b, 3))
    arrays = {"tip": start + t * (goal[:, None] - start), "goal": goal, "success": np.ones(b),
              "final_distance": np.full(b, 0.01), "switch_step": np.full(b, -1),
              "new_goal": np.full((b, 3), np.nan), "radius": np.full(b, np.nan), "center": np.full((b, 3), np.nan)}
    if task.endswith("changing-goal"):
        arrays["new_goal"] = goal + 0.1
        arrays["switch_step"] = np.full(b, h // 2)
        arrays["expert_tip"] = start + t * (arrays["new_goal"][:, None] - start)
    if task == "circle":
        radius = np.resize([0.05, 0.10, 0.05], b)
        ang = np.linspace(0, 2 * np.pi, h + 1)
        center = np.tile([0.6, 0.0, 0.1], (b, 1))
        arrays["tip"] = center[:, None] + radius[:, None, None] * 1.05 * np.stack(
            [np.cos(ang), np.sin(ang), np.zeros_like(ang)], -1)[None]
        arrays.update(radius=radius, center=center, goal=np.full((b, 3), np.nan))
    return arrays


def _child(client, exp, parent, task, variant, seed, metrics, status="FINISHED", artifacts=None, tmp=None,
           params=None, extra_tags=None):
    tags = {"mlflow.parentRunId": parent, "task": task, "variant": variant, "seed": str(seed), "profile": "smoke",
            "config_hash": f"h{task}{variant}{seed}", **(extra_tags or {})}
    run = client.create_run(exp, tags=tags)
    rid = run.info.run_id
    batch = [Metric(k, float(v), 0, 0) for k, v in metrics.items()]
    batch += [Metric("train/loss", 2.0 / (i + 1) + 0.1 * seed, 0, i * 10) for i in range(15)]
    client.log_batch(rid, metrics=batch, params=[Param(k, str(v)) for k, v in (params or {}).items()])
    for name, content in (artifacts or {}).items():
        path = Path(tmp) / rid / name
        path.parent.mkdir(parents=True, exist_ok=True)
        if isinstance(content, bytes):
            path.write_bytes(content)
        elif name.endswith(".npz"):
            np.savez_compressed(path, **content)
        else:
            path.write_text(json.dumps(content))
        client.log_artifact(rid, str(path), "rollouts")
    client.set_terminated(rid, status)
    return rid


@pytest.fixture(scope="module")
def store(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("store")
    uri = f"sqlite:///{tmp / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("ablation", artifact_location=(tmp / "artifacts").as_uri())
    # An older study without usable artifacts (a corrupt npz): it must still build, with gaps.
    old = client.create_run(exp, tags={"kind": "ablation", "profile": "smoke", "study_name": "old-study"})
    _child(client, exp, old.info.run_id, "reacher", "lstm", 0,
           {"reacher/success_rate": 0.5, "reacher/n_rollouts": 4},
           artifacts={"reacher.npz": b"not an npz file"}, tmp=tmp)
    client.set_terminated(old.info.run_id)
    parent = client.create_run(exp, tags={"kind": "ablation", "profile": "smoke", "study_name": "test-study"})
    pid = parent.info.run_id
    rng = np.random.default_rng(0)
    ids = {}
    for v in VARIANTS:
        for s in SEEDS:
            metrics = {"reacher/success_rate": REACHER[v, s], "reacher/n_rollouts": N_ROLLOUTS,
                       "reacher-changing-goal/success_rate": CHANGING[v, s],
                       "reacher-changing-goal/n_rollouts": N_ROLLOUTS,
                       "time/train_seconds": 10.0 + s, "time/generation_seconds_per_traj": 0.01,
                       "time/ik_seconds_per_traj": 0.03}
            arts = {}
            if s == 0:
                arts = {f"{t}.npz": _rollouts(rng, t) for t in ("reacher", "reacher-changing-goal")}
            ids[v, s] = _child(client, exp, pid, "reacher", v, s, metrics,
                               status="FAILED" if (v, s) == FAILED else "FINISHED", artifacts=arts, tmp=tmp)
        circle = {f"circle/r{r:g}/radial_rmse": RMSE[v, r] for r in (5, 10)}
        circle |= {f"circle/r{r:g}/max_radial_error_pct": 100 * RMSE[v, r] / (r / 100) for r in (5, 10)}
        timing = {"circle": {"n_trajectories": 3, "batch_size": 3, "horizon": 12, "stm_seconds_per_traj": 0.02,
                             "stm_batched_seconds_per_traj": 0.004, "ik_seconds_per_traj": 0.05,
                             "ik_batched_seconds_per_traj": 0.01}}
        _child(client, exp, pid, "circle", v, 0, circle | {"time/train_seconds": 5.0},
               artifacts={"circle.npz": _rollouts(rng, "circle"), "ik_timing.json": timing}, tmp=tmp,
               params={"eval.circle_radii": "0.05", "eval.circle_unseen_radii": "0.1"})
    client.set_terminated(pid)
    # A sweep study: 4 trials, one pruned.
    sexp = client.create_experiment("sweep", artifact_location=(tmp / "sweep-artifacts").as_uri())
    sp = client.create_run(sexp, tags={"kind": "sweep", "profile": "smoke", "study_name": "test-sweep"})
    for trial, (m, obj, state) in enumerate([(1, 0.5, "COMPLETE"), (3, 0.3, "COMPLETE"), (5, 0.9, "PRUNED"),
                                             (3, 0.2, "COMPLETE")]):
        rid = _child(client, sexp, sp.info.run_id, "reacher", "ac-lstm-mdn", 0, {"objective": obj},
                     params={"trial.m": m, "trial.u": 5, "model.mixtures": m, "train.iters": 10},
                     extra_tags={"trial": str(trial), "trial_state": state},
                     status="KILLED" if state == "PRUNED" else "FINISHED")
        client.log_batch(rid, metrics=[Metric("val/metric", obj + 1.0 / (i + 1), 0, i) for i in range(4)])
    client.set_terminated(sp.info.run_id)
    return {"uri": uri, "tmp": tmp, "parent": pid, "old": old.info.run_id, "ids": ids, "client": client}


@pytest.fixture(scope="module")
def built(store, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    assert main(["--tracking-uri", store["uri"], "--out", str(out)]) == 0
    return out


@pytest.mark.slow
def test_every_table_and_figure_is_produced(built):
    folder = built / "test-study"
    for table in ("table_one", "claims_table", "success_table", "circle_table", "train_time_table", "metrics_table"):
        for ext in ("md", "html", "tex", "csv"):
            assert (folder / f"{table}.{ext}").stat().st_size > 0, (table, ext)
    for fig in ("table_one", "success_bars", "circles", "compute_time", "train_time", "training_curves", "tip_paths",
                "changing_goal"):
        assert drawn_colours(folder / f"{fig}.png") > 10, fig  # drawn, not a blank canvas
        assert is_pdf(folder / f"{fig}.pdf"), fig
        assert f"{fig}.png" in (folder / "index.html").read_text()
    for fig in ("sweep_history", "sweep_params", "sweep_intermediate"):
        assert (built / "test-sweep" / f"{fig}.png").exists()
    assert not (built / "old-study").exists()  # default = latest study of each kind
    root = (built / "index.html").read_text()
    assert "test-study/index.html" in root and "test-sweep/index.html" in root


@pytest.mark.slow
def test_success_numbers_equal_logged_and_wilson_equals_scipy(store):
    study = Store(store["uri"]).studies("ablation")[0]
    agg = success_summary(study).set_index(["variant", "eval_task"])
    for task, logged in (("reacher", REACHER), ("reacher-changing-goal", CHANGING)):
        for v in VARIANTS:
            seeds = [s for s in SEEDS if (v, s) != FAILED]
            row = agg.loc[(v, task)]
            assert row["mean"] == pytest.approx(np.mean([logged[v, s] for s in seeds]))
            k = sum(round(logged[v, s] * N_ROLLOUTS) for s in seeds)
            n = N_ROLLOUTS * len(seeds)
            assert (row["successes"], row["n"]) == (k, n)
            ci = binomtest(k, n).proportion_ci(0.95, method="wilson")
            assert (row["ci_low"], row["ci_high"]) == pytest.approx((ci.low, ci.high))
    assert math.isnan(wilson_interval(0, 0)[0])


@pytest.mark.slow
def test_failed_and_missing_cells_are_marked(store, built):
    study = Store(store["uri"]).studies("ablation")[0]
    agg = success_summary(study).set_index(["variant", "eval_task"])
    assert agg.loc[("ac-lstm-mdn", "reacher"), "status"] == "partial"
    assert "seed 1: FAILED" in agg.loc[("ac-lstm-mdn", "reacher"), "note"]
    assert agg.loc[("lstm", "reacher"), "status"] == "ok"
    for task in ("pick-place", "stack", "pick-place-changing-goal"):  # no run trained pick-place
        assert agg.loc[("lstm", task), "status"] == "gap"
    md = (built / "test-study" / "success_table.md").read_text()
    assert "†" in md and "gap" in md
    assert "FAILED" in (built / "test-study" / "index.html").read_text()


@pytest.mark.slow
def test_circle_table_equals_logged(built):
    import pandas as pd
    df = pd.read_csv(built / "test-study" / "circle_table.csv").set_index(["radius_cm", "variant"])
    for (v, r), rmse in RMSE.items():
        assert df.loc[(float(r), v), "rmse_mean"] == pytest.approx(rmse)
        assert df.loc[(float(r), v), "maxerr_mean"] == pytest.approx(100 * rmse / (r / 100))
    md = (built / "test-study" / "circle_table.md").read_text()
    assert re.search(r"^\| 10 \(unseen\) +\|", md, re.M) and re.search(r"^\| 5 +\|", md, re.M)


@pytest.mark.slow
def test_report_is_logged_to_parent_and_rebuild_is_idempotent(store, built):
    client = store["client"]
    names = {f.path for f in client.list_artifacts(store["parent"], "report")}
    assert "report/index.html" in names and "report/success_table.tex" in names
    folder = built / "test-study"
    listing = sorted(p.name for p in folder.iterdir())
    table = (folder / "success_table.csv").read_text()
    study = Store(store["uri"]).studies(study=store["parent"])[0]
    again = build_report(study, built)
    assert again.folder == folder
    assert sorted(p.name for p in folder.iterdir()) == listing
    assert (folder / "success_table.csv").read_text() == table
    logged = sorted(f.path.removeprefix("report/") for f in client.list_artifacts(store["parent"], "report"))
    assert logged == listing  # the parent's copy is replaced, not accumulated


@pytest.mark.slow
def test_study_without_artifacts_marks_figure_gaps(store, tmp_path):
    assert main(["--tracking-uri", store["uri"], "--study", "old-study", "--out", str(tmp_path),
                 "--no-log-artifacts"]) == 0
    index = (tmp_path / "old-study" / "index.html").read_text()
    for fig in ("circles", "tip_paths", "changing_goal", "compute_time"):
        assert f"figure <b>{fig}</b>" in index
        assert not (tmp_path / "old-study" / f"{fig}.png").exists()
    assert (tmp_path / "old-study" / "success_table.md").exists()


@pytest.mark.parametrize("args, message", [
    (["--experiment", "nope"], "unknown experiment 'nope'"),
    (["--study", "0123abc"], "unknown study '0123abc'"),
    (["--bogus"], "unrecognized arguments: --bogus"),
])
@pytest.mark.slow
def test_unknown_selection_is_one_line_exit_2(store, args, message, capsys, tmp_path):
    try:
        code = main(["--tracking-uri", store["uri"], "--out", str(tmp_path), *args])
    except SystemExit as exit_:  # argparse's exit
        code = exit_.code
    assert code == 2
    err = capsys.readouterr().err.strip()
    assert message in err and "\n" not in err


@pytest.mark.slow
def test_empty_or_missing_store_is_one_line_exit_2(tmp_path, capsys):
    assert main(["--tracking-uri", f"sqlite:///{tmp_path / 'absent.db'}", "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert "no MLflow store" in err and "\n" not in err
    assert not (tmp_path / "absent.db").exists()  # reading never creates a store
    empty = f"sqlite:///{tmp_path / 'empty.db'}"
    MlflowClient(empty).search_experiments()  # creates the schema, no runs
    capsys.readouterr()  # MLflow's own schema-creation log lines
    assert main(["--tracking-uri", empty, "--out", str(tmp_path)]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("reports: error: no studies") and "\n" not in err
    for name, content in (("garbage.db", b"not a database at all"), ("zero.db", b"")):
        (tmp_path / name).write_bytes(content)
        assert main(["--tracking-uri", f"sqlite:///{tmp_path / name}", "--out", str(tmp_path)]) == 2
        err = capsys.readouterr().err.strip()
        assert "is not an MLflow store" in err and "\n" not in err
        assert (tmp_path / name).read_bytes() == content  # left as it was



@pytest.mark.bench
def test_bench_quick_sized_report(tmp_path, benchmark):
    """Regeneration time of a report the size of a quick-profile study (3 tasks x 4 variants x 2 seeds, 50
    rollouts per evaluated task, a 20-trial sweep), as `python -m reports` in a fresh process."""
    import subprocess
    import sys

    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("ablation", artifact_location=(tmp_path / "art").as_uri())
    pid = client.create_run(exp, tags={"kind": "ablation", "profile": "quick", "study_name": "quick"}).info.run_id
    rng = np.random.default_rng(1)
    evals = {"reacher": ("reacher", "reacher-changing-goal"),
             "pick-place": ("pick-place", "stack", "pick-place-changing-goal"), "circle": ("circle",)}
    for task, tasks in evals.items():
        for v in ("lstm", "ac-lstm", "lstm-mdn", "ac-lstm-mdn"):
            for s in SEEDS:
                metrics = {f"{e}/{k}": val for e in tasks if e != "circle"
                           for k, val in (("success_rate", rng.uniform()), ("n_rollouts", 50))}
                metrics |= {f"circle/r{r:g}/radial_rmse": rng.uniform(0, 0.05) for r in (5, 7.5, 10, 12.5, 15)}
                metrics |= {"time/train_seconds": 60.0, "time/generation_seconds_per_traj": 0.02,
                            "time/ik_seconds_per_traj": 0.05}
                arts = {f"{e}.npz": _rollouts(rng, e, b=50, h=170) for e in tasks}
                _child(client, exp, pid, task, v, s, metrics, artifacts=arts, tmp=tmp_path)
    client.set_terminated(pid)
    sexp = client.create_experiment("sweep", artifact_location=(tmp_path / "sweep").as_uri())
    sp = client.create_run(sexp, tags={"kind": "sweep", "profile": "quick", "study_name": "quick-sweep"})
    for trial in range(20):
        rid = _child(client, sexp, sp.info.run_id, "reacher", "ac-lstm-mdn", 0, {"objective": rng.uniform()},
                     params={"trial.m": int(rng.integers(1, 20)), "trial.u": int(rng.integers(1, 10))},
                     extra_tags={"trial": str(trial), "trial_state": "COMPLETE"})
        client.log_batch(rid, metrics=[Metric("val/metric", rng.uniform(), 0, i * 50) for i in range(6)])
    client.set_terminated(sp.info.run_id)

    def regenerate():
        subprocess.run([sys.executable, "-m", "reports", "--tracking-uri", uri, "--out", str(tmp_path / "out")],
                       check=True, capture_output=True)

    benchmark.pedantic(regenerate, rounds=2, iterations=1)
    assert (tmp_path / "out" / "quick" / "tip_paths.png").exists()


def test_curve_band_over_seeds_with_missing_steps():
    import pandas as pd

    from reports.data.seed_aggregates import curve_band
    a = pd.DataFrame({"step": [0, 10, 20], "value": [3.0, 2.0, 1.0]})
    b = pd.DataFrame({"step": [0, 10], "value": [5.0, 4.0]})  # this seed stopped early
    band = curve_band([a, b]).set_index("step")
    assert band.loc[10, "mean"] == 3.0 and band.loc[10, "std"] == 1.0 and band.loc[10, "n"] == 2
    assert band.loc[20, "mean"] == 1.0 and band.loc[20, "n"] == 1
    assert curve_band([]).empty


def test_table_renderings_escape_their_markup():
    from reports.study_report.tables import Table
    t = Table("t", "rate_1 & 50%", ["variant", "a|b"], [["x_1 <b>", "50% ± 2 †"]], ["note #1"])
    assert r"rate\_1 \& 50\%" in t.to_latex() and r"50\% $\pm$ 2 $^\dagger$" in t.to_latex()
    assert "&lt;b&gt;" in t.to_html() and "a\\|b" in t.to_markdown()


def _failed_only_store(tmp_path) -> str:
    """A store whose only study failed: every cell FAILED before logging a metric."""
    uri = f"sqlite:///{tmp_path / 'mlflow.db'}"
    client = MlflowClient(uri)
    exp = client.create_experiment("ablation", artifact_location=(tmp_path / "artifacts").as_uri())
    parent = client.create_run(exp, tags={"kind": "ablation", "profile": "smoke", "study_name": "broken"})
    for v in VARIANTS:
        _child(client, exp, parent.info.run_id, "reacher", v, 0, {}, status="FAILED")
    client.set_terminated(parent.info.run_id, "FAILED")
    return uri


@pytest.mark.slow
def test_store_whose_only_study_failed_is_one_line_exit_2_and_no_folder(tmp_path, capsys):
    uri = _failed_only_store(tmp_path)
    capsys.readouterr()  # MLflow's own schema-creation log lines
    out = tmp_path / "out"
    assert main(["--tracking-uri", uri, "--out", str(out), "--no-log-artifacts"]) == 2
    err = capsys.readouterr().err.strip()
    assert err.startswith("reports: error: ") and "no finished run" in err and "\n" not in err, err
    assert "broken" in err and "2 FAILED" in err
    assert not out.exists()


@pytest.mark.slow
def test_index_opens_with_table_one_and_reads_in_the_order_of_results_md(built):
    """Table I and its figure first, then the paper's comparisons, the circles, the compute, each table followed by
    its figures; the metric dump last and folded."""
    index = (built / "test-study" / "index.html").read_text()
    order = [index.index(s) for s in ("Table I: success rate, ours beside the paper", "src='table_one.png'",
                                      "comparisons on Table I&#x27;s cells", "Circle drawing", "src='circles.png'",
                                      "Training time per variant", "src='compute_time.png'",
                                      "src='training_curves.png'", "Success rate (Table I, extended)",
                                      "src='success_bars.png'", "<details>", "All logged metrics")]
    assert order == sorted(order), order
    folded = index[index.index("<details>"):index.index("</details>")]
    assert "All logged metrics" in folded and 'id="T_metrics_table"' in folded
    assert index.count("<details>") == 1


@pytest.mark.slow
def test_no_generated_file_names_a_path_of_the_machine(store, built):
    roots = {str(store["tmp"]), str(built), str(Path.home()), str(Path.cwd())}
    for path in built.rglob("*"):
        if path.suffix in {".md", ".html", ".tex", ".csv"}:
            text = path.read_text()
            assert not [r for r in roots if r in text], path


# ------------------------------------------------------------------ seed-level statistics (experiments.stats)
RATES = (0.01, 0.02, 0.05, 0.5, 0.8, 0.95, 0.98, 0.99)  # true rates of the coverage grid
EPISODES = 34  # per seed, as the headline's evaluations


def _logit_normal(rate: float, spread: float) -> tuple[float, float]:
    """(location, scale) on the logit scale of seed rates whose mean is `rate` and whose standard deviation would be
    `spread` at a 50 % rate (it shrinks towards the edges, as a rate's spread must: 25 points around 1 % cannot
    exist); (logit(rate), 0) without a spread."""
    from scipy.optimize import brentq
    from scipy.special import expit, logit

    z, w = np.polynomial.hermite_e.hermegauss(80)
    w = w / w.sum()
    if spread == 0:
        return float(logit(rate)), 0.0
    scale = brentq(lambda s: math.sqrt(np.sum(w * expit(s * z) ** 2) - 0.25) - spread, 1e-6, 20)
    return brentq(lambda m: np.sum(w * expit(m + scale * z)) - rate, -30, 30), scale


def _true_seed_rates(rng, rate: float, spread: float, seeds: int, replicates: int) -> np.ndarray:
    """(replicates, seeds) true rates of trained models, logit-normal around the variant's rate (_logit_normal)."""
    from scipy.special import expit

    loc, scale = _logit_normal(rate, spread)
    return expit(loc + scale * rng.standard_normal((replicates, seeds)))


@pytest.mark.parametrize("seeds", [3, 5])
@pytest.mark.parametrize("spread", [0.0, 0.10, 0.25])
def test_seed_level_interval_keeps_its_coverage_at_every_rate(spread, seeds):
    """The seed-level interval of a success rate (rate_interval) covers the variant's rate (the mean of its seeds'
    true rates) at least 93 % of the time at rates from 1 % to 99 %, for seeds that agree and seeds 10 or 25 points
    apart (at 50 %), with 3 and 5 seeds of 34 episodes, and it never has zero width; the t-interval over the rates
    alone, which it replaced, collapses near the edges (it covers a 1 % rate with 3 seeds about 60 % of the time)."""
    from experiments.stats import rate_interval, seed_interval
    replicates = 4000  # coverage's standard error ~0.4 points
    rng = np.random.default_rng(1000 * seeds + int(100 * spread))
    for rate in RATES:
        rates = rng.binomial(EPISODES, _true_seed_rates(rng, rate, spread, seeds, replicates)) / EPISODES
        low, high = rate_interval(rates, EPISODES)
        coverage = np.mean((low <= rate) & (rate <= high))
        assert coverage >= 0.93, (rate, coverage)
        assert (high > low).all()  # never a point, whatever the seeds agree on
        t_low, t_high = seed_interval(rates)
        assert (low <= t_low).all() and (high >= t_high).all()  # never narrower than the t-interval it extends
    t_low, t_high = seed_interval(rng.binomial(EPISODES, np.full((replicates, 3), 0.01)) / EPISODES)
    assert np.mean((t_low <= 0.01) & (0.01 <= t_high)) < 0.7


def test_seed_level_interval_of_rates_is_never_a_point():
    """Every outcome of 3 seeds of 34 episodes (35^3 of them, seeds that all fail or all succeed included), and
    seeds of unequal episode counts: an interval of positive width around the mean rate."""
    from experiments.stats import rate_interval
    k = np.stack(np.meshgrid(*[np.arange(EPISODES + 1)] * 3, indexing="ij"), axis=-1).reshape(-1, 3)
    low, high = rate_interval(k / EPISODES, EPISODES)
    mean = k.mean(axis=1) / EPISODES
    assert (high > low).all() and (low <= mean + 1e-12).all() and (mean <= high + 1e-12).all()
    assert rate_interval([0.0, 0.0, 0.0], EPISODES)[1] > 0 and rate_interval([1.0, 1.0, 1.0], EPISODES)[0] < 1
    low, high = rate_interval([0.0, 0.0], [10, 100])
    assert 0 == low < high < 1
    assert all(math.isnan(x) for x in rate_interval([0.5], EPISODES))  # one seed: no spread between seeds to read


@pytest.mark.parametrize(("rate_a", "rate_b"), [(0.01, 0.01), (0.05, 0.01), (0.5, 0.5), (0.8, 0.5), (0.99, 0.95),
                                                (0.99, 0.99)])
def test_paired_difference_interval_keeps_its_coverage(rate_a, rate_b):
    """The paired difference's interval (paired_interval: seeds of two variants on the same episodes) covers the
    difference of the variants' rates at least 93 % of the time, near the edges too, for 3 and 5 seeds and spreads
    of 0 and 25 points; episodes shared (an easy episode is easy for both: one uniform draw per episode decides
    both outcomes) or not; never a point, where the t-interval over the differences collapses (both at 0 %)."""
    from experiments.stats import paired_interval
    rng = np.random.default_rng(int(1000 * rate_a + 10 * rate_b))
    replicates = 3000
    for seeds in (3, 5):
        for spread in (0.0, 0.25):
            ta = _true_seed_rates(rng, rate_a, spread, seeds, replicates)
            tb = _true_seed_rates(rng, rate_b, spread, seeds, replicates)
            for shared in (True, False):
                u = rng.random((replicates, seeds, EPISODES))
                v = u if shared else rng.random((replicates, seeds, EPISODES))
                a = (u < ta[..., None]).mean(axis=-1)
                b = (v < tb[..., None]).mean(axis=-1)
                low, high = paired_interval(a, b, EPISODES, EPISODES)
                coverage = np.mean((low <= rate_a - rate_b) & (rate_a - rate_b <= high))
                assert coverage >= 0.93, (seeds, spread, shared, coverage)
                assert (high > low).all()


def test_seed_interval_is_the_t_interval_of_the_seeds_rates():
    from scipy import stats

    from experiments.stats import seed_interval, wilson_interval
    rates = [20 / 34, 17 / 34, 24 / 34]
    t = stats.t.interval(0.95, 2, loc=np.mean(rates), scale=stats.sem(rates))
    assert seed_interval(rates) == pytest.approx(t)
    near_zero = [0.05, 0.0, 0.1]  # the t-interval reaches below 0: clipped to a rate
    assert seed_interval(near_zero) == pytest.approx((0.0, stats.t.interval(0.95, 2, loc=0.05,
                                                                            scale=stats.sem(near_zero))[1]))
    # seeds that disagree: far wider than the pooled Wilson interval of the same rollouts
    wl, wh = wilson_interval(60, 102)
    low, high = seed_interval([7 / 34, 20 / 34, 33 / 34])
    assert low < wl and high > wh and high - low > 2 * (wh - wl)
    assert all(math.isnan(x) for x in seed_interval([0.5]))  # one seed: no spread between seeds to read
    assert seed_interval([1.0, 1.0]) == (1.0, 1.0)  # seeds that agree exactly: the interval collapses
    many = seed_interval(np.array([[0.5, 0.6, 0.7], [0.1, 0.1, 0.1]]))
    assert many[0] == pytest.approx([seed_interval([0.5, 0.6, 0.7])[0], 0.1])


def test_sign_flip_and_permutation_p_values_are_exact():
    from experiments.stats import group_comparison, paired_comparison, permutation_p, sign_flip_p
    assert sign_flip_p([0.2, 0.3, 0.1]) == pytest.approx(2 / 8)  # the smallest p three seeds can give
    assert sign_flip_p([0.2, -0.3, 0.1]) == pytest.approx(1.0)  # sum 0: every flip is as far from 0
    assert sign_flip_p([0.1, 0.1, -0.1, 0.1, 0.1]) == pytest.approx(12 / 32)  # |sum| >= 0.3: 2 x (1 + 5)
    # 6 vs 6 models with no overlap: the observed split and its mirror are the only ones as extreme
    a, b = [0.9, 0.8, 0.85, 0.7, 0.95, 0.75], [0.2, 0.3, 0.1, 0.4, 0.25, 0.35]
    assert permutation_p(a, b) == pytest.approx(2 / 924)
    assert permutation_p([0.5, 0.5], [0.5, 0.5]) == 1.0
    many = permutation_p([0.9] * 15, [0.1] * 15)  # 155 million splits: estimated from random ones, not listed
    assert 0 <= many < 0.001 and many == permutation_p([0.9] * 15, [0.1] * 15)
    paired = paired_comparison({0: 0.6, 1: 0.7, 2: 0.9}, {0: 0.5, 1: 0.4, 2: 0.6, 3: 0.1})  # seed 3: no pair
    assert paired["n"] == 3 and paired["difference"] == pytest.approx(0.7 / 3) and paired["p"] == pytest.approx(0.25)
    from scipy import stats
    assert (paired["low"], paired["high"]) == pytest.approx(
        stats.t.interval(0.95, 2, loc=0.7 / 3, scale=stats.sem([0.1, 0.3, 0.3])))
    groups = group_comparison(a, b)
    welch = stats.ttest_ind(a, b, equal_var=False).confidence_interval(0.95)
    assert groups["n"] == "6+6" and (groups["low"], groups["high"]) == pytest.approx((welch.low, welch.high))


def test_paired_interval_keeps_the_pairings_gain_mid_range_and_holds_at_the_edges():
    from experiments.stats import paired_comparison, paired_interval, seed_interval
    # five seeds whose rates move together (LSTM-MDN against LSTM on the changing-goal reacher): the t-interval over
    # the differences stands, clear of zero, where taking the two as independent would not be
    a, b = np.array([6, 9, 12, 3, 12]) / 34, np.array([12, 15, 24, 6, 24]) / 34
    low, high = paired_interval(a, b, EPISODES, EPISODES)
    t_low, t_high = seed_interval(a - b, bounds=(-1.0, 1.0))
    assert low <= t_low and high >= t_high and high < 0
    # both variants at 0 % on every seed: the t-interval is the point 0, the paired interval is not
    zero = paired_comparison({0: 0.0, 1: 0.0, 2: 0.0}, {0: 0.0, 1: 0.0, 2: 0.0}, {s: 34 for s in range(3)},
                             {s: 34 for s in range(3)})
    assert zero["low"] < 0 < zero["high"] and zero["difference"] == 0.0
    assert paired_comparison({0: 0.0, 1: 0.0}, {0: 0.0, 1: 0.0})["low"] == 0.0  # without episode counts: the t


def test_a_validation_study_stays_out_of_headline_tables_and_comparisons_label_it():
    import pandas as pd

    from reports.data.store import StoreError, Study
    from reports.results.comparisons import sentence
    from reports.results.selection import headline_study

    def study(**columns) -> Study:
        kids = pd.DataFrame({"run_id": ["a", "b"], "status": ["FINISHED"] * 2, **columns})
        return Study("milestones", {"run_id": "p", "tags.study_name": "s"}, kids, client=None)

    for validation in (study(**{"tags.split": ["validation", "validation"]}),
                       study(**{"params.eval.split": [None, "validation"]})):
        assert validation.split == "validation"
        with pytest.raises(StoreError, match="'s' was evaluated on the validation episodes"):
            headline_study(validation, "success_table")
    plain = study(**{"tags.split": ["test", None]})
    assert plain.split == "test" and headline_study(plain, "success_table") is plain and study().split == "test"
    c = {"difference": 0.1, "low": -0.1, "high": 0.3, "p": 0.5, "test": "paired", "n": 3}
    assert "validation" not in sentence(c) and sentence({**c, "validation": True}).endswith(
        "(95 % interval -10 to +30; paired, 3 seeds, validation episodes; p = 0.50)")


def test_small_p_values_print_as_a_bound_not_as_zero():
    from experiments.stats import p_value
    from reports.results.comparisons import sentence

    assert [p_value(p) for p in (0.25, 0.0625, 0.004, 0.0004)] == ["0.25", "0.06", "0.004", "< 0.001"]
    c = {"difference": -0.21, "low": -0.30, "high": -0.12, "p": 2e-5, "test": "groups", "n": "10+10"}
    assert sentence(c).endswith("; p < 0.001)")


def test_success_over_seeds_and_table_say_what_n_counts():
    from experiments.stats import success_over_seeds, success_table
    success = success_over_seeds({0: (0.5, 34), 1: (0.9117647, 34), 2: (float("nan"), 34)})  # seed 2 logged no rate
    assert success["seeds"] == 2 and success["n"] == 68 and success["successes"] == 17 + 31
    assert success["seed_rates"] == {0: 0.5, 1: pytest.approx(31 / 34)}
    assert success["mean"] == pytest.approx((0.5 + 31 / 34) / 2)
    assert (success["ci_low"], success["ci_high"]) == pytest.approx(binomtest(48, 68).proportion_ci(0.95, "wilson"))
    assert success["seed_low"] < success["ci_low"] and success["seed_high"] > success["ci_high"]
    one = success_over_seeds({3: (0.5, 10)})
    assert one["seeds"] == 1 and math.isnan(one["seed_low"])  # one seed: no seed-level interval
    import pandas as pd
    frame = success_table(pd.DataFrame([{"variant": "lstm", "eval_task": "reacher", **success},
                                        {"variant": "lstm", "eval_task": "stack", **success_over_seeds({})}]))
    assert list(frame.columns) == ["task", "variant", "success", "per seed", "seed-level 95%",
                                   "Wilson 95% (rollouts independent)", "rollouts", "seeds"]
    assert frame.iloc[0].tolist()[2:] == ["71%", "50% / 91%", f"{100 * success['seed_low']:.0f}–100%", "59–80%",
                                          "68", "2"]
    assert frame.iloc[1].tolist()[2:] == ["gap", "–", "–", "–", "0", "0"]


@pytest.mark.slow
def test_study_summary_prints_the_report_success_table(store):
    """experiments' end-of-study summary and the report share one success table (experiments.stats)."""
    from experiments.ablation import success_markdown
    client = store["client"]
    exp = client.get_experiment_by_name("ablation").experiment_id
    text = success_markdown(client, exp, store["parent"])
    header = text.splitlines()[0]
    for column in ("per seed", "Wilson 95% (rollouts independent)", "seed-level 95%", "rollouts", "seeds"):
        assert column in header
    row = next(line for line in text.splitlines() if re.match(r"\| reacher +\| lstm +\|", line))
    assert "60% / 80%" in row and re.search(r"\| 20 +\| 2 +\|$", row)  # 2 seeds x 10 rollouts


@pytest.mark.slow
def test_failed_study_beside_a_good_one_is_skipped_with_one_line(tmp_path, capsys):
    uri = _failed_only_store(tmp_path)
    client = MlflowClient(uri)
    sexp = client.create_experiment("sweep", artifact_location=(tmp_path / "sweep-artifacts").as_uri())
    sp = client.create_run(sexp, tags={"kind": "sweep", "profile": "smoke", "study_name": "good-sweep"})
    _child(client, sexp, sp.info.run_id, "reacher", "ac-lstm-mdn", 0, {"objective": 0.5},
           params={"trial.m": 1}, extra_tags={"trial": "0", "trial_state": "COMPLETE"})
    client.set_terminated(sp.info.run_id)
    capsys.readouterr()
    out = tmp_path / "out"
    assert main(["--tracking-uri", uri, "--out", str(out), "--no-log-artifacts"]) == 0
    err = [line for line in capsys.readouterr().err.splitlines() if line.startswith("reports:")]
    assert err == ["reports: skipped: ablation study 'broken' has no finished run (2 FAILED)"]
    assert (out / "good-sweep" / "index.html").exists() and not (out / "broken").exists()


@pytest.mark.parametrize("name", ["paper-pickplace-30k", "paper-pickplace-30k-milestones@5000", "x+y", "a..b"])
def test_the_report_path_a_study_prints_is_where_its_report_goes(name):
    """The ablation, sweep and post-processing summaries print experiments.runtime.tracking.report_index; the report
    builds in DEFAULT_OUT/<the study's name>/, a folder name by the study name rule."""
    import pandas as pd

    from experiments.runtime.study_names import study_folder
    from experiments.runtime.tracking import report_index
    from reports.__main__ import DEFAULT_OUT
    from reports.data.store import Study

    study = Study("ablation", {"run_id": "r", "tags.study_name": name}, pd.DataFrame(), client=None)
    assert report_index(name) == f"{study_folder(DEFAULT_OUT, study.slug).as_posix()}/index.html"
    assert Path(report_index(name)).parts == (*DEFAULT_OUT.parts, name, "index.html")


@pytest.mark.parametrize("name", ["..", ".", "../x", "a b", 'a"b', "a\nb", "a/b", "-x", "x" * 101])
def test_a_study_name_that_breaks_the_rule_gets_no_folder(name):
    """A store from before the rule may hold such a name: no folder is made of it, cleaned or not (two names that
    cleaned to one folder would share it, and '..' is the folder above)."""
    import pandas as pd

    from experiments.runtime.study_names import RULE, StudyNameError
    from reports.data.store import Study

    study = Study("ablation", {"run_id": "r", "tags.study_name": name}, pd.DataFrame(), client=None)
    with pytest.raises(StudyNameError) as err:
        study.slug  # noqa: B018 - the property raises
    assert RULE in str(err.value) and "\n" not in str(err.value)


def test_a_report_rebuild_removes_only_what_the_last_build_wrote(tmp_path):
    """A report folder's manifest lists what a build wrote: the next build removes those files (a figure that became a
    gap does not linger) and nothing else; a manifest line leading out of the folder is refused."""
    from experiments.runtime.study_names import UnsafeFolder
    from reports.study_report.build import MANIFEST, _clear, _write_manifest

    folder = tmp_path / "out" / "s"
    folder.mkdir(parents=True)
    ours, mine = folder / "old_figure.png", folder / "notes.md"
    ours.write_text("x")
    mine.write_text("the user's")
    _write_manifest(folder, {ours, tmp_path / "elsewhere.png"})  # a path outside the folder is never listed
    assert (folder / MANIFEST).read_text() == "old_figure.png\n"
    _clear(folder)
    assert not ours.exists() and mine.read_text() == "the user's" and not (folder / MANIFEST).exists()
    (tmp_path / "out" / "RESULTS.md").write_text("keep")
    (folder / MANIFEST).write_text("../RESULTS.md\n")
    with pytest.raises(UnsafeFolder):
        _clear(folder)
    assert (tmp_path / "out" / "RESULTS.md").read_text() == "keep"


def test_a_packs_training_time_is_reported_once_not_as_a_spread_over_seeds():
    from types import SimpleNamespace

    import pandas as pd

    from reports.study_report.tables import train_time_summary, train_time_table
    runs = pd.DataFrame({"task": ["reacher"] * 5, "variant": ["lstm"] * 3 + ["ac-lstm"] * 2, "seed": [0, 1, 2, 0, 1],
                         "metrics.time/train_seconds": [1803.45, 1803.47, 1803.47, 900.0, 1100.0],
                         "tags.worker": ["vm:1", "vm:1", "vm:1", "vm:2", "vm:3"], "status": "FINISHED"})
    study = SimpleNamespace(name="s", ok=runs, children=runs, variants=["lstm", "ac-lstm"])
    summary = train_time_summary(study)
    assert summary.set_index("variant")["pack"].to_dict() == {"lstm": True, "ac-lstm": False}
    rows = train_time_table(summary, study).rows
    assert rows == [["LSTM", "1,803 (pack of 3)"], ["a.c. LSTM", "1,000 ± 100 (2 runs)"]]
    untagged = runs.drop(columns="tags.worker")  # studies from before the worker tag: the times alone say it
    assert train_time_summary(SimpleNamespace(ok=untagged))["pack"].tolist() == [True, False]
    other_workers = runs.assign(**{"tags.worker": ["vm:1", "vm:2", "vm:1", "vm:2", "vm:3"]})
    assert train_time_summary(SimpleNamespace(ok=other_workers))["pack"].tolist() == [False, False]


def test_comparisons_pair_the_seeds_that_saw_the_same_episodes():
    from types import SimpleNamespace

    import pandas as pd

    from reports.results import comparisons

    def study(name, rows):  # rows: (variant, seed, success rate, episode seed)
        evals = pd.DataFrame([{"run_id": f"{name}-{v}-{s}", "status": "FINISHED", "task": "reacher", "variant": v,
                               "seed": s, "eval_task": "reacher", "success_rate": r, "n_rollouts": 34.0,
                               "episode_seed": e} for v, s, r, e in rows])
        children = evals[["run_id"]].assign(**{"params.data.start_joint_range": "0.1"})
        return SimpleNamespace(name=name, eval_metrics=lambda: evals, children=children, split="test")

    a = study("a", [("lstm", 0, 0.5, 10_000), ("lstm", 1, 0.6, 10_001), ("lstm", 2, 0.7, 10_002),
                    ("ac-lstm", 0, 0.7, 10_000), ("ac-lstm", 1, 0.9, 10_001), ("ac-lstm", 2, 0.8, 10_002)])
    b = study("b", [("lstm", 0, 0.4, 20_000), ("lstm", 1, 0.5, 20_001), ("lstm", 2, 0.6, 20_002)])
    named = {"a": a, "b": b}
    paired = comparisons.between(named, "reacher", "a/ac-lstm", "a/lstm")
    assert (paired["test"], paired["n"]) == ("paired", 3)
    assert paired["difference"] == pytest.approx(0.2) and paired["p"] == pytest.approx(0.25)
    assert comparisons.sentence(paired) == "+20 points (95 % interval -9 to +45; paired, 3 seeds; p = 0.25)"
    # a target sentence quotes the row's seed-level interval (experiments.stats.rate_interval): mean 80 %; the
    # t-interval over the rates alone, 80 +- 4.30 x 10 / sqrt(3), would start at 55; the logit part reaches 48
    assert comparisons.rate_sentence(named, "reacher", "a/ac-lstm") == (
        "80 % (seed-level 95 % interval 48–100%; 3 seeds)")
    other_episodes = comparisons.between(named, "reacher", "a/lstm", "b/lstm")  # same seeds, other episodes
    assert (other_episodes["test"], other_episodes["n"]) == ("groups", "3+3")
    assert comparisons.between(named, "reacher", "a/ac-lstm+lstm", "b/lstm")["n"] == "6+3"  # pooled variants
    agg = comparisons.paper_rows([a], "reacher")  # of the paper's comparisons, the one this study has
    assert agg[["A", "B", "A − B (points)", "p", "test"]].values.tolist() == [
        ["a.c. LSTM", "LSTM", "+20", "0.25", "paired, 3 seeds"]]
    with pytest.raises(comparisons.ComparisonError, match="no finished lstm-mdn run"):
        comparisons.between(named, "reacher", "a/lstm-mdn", "a/lstm")
