"""Optuna sweeps of the mixture count and the auto-conditioning schedule for one
(task, variant), each trial an MLflow child run under a sweep parent run.

Search space (`--space` picks a subset; the others keep the profile's values):

| name      | config field        | TPE / random range              | grid values            |
|-----------|---------------------|---------------------------------|------------------------|
| m         | model.mixtures      | int 1..20, log scale            | 1, 3, 5, 10, 20        |
| u         | train.u             | int 1..10                       | 1, 2, 5, 10            |
| v         | train.v             | int 0..10 (0 = teacher forcing) | 0, 1, 2, 5, 10         |
| feedback  | train.feedback      | sample, component_mean, mixture_mean (all three)     |
| sigma_min | model.sigma_min     | float 1e-4..1e-1, log scale     | 1e-4, 1e-3, 1e-2       |

The sampled values are applied after the variant, so v = 0 on an auto-conditioned variant
means "the same head, trained with teacher forcing".

Objective (minimised): "val" = the last validation metric reported by `stm.train` (the
closed-loop error of rollouts on fresh task episodes), "final_distance" = the mean final
goal distance of `sweep.eval_rollouts` pybullet rollouts (circle: mean radial RMSE), or
"failure_rate" = 1 - their success rate (robust where one knocked-off block makes a mean
distance of metres, as in pick-and-place). The
median pruner watches the validation metric through `on_validation`.

Storage: by default a JournalFileBackend file `optuna.journal` next to mlflow.db (safe for
several processes on one host); `--storage postgresql://...` for several hosts. Re-running
the same sweep continues it until `trials` trials are COMPLETE or PRUNED.

Dead workers: on the journal file, trials left RUNNING by a killed sweep are marked FAIL
when a sweep starts (do not start two sweeps of the same study at once there; use
`--workers`). On an RDB storage (postgresql://, sqlite:///) every trial process beats a
heartbeat (`sweep.heartbeat` s); a trial without a beat for `sweep.grace_period` s is marked
FAIL by whichever worker looks next, its MLflow run FAILED, and it is re-queued with the same
parameters (`sweep.max_retry` times, Optuna's RetryFailedTrialCallback). So the same command
can run on several hosts at once (see docs/scale-out.md): each runs trials until the study
has `trials` COMPLETE or PRUNED, then waits for the trials other workers hold, running the
retries of dead ones, before it writes the summary.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import multiprocessing as mp
import os
import socket
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from mlflow.entities import Metric

from experiments.ablation import TORCH_THREADS, default_workers
from experiments.config import ConfigError, StudyConfig, SweepConfig, config_hash
from experiments.tracking import (
    PARENT_TAG,
    Client,
    MetricBuffer,
    flatten,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_metrics,
    log_params,
    provenance_params,
    runs_page_url,
    set_tags,
    settle_parent_run,
    store_dir,
    tracking_uri,
)

log = logging.getLogger(__name__)
EXPERIMENT = "sweep"
JOURNAL_NAME = "optuna.journal"

GRID = {"m": [1, 3, 5, 10, 20], "u": [1, 2, 5, 10], "v": [0, 1, 2, 5, 10],
        "feedback": ["sample", "component_mean", "mixture_mean"], "sigma_min": [1e-4, 1e-3, 1e-2]}
FIELDS = {"m": ("model", "mixtures"), "u": ("train", "u"), "v": ("train", "v"),
          "feedback": ("train", "feedback"), "sigma_min": ("model", "sigma_min")}


def suggest(trial, space: tuple[str, ...]) -> dict[str, Any]:
    """Sample the swept parameters (see the table in the module docstring)."""
    out: dict[str, Any] = {}
    if "m" in space:
        out["m"] = trial.suggest_int("m", 1, 20, log=True)
    if "u" in space:
        out["u"] = trial.suggest_int("u", 1, 10)
    if "v" in space:
        out["v"] = trial.suggest_int("v", 0, 10)
    if "feedback" in space:
        out["feedback"] = trial.suggest_categorical("feedback", GRID["feedback"])
    if "sigma_min" in space:
        out["sigma_min"] = trial.suggest_float("sigma_min", 1e-4, 1e-1, log=True)
    return out


def storage_spec(cfg: StudyConfig, uri: str) -> str:
    return cfg.sweep.storage or f"journal:{store_dir(uri) / JOURNAL_NAME}"


def open_storage(spec: str, sweep: SweepConfig | None = None, uri: str | None = None):
    """The Optuna storage; an RDB one beats heartbeats and retries dead workers' trials when
    `sweep` is given (their MLflow runs, in store `uri`, are marked FAILED)."""
    import warnings

    import optuna
    from optuna.storages.journal import JournalFileBackend, JournalStorage

    if spec.startswith("journal:"):
        path = Path(spec.removeprefix("journal:"))
        path.parent.mkdir(parents=True, exist_ok=True)
        return JournalStorage(JournalFileBackend(str(path)))
    if sweep is None:
        return optuna.storages.RDBStorage(spec)
    with warnings.catch_warnings():  # heartbeats are marked experimental in Optuna
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        return optuna.storages.RDBStorage(spec, heartbeat_interval=sweep.heartbeat, grace_period=sweep.grace_period,
                                          heartbeat_stale_trial_callback=RetryDeadTrial(sweep.max_retry, uri))


def has_heartbeat(storage) -> bool:
    from optuna.storages._heartbeat import is_heartbeat_enabled

    return is_heartbeat_enabled(storage)


def fail_dead_trials(study) -> None:
    """Optuna's heartbeat check (marked experimental): FAIL, and re-queue, the trials of dead workers."""
    import warnings

    import optuna

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        optuna.storages.fail_stale_trials(study)


def worker_id() -> str:
    return f"{socket.gethostname()}:{os.getpid()}"


class RetryDeadTrial:
    """Called by Optuna for a trial whose worker stopped beating: re-queue it with the same
    parameters (RetryFailedTrialCallback) and mark its MLflow run FAILED with the reason."""

    def __init__(self, max_retry: int, uri: str | None):
        import warnings

        import optuna
        from optuna.storages import RetryHeartbeatStaleTrialCallback

        with warnings.catch_warnings():
            warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
            self.retry = RetryHeartbeatStaleTrialCallback(max_retry=max_retry)
        self.uri = uri

    def __call__(self, study, frozen) -> None:
        log.warning("trial %d: its worker %s stopped beating; marked FAIL and re-queued", frozen.number,
                    frozen.user_attrs.get("worker", "?"))
        self.retry(study, frozen)
        run_id = frozen.user_attrs.get("mlflow_run_id")
        if run_id and self.uri:
            client = Client(self.uri)
            # what the dead worker reported to Optuna may not have reached MLflow (metrics are batched)
            now = int(time.time() * 1000)
            client.log_batch(run_id, metrics=[Metric("val/metric", float(v), now, int(step))
                                              for step, v in sorted(frozen.intermediate_values.items())])
            set_tags(client, run_id, {"trial_state": "FAIL", "error": f"worker {frozen.user_attrs.get('worker', '?')} "
                                      "died (no heartbeat); the trial was re-queued with the same parameters"})
            client.set_terminated(run_id, "FAILED")


def make_sampler(cfg: StudyConfig):
    import optuna

    s = cfg.sweep
    if s.sampler == "grid":
        return optuna.samplers.GridSampler({p: GRID[p] for p in s.space}, seed=s.seed)
    if s.sampler == "random":
        return optuna.samplers.RandomSampler(seed=s.seed)
    return optuna.samplers.TPESampler(seed=s.seed)


def study_name(cfg: StudyConfig) -> str:
    """`--study-name`, else task-variant-<ablation study name> (profile, plus a config hash when
    overridden), plus a hash of space/objective when not the defaults: a re-run with the same
    settings continues the same Optuna study, different settings never mix into it."""
    s = cfg.sweep
    if s.study_name:
        return s.study_name
    name = f"{s.task}-{s.variant}-{cfg.resolved_study_name()}"
    default = SweepConfig()
    if (tuple(s.space), s.objective) != (tuple(default.space), default.objective):
        name += "-" + config_hash([list(s.space), s.objective])[:6]
    return name


def trial_configs(cfg: StudyConfig, params: dict[str, Any], seed: int):
    """(ModelConfig, TrainConfig) of one trial: profile -> variant -> swept values."""
    from experiments.cells import resolve_stm_configs

    model, train = resolve_stm_configs(cfg, cfg.sweep.task, cfg.sweep.variant, seed)
    model_over = {FIELDS[k][1]: v for k, v in params.items() if FIELDS[k][0] == "model"}
    train_over = {FIELDS[k][1]: v for k, v in params.items() if FIELDS[k][0] == "train"}
    return dataclasses.replace(model, **model_over), dataclasses.replace(train, **train_over)


def check_sweep(cfg: StudyConfig) -> None:
    """Config errors a sweep would hit later, raised now (before anything is written)."""
    # the pruner needs intermediate values whatever the objective
    if cfg.task_config(cfg.sweep.task).train.val_every <= 0:
        raise ConfigError("train.val_every: must be > 0 for a sweep (the pruner and objective read the "
                          "validation metric); allowed: positive integers")
    try:
        trial_configs(cfg, {}, cfg.sweep.seed)
    except ValueError as e:
        raise ConfigError(f"sweep: {e}") from None


class MlflowTrialLink:
    """Our small Optuna <-> MLflow link: `start` opens a child run for a trial under the sweep
    parent run (its id stored as the trial's user attribute), and as an Optuna callback it
    closes the run with the trial's value and state when the trial ends."""

    STATUS = {"COMPLETE": "FINISHED", "PRUNED": "KILLED", "FAIL": "FAILED"}

    def __init__(self, uri: str, experiment_id: str, parent_id: str, tags: dict[str, str]):
        self.uri, self.experiment_id, self.parent_id, self.tags = uri, experiment_id, parent_id, tags
        self._client: Client | None = None

    @property
    def client(self) -> Client:
        if self._client is None:
            self._client = Client(self.uri)
        return self._client

    def start(self, trial) -> str:
        tags = {**self.tags, PARENT_TAG: self.parent_id, "role": "trial", "trial": str(trial.number),
                "optuna_study": trial.study.study_name}
        retried = trial.storage.get_trial_system_attrs(trial._trial_id).get("failed_trial")
        if retried is not None:
            tags["retry_of_trial"] = str(retried)
        run = self.client.create_run(self.experiment_id, run_name=f"trial-{trial.number}", tags=tags)
        trial.set_user_attr("mlflow_run_id", run.info.run_id)
        trial.set_user_attr("worker", worker_id())
        return run.info.run_id

    def __call__(self, study, frozen) -> None:
        run_id = frozen.user_attrs.get("mlflow_run_id")
        if not run_id:
            return
        state = frozen.state.name
        metrics = {}
        if frozen.value is not None:
            metrics["objective"] = frozen.value
        if frozen.intermediate_values:
            metrics["pruned_at_step" if state == "PRUNED" else "last_step"] = max(frozen.intermediate_values)
        if metrics:
            log_metrics(self.client, run_id, metrics)
        set_tags(self.client, run_id, {"trial_state": state})
        self.client.set_terminated(run_id, self.STATUS.get(state, "FAILED"))


def objective_factory(cfg: StudyConfig, link: MlflowTrialLink):
    def objective(trial) -> float:
        try:
            return _objective(trial)
        except Exception as exc:  # optuna records FAIL; keep the reason on the trial's run
            run_id = trial.user_attrs.get("mlflow_run_id")
            if run_id:
                set_tags(link.client, run_id, {"error": f"{type(exc).__name__}: {exc}"[:5000]})
            raise

    def _objective(trial) -> float:
        import optuna

        from envs.datasets import load_demos
        from envs.tasks import get_task
        from experiments.evaluation import evaluate_model
        from experiments.worker import seed_everything
        from stm.train import train

        run_id = link.start(trial)
        client = link.client
        params = suggest(trial, cfg.sweep.space)
        seed = cfg.sweep.seed
        model_cfg, train_cfg = trial_configs(cfg, params, seed)
        log_params(client, run_id, {**{f"trial.{k}": v for k, v in params.items()},
                                    **flatten({"model": model_cfg.to_dict(), "train": train_cfg.to_dict()}),
                                    "task": cfg.sweep.task, "variant": cfg.sweep.variant, **provenance_params()})
        task = get_task(cfg.sweep.task, **cfg.data_options(cfg.sweep.task))
        demos = load_demos(task, seed=0)
        seed_everything(seed)
        buffer = MetricBuffer(client, run_id)
        last: dict[str, float] = {}
        pruned = {"flag": False}

        def on_validation(iteration: int, value: float) -> bool:
            buffer.add(iteration, {"val/metric": value})
            last["val"] = value
            if not math.isfinite(value):
                return False
            trial.report(value, iteration)
            if trial.should_prune():
                pruned["flag"] = True
                return True
            return False

        with tempfile.TemporaryDirectory(prefix="acrmdn-trial-") as tmp:
            result = train(model_cfg, train_cfg, task, demos, checkpoint_path=Path(tmp) / "model.pt",
                           resume=False, on_metrics=buffer.add, on_validation=on_validation)
        buffer.flush()
        log_metrics(client, run_id, {"time/train_seconds": result.seconds})
        if pruned["flag"]:
            raise optuna.TrialPruned(f"pruned at iteration {result.iterations}")
        if cfg.sweep.objective in ("final_distance", "failure_rate"):
            ev = {**dataclasses.asdict(cfg.eval), "rollouts": cfg.sweep.eval_rollouts}
            metrics, _ = evaluate_model(result.model, [cfg.sweep.task], ev, seed=seed, phi_mode=train_cfg.phi_mode,
                                        timings=False)
            log_metrics(client, run_id, metrics)
            if cfg.sweep.objective == "failure_rate":
                return 1.0 - metrics[f"{cfg.sweep.task}/success_rate"]
            key = "radial_rmse_mean" if cfg.sweep.task == "circle" else "final_distance_mean"
            return metrics[f"{cfg.sweep.task}/{key}"]
        if "val" not in last:
            raise RuntimeError("training reported no validation metric (train.val_every > train.iters?)")
        return last["val"]

    return objective


def _optimize(cfg_dict: dict, spec: str, name: str, uri: str, experiment_id: str, parent_id: str,
              n_trials: int, total: int, level: int, threads: int | None = None) -> None:
    """One optimisation process (the main one or a spawned worker)."""
    import optuna

    if threads:
        import torch

        torch.set_num_threads(threads)
    from optuna.trial import TrialState

    from experiments.config import from_dict

    logging.basicConfig(level=level, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    optuna.logging.set_verbosity(optuna.logging.WARNING if level > logging.DEBUG else optuna.logging.INFO)
    cfg = from_dict(cfg_dict)
    study = optuna.load_study(study_name=name, storage=open_storage(spec, cfg.sweep, uri), sampler=make_sampler(cfg),
                              pruner=make_pruner(cfg))
    link = MlflowTrialLink(uri, experiment_id, parent_id, {"task": cfg.sweep.task, "variant": cfg.sweep.variant,
                                                           "profile": cfg.profile, "study_name": name})
    callbacks = [link]
    if total:
        callbacks.append(optuna.study.MaxTrialsCallback(total, states=(TrialState.COMPLETE, TrialState.PRUNED)))
    study.optimize(objective_factory(cfg, link), n_trials=n_trials, catch=(Exception,), callbacks=callbacks)


def _drain(cfg: StudyConfig, args: tuple, level: int) -> None:
    """RDB storages: wait until no trial is RUNNING (other workers finishing theirs), failing
    the trials of dead workers and running their re-queued copies (WAITING) one at a time."""
    import optuna
    from optuna.trial import TrialState

    spec, name, uri = args[1], args[2], args[3]
    study = optuna.load_study(study_name=name, storage=open_storage(spec, cfg.sweep, uri))
    announced = False
    while True:
        fail_dead_trials(study)
        if study.get_trials(deepcopy=False, states=(TrialState.WAITING,)):
            _optimize(*args, 1, 0, level, TORCH_THREADS)
            continue
        running = study.get_trials(deepcopy=False, states=(TrialState.RUNNING,))
        if not running:
            return
        if not announced:
            log.info("waiting for %d trial(s) held by other workers: %s", len(running),
                     ", ".join(f"{t.number} ({t.user_attrs.get('worker', '?')})" for t in running))
            announced = True
        time.sleep(cfg.sweep.heartbeat)


def make_pruner(cfg: StudyConfig):
    import optuna

    return optuna.pruners.MedianPruner(n_startup_trials=cfg.sweep.startup_trials,
                                       n_warmup_steps=cfg.sweep.warmup_steps)


@dataclass
class SweepOutcome:
    study_name: str
    experiment_id: str
    parent_run_id: str
    storage: str
    counts: dict[str, int] = field(default_factory=dict)
    best_value: float | None = None
    best_params: dict[str, Any] = field(default_factory=dict)
    failed: int = 0
    seconds: float = 0.0

    def summary(self) -> str:
        counts = ", ".join(f"{v} {k.lower()}" for k, v in sorted(self.counts.items()))
        lines = [f"sweep {self.study_name!r}: {counts} ({self.seconds:.0f}s); storage {self.storage}"]
        if self.best_value is not None:
            lines.append(f"best value {self.best_value:.5g} with {self.best_params}")
        if self.failed:
            lines.append(f"{self.failed} trial(s) FAILED (not recovered by a retry); see the trial runs' error text")
        lines.append(f"runs: {runs_page_url(self.experiment_id)}  (start the UI with `nox -s ui`)")
        return "\n".join(lines)


def _fail_stale_trials(study, storage, link: MlflowTrialLink) -> None:
    """Trials a killed sweep left RUNNING: by heartbeat on an RDB storage (another host's live
    trial is left alone), else all of them (journal file: one sweep command at a time)."""
    from optuna.trial import TrialState

    if has_heartbeat(storage):
        fail_dead_trials(study)
        return
    for t in study.get_trials(deepcopy=False, states=(TrialState.RUNNING,)):
        log.warning("trial %d was left RUNNING by a killed sweep; marking it FAIL", t.number)
        storage.set_trial_state_values(t._trial_id, TrialState.FAIL)
        link(study, storage.get_trial(t._trial_id))


def run_sweep(cfg: StudyConfig) -> SweepOutcome:
    import optuna
    from optuna.trial import TrialState

    start = time.perf_counter()
    uri = tracking_uri()
    spec = storage_spec(cfg, uri)
    name = study_name(cfg)
    client = Client(uri)
    experiment_id = get_or_create_experiment(client, EXPERIMENT)
    parent_id = get_or_create_parent_run(client, experiment_id, name, {
        "kind": "sweep", "profile": cfg.profile, "task": cfg.sweep.task, "variant": cfg.sweep.variant,
        "optuna_storage": spec})
    parent_id = settle_parent_run(client, experiment_id, name, parent_id)
    log_params(client, parent_id, {**flatten({"sweep": dataclasses.asdict(cfg.sweep)}), **provenance_params()})
    storage = open_storage(spec, cfg.sweep, uri)
    study = optuna.create_study(study_name=name, storage=storage, direction="minimize", load_if_exists=True,
                                sampler=make_sampler(cfg), pruner=make_pruner(cfg))
    link = MlflowTrialLink(uri, experiment_id, parent_id, {})
    _fail_stale_trials(study, storage, link)
    done_states = (TrialState.COMPLETE, TrialState.PRUNED)
    remaining = cfg.sweep.trials - len(study.get_trials(deepcopy=False, states=done_states))
    workers = max(1, min(cfg.workers or default_workers(), remaining)) if remaining > 0 else 0
    log.info("sweep %r: %d trial(s) to run with %d process(es); storage %s", name, max(remaining, 0), workers, spec)
    level = logging.getLogger().getEffectiveLevel()
    args = (cfg.to_dict(), spec, name, uri, experiment_id, parent_id)
    if remaining > 0:
        if workers == 1:
            _optimize(*args, remaining, cfg.sweep.trials, level, TORCH_THREADS)
        else:
            per = [remaining // workers + (i < remaining % workers) for i in range(workers)]
            with ProcessPoolExecutor(workers, mp_context=mp.get_context("spawn")) as pool:
                for f in [pool.submit(_optimize, *args, n, cfg.sweep.trials, level, TORCH_THREADS) for n in per]:
                    f.result()
    if has_heartbeat(storage):
        _drain(cfg, args, level)

    study = optuna.load_study(study_name=name, storage=open_storage(spec))
    trials = study.get_trials(deepcopy=False)
    outcome = SweepOutcome(name, experiment_id, parent_id, spec)
    for t in trials:
        outcome.counts[t.state.name] = outcome.counts.get(t.state.name, 0) + 1
    outcome.failed = len(unrecovered_failures(trials))
    if any(t.state == TrialState.COMPLETE for t in trials):
        best = study.best_trial
        outcome.best_value, outcome.best_params = best.value, best.params
        log_metrics(client, parent_id, {"best_value": best.value, "best_trial": best.number})
        set_tags(client, parent_id, {f"best.{k}": v for k, v in best.params.items()}
                 | {"best_run_id": best.user_attrs.get("mlflow_run_id", "")})
    log_metrics(client, parent_id, {f"trials_{k.lower()}": v for k, v in outcome.counts.items()})
    with tempfile.TemporaryDirectory(prefix="acrmdn-sweep-") as tmp:
        figures = sweep_figures(study, Path(tmp))
        if figures:
            client.log_artifacts(parent_id, tmp, "figures")
    outcome.seconds = time.perf_counter() - start
    client.set_terminated(parent_id, "FINISHED" if not outcome.failed else "FAILED")
    return outcome


def unrecovered_failures(trials) -> list:
    """FAIL trials whose re-queued copy (after a dead worker) did not end COMPLETE or PRUNED."""
    from optuna.trial import TrialState

    recovered = {n for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)
                 for n in t.system_attrs.get("retry_history", [])}
    return [t for t in trials if t.state == TrialState.FAIL and t.number not in recovered]


def sweep_figures(study, out: Path) -> list[Path]:
    """optuna.visualization.matplotlib figures: history, importances, slice, contour; a figure
    that cannot be drawn yet (too few finished trials, one parameter) is skipped with a log line."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.trial import TrialState
    from optuna.visualization import matplotlib as ovm

    complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    params = sorted({p for t in complete for p in t.params})
    plots = {"optimization_history": ovm.plot_optimization_history,
             "intermediate_values": ovm.plot_intermediate_values}
    if complete:
        plots["slice"] = ovm.plot_slice
    if len(complete) >= 2 and params:
        plots["param_importances"] = ovm.plot_param_importances
    if len(params) >= 2 and len(complete) >= 2:
        plots["contour"] = ovm.plot_contour
    paths = []
    for name, fn in plots.items():
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                ax = fn(study)
            fig = ax.flat[0].figure if hasattr(ax, "flat") else ax.figure
            for ext in ("png", "pdf"):
                path = out / f"{name}.{ext}"
                fig.savefig(path, dpi=110, bbox_inches="tight")
                paths.append(path)
            plt.close(fig)
        except Exception as exc:  # optuna raises for degenerate studies (e.g. zero-variance importances)
            log.info("figure %s skipped: %s", name, exc)
            plt.close("all")
    return paths
