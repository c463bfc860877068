"""Optuna sweeps of the mixture count and the auto-conditioning schedule for one
(task, variant), each trial an MLflow child run under a sweep parent run.

Search space (`--space` picks a subset; the others keep the profile's values):

| name      | config field        | TPE / random range              | grid values (default)             |
|-----------|---------------------|---------------------------------|-----------------------------------|
| m         | model.mixtures      | int 1..20, log scale            | sweep.grid_m: 1, 3, 5, 10, 20     |
| u         | train.u             | int 1..10                       | sweep.grid_u: 1, 2, 5, 10         |
| v         | train.v             | int 0..10 (0 = teacher forcing) | sweep.grid_v: 0, 1, 2, 5, 10      |
| feedback  | train.feedback      | sample, component_mean, mixture_mean (all three)     |
| sigma_min | model.sigma_min     | float 1e-4..1e-1, log scale     | 1e-4, 1e-3, 1e-2                  |

The sampled values are applied after the variant, so v = 0 on an auto-conditioned variant
means "the same head, trained with teacher forcing".

Samplers (`sweep.sampler`), each seeded by `sweep.seed` plus the worker's index (and, on an RDB
storage, a number from the host name), so that the processes of one sweep do not draw the same
values:
- "tpe": TPE after `sweep.tpe_startup` random start-up trials, by default a third of the trials
  (at least one). Optuna's default of 10 start-up trials meant that a sweep of <= 10 trials never
  used TPE: it drew the same random values as every other sweep with the same seed.
- "grid": every point of the product of the swept parameters' grids once (the trials are capped
  at the grid's size; fewer cover part of it, with a warning). `sweep.grid_uv = [[1, 9], [5, 5],
  [2, 2]]` sweeps u and v together as those pairs (one Optuna parameter "uv", values "u/v")
  instead of grid_u x grid_v, so that a grid over m x a few schedules is one command and no m is
  tied to one schedule:
      python -m experiments sweep --profile results --sampler grid --space m,u,v --trials 15
          --set 'sweep.grid_uv=[[1, 9], [5, 5], [2, 2]]' --set sweep.seeds=2 --set sweep.pruner=none
- "random": uniform draws from the ranges.

Seeds: `sweep.seeds` = K trains K seeds per trial (packed) and minimises their mean objective
(experiments/sweeps/objective.py). Pruner (`sweep.pruner`): "median" (Optuna's MedianPruner on
the validation metric, `sweep.startup_trials`, `sweep.warmup_steps`) or "none" (a grid whose
every point should be trained to the end).

Parameter importances: at the end of a sweep with >= 2 complete trials and >= 2 swept
parameters, Optuna's fANOVA (FanovaImportanceEvaluator, seeded by sweep.seed; Optuna 5's default
would be PED-ANOVA, which looks at the best 10 % of the trials: too few in a sweep of 15-30)
over the complete trials, normalised to sum 1, logged on the parent run as `importance/<param>`
(experiments/sweeps/figures.py); when they cannot be computed, the tag `importance_note` says why.

Objective (minimised; experiments/sweeps/objective.py): "val" (the last validation metric),
"final_distance" or "failure_rate" over `sweep.eval_rollouts` rollouts per seed. Figures:
experiments/sweeps/figures.py.

Storage (experiments/runtime/optuna_storage.py): by default a JournalFileBackend file `optuna.journal`
next to mlflow.db (safe for several processes on one host); `--storage postgresql://...` for
several hosts. Re-running the same sweep continues it until `trials` trials are COMPLETE or
PRUNED.

Dead workers: on the journal file, trials left RUNNING by a killed sweep are marked FAIL and
re-queued with the same parameters when a sweep starts (do not start two sweeps of the same
study at once there; use `--workers`). On an RDB storage (postgresql://, sqlite:///) every trial process beats a
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
import socket
import tempfile
import time
import zlib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from experiments.ablation import command_line
from experiments.runtime.optuna_storage import (
    describe,
    drain,
    has_heartbeat,
    open_storage,
    retry_callback,
    retry_history,
    storage_spec,
    trials_in,
)
from experiments.runtime.processes import default_workers, training_threads, worker_pool
from experiments.runtime.study_names import check_study_name
from experiments.runtime.tracking import (
    NOTE_TAG,
    SWEEP,
    Client,
    flatten,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_metrics,
    log_params,
    provenance_params,
    report_index,
    runs_page_url,
    set_tags,
    tracking_uri,
)
from experiments.study_config import ConfigError, StudyConfig, SweepConfig, config_hash, from_dict
from experiments.sweeps.figures import importance_evaluator, param_importances, sweep_figures
from experiments.sweeps.objective import (
    MlflowTrialLink,
    expand_uv,
    grid_space,
    objective_factory,
    trial_configs,
    uv_pairs,
)

log = logging.getLogger(__name__)
EXPERIMENT = SWEEP


def make_sampler(cfg: StudyConfig, worker: int = 0):
    """The sweep's sampler in worker process `worker` (0: the main one): seeded by sweep.seed +
    worker, since processes with one seed would draw the same random values."""
    import optuna

    s = cfg.sweep
    seed = s.seed + worker
    if s.sampler == "grid":
        return optuna.samplers.GridSampler(grid_space(s), seed=seed)
    if s.sampler == "random":
        return optuna.samplers.RandomSampler(seed=seed)
    return optuna.samplers.TPESampler(seed=seed, n_startup_trials=s.tpe_startup_trials())


def make_pruner(cfg: StudyConfig):
    import optuna

    if cfg.sweep.pruner == "none":
        return optuna.pruners.NopPruner()
    return optuna.pruners.MedianPruner(n_startup_trials=cfg.sweep.startup_trials,
                                       n_warmup_steps=cfg.sweep.warmup_steps)


def grid_size(cfg: StudyConfig) -> int:
    return math.prod(len(values) for values in grid_space(cfg.sweep).values())


def planned_trials(cfg: StudyConfig) -> int:
    """sweep.trials, capped at the grid's size for the grid sampler (each point once)."""
    if cfg.sweep.sampler == "grid":
        return min(cfg.sweep.trials, grid_size(cfg))
    return cfg.sweep.trials


def study_name(cfg: StudyConfig) -> str:
    """`--study-name`, else task-variant-<ablation study name> (profile, plus a config hash when
    overridden), plus a hash of space/objective when not the defaults: a re-run with the same
    settings continues the same Optuna study, different settings never mix into it."""
    s = cfg.sweep
    if s.study_name:
        return s.study_name
    name = f"{s.task}-{s.variant}-{cfg.resolved_study_name()}"
    default = SweepConfig()
    # what changes the objective's meaning or the grid; left out at its default, so that the names of
    # studies from before these fields existed stay
    extra: dict[str, Any] = {"seeds": s.seeds} if s.seeds != default.seeds else {}
    if s.sampler == "grid":
        grid = grid_space(s)
        if grid != grid_space(dataclasses.replace(default, space=s.space, sampler="grid")):
            extra["grid"] = grid
    if (tuple(s.space), s.objective) != (tuple(default.space), default.objective) or extra:
        name += "-" + config_hash([list(s.space), s.objective, *([extra] if extra else [])])[:6]
    return name


def check_sweep(cfg: StudyConfig) -> None:
    """Config errors a sweep would hit later, raised now (before anything is written)."""
    check_study_name(study_name(cfg), "sweep study name (<task>-<variant>-<profile> unless --study-name)")
    # the pruner needs intermediate values whatever the objective
    if cfg.task_config(cfg.sweep.task).train.val_every <= 0:
        raise ConfigError("train.val_every: must be > 0 for a sweep (the pruner and objective read the "
                          "validation metric); allowed: positive integers")
    s = cfg.sweep
    if s.sampler == "grid" and s.grid_uv and not uv_pairs(s):
        raise ConfigError(f"sweep.grid_uv: (u, v) pairs need both u and v in sweep.space (got "
                          f"{','.join(s.space)}); allowed: a space with u and v, or grid_uv = []")
    try:
        for seed in range(s.seed, s.seed + s.seeds):
            trial_configs(cfg, {}, seed)
    except ValueError as e:
        raise ConfigError(f"sweep: {e}") from None


def _load(cfg: StudyConfig, spec: str, name: str, uri: str, worker: int):
    import optuna

    if has_heartbeat(spec):  # an RDB storage that several machines may share: their processes draw apart too
        worker += zlib.crc32(socket.gethostname().encode()) % 100_000 * 1_000
    return optuna.load_study(study_name=name, storage=open_storage(spec, cfg.sweep, uri),
                             sampler=make_sampler(cfg, worker), pruner=make_pruner(cfg))


def _optimize(cfg_dict: dict, spec: str, name: str, uri: str, experiment_id: str, parent_id: str,
              n_trials: int, total: int, level: int, threads: int | None = None, drain_after: bool = False,
              worker: int = 0) -> None:
    """One optimisation process (the main one or spawned worker number `worker`): `n_trials`
    trials (stopping when `total` are COMPLETE or PRUNED), then, with `drain_after`, the drain loop."""
    import optuna

    if threads:
        import torch

        torch.set_num_threads(threads)
    from optuna.trial import TrialState

    logging.basicConfig(level=level, format="%(asctime)s %(processName)s %(name)s: %(message)s")
    optuna.logging.set_verbosity(optuna.logging.WARNING if level > logging.DEBUG else optuna.logging.INFO)
    cfg = from_dict(cfg_dict)
    study = _load(cfg, spec, name, uri, worker)
    link = MlflowTrialLink(uri, experiment_id, parent_id, {"task": cfg.sweep.task, "variant": cfg.sweep.variant,
                                                           "profile": cfg.profile, "study_name": name})
    objective = objective_factory(cfg, link)
    callbacks = [link]
    if total:
        callbacks.append(optuna.study.MaxTrialsCallback(total, states=(TrialState.COMPLETE, TrialState.PRUNED)))
    if n_trials:
        study.optimize(objective, n_trials=n_trials, catch=(Exception,), callbacks=callbacks)
    if drain_after:  # the retries of dead workers' trials, one at a time; then wait for the others
        drain(study, lambda: study.optimize(objective, n_trials=1, catch=(Exception,), callbacks=[link]),
              cfg.sweep.heartbeat)


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
    importances: dict[str, float] = field(default_factory=dict)

    def summary(self) -> str:
        counts = ", ".join(f"{v} {k.lower()}" for k, v in sorted(self.counts.items()))
        lines = [f"sweep {self.study_name!r}: {counts} ({self.seconds:.0f}s); storage {describe(self.storage)}"]
        if self.best_value is not None:
            lines.append(f"best value {self.best_value:.5g} with {self.best_params}")
        if self.importances:
            lines.append("parameter importances (fANOVA): "
                         + ", ".join(f"{k} {v:.2f}" for k, v in self.importances.items()))
        if self.failed:
            lines.append(f"{self.failed} trial(s) FAILED (not recovered by a retry); see the trial runs' error text")
        lines.append(f"runs: {runs_page_url(self.experiment_id)}  (start the UI with `nox -s ui`)")
        return "\n".join(lines)

    def note(self) -> str:
        """The parent run's description (Markdown)."""
        rows = "\n".join(f"| {k.lower()} | {v} |" for k, v in sorted(self.counts.items()))
        lines = [f"**sweep `{self.study_name}`** ({self.seconds:.0f} s), storage `{describe(self.storage)}`", "",
                 "| trials | count |", "|---|---|", rows, ""]
        if self.best_value is not None:
            lines += [f"Best value **{self.best_value:.5g}** with `{self.best_params}`.", ""]
        if command_line():
            lines += ["Command:", "", f"    {command_line()}", ""]
        lines.append(f"Report: `python -m reports --study {self.study_name}` writes `{report_index(self.study_name)}`.")
        return "\n".join(lines)


def _fail_stale_trials(study, spec: str, link: MlflowTrialLink, max_retry: int) -> None:
    """Trials a killed sweep left RUNNING: by heartbeat on an RDB storage (another host's live
    trial is left alone), else all of them (journal file: one sweep command at a time), each
    re-queued with the same parameters like a dead worker's."""
    from optuna.trial import TrialState

    if has_heartbeat(spec):
        return  # the drain loop and Optuna's heartbeat check handle them
    retry = retry_callback(max_retry)
    for t in trials_in(study, "RUNNING"):
        log.warning("trial %d was left RUNNING by a killed sweep; marking it FAIL and re-queueing it", t.number)
        frozen = study.tell(t.number, state=TrialState.FAIL, skip_if_finished=True)
        link(study, frozen)
        retry(study, frozen)


def run_sweep(cfg: StudyConfig) -> SweepOutcome:
    import optuna

    start = time.perf_counter()
    uri = tracking_uri()
    spec = storage_spec(cfg.sweep.storage, uri)
    name = study_name(cfg)
    client = Client(uri)
    experiment_id = get_or_create_experiment(client, EXPERIMENT)
    parent_id = get_or_create_parent_run(client, experiment_id, name, {
        "kind": "sweep", "profile": cfg.profile, "task": cfg.sweep.task, "variant": cfg.sweep.variant,
        "optuna_storage": describe(spec)})
    log_params(client, parent_id, {**flatten({"sweep": {**dataclasses.asdict(cfg.sweep),
                                                        "storage": describe(spec)}}), **provenance_params()})
    storage = open_storage(spec, cfg.sweep, uri)
    study = optuna.create_study(study_name=name, storage=storage, direction="minimize", load_if_exists=True,
                                sampler=make_sampler(cfg), pruner=make_pruner(cfg))
    _fail_stale_trials(study, spec, MlflowTrialLink(uri, experiment_id, parent_id, {}), cfg.sweep.max_retry)
    total = planned_trials(cfg)
    if total < cfg.sweep.trials:
        log.info("grid sampler: %d grid points, so %d trials (not sweep.trials = %d)", total, total,
                 cfg.sweep.trials)
    elif cfg.sweep.sampler == "grid" and total < grid_size(cfg):
        log.warning("grid sampler: %d trials cover %d of the %d grid points; re-run with --trials %d to finish it",
                    total, total, grid_size(cfg), grid_size(cfg))
    remaining = total - len(trials_in(study, "COMPLETE", "PRUNED"))
    workers = max(1, min(cfg.workers or default_workers(), remaining)) if remaining > 0 else 0
    log.info("sweep %r: %d trial(s) to run with %d process(es); storage %s", name, max(remaining, 0), workers,
             describe(spec))
    level = logging.getLogger().getEffectiveLevel()
    args = (cfg.to_dict(), spec, name, uri, experiment_id, parent_id)
    retries_left = bool(trials_in(study, "WAITING"))
    if workers <= 1:
        _optimize(*args, max(remaining, 0), total, level, training_threads(), has_heartbeat(spec) or retries_left)
    else:
        per = [remaining // workers + (i < remaining % workers) for i in range(workers)]
        with worker_pool(workers) as pool:
            for f in [pool.submit(_optimize, *args, n, total, level, training_threads(), False, i)
                      for i, n in enumerate(per)]:
                f.result()
        if has_heartbeat(spec) or trials_in(study, "WAITING"):
            _optimize(*args, 0, 0, level, training_threads(), True, workers)
    return _finish(cfg, client, spec, name, experiment_id, parent_id, start)


def _finish(cfg: StudyConfig, client: Client, spec: str, name: str, experiment_id: str, parent_id: str,
            start: float) -> SweepOutcome:
    import optuna
    from optuna.trial import TrialState

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
        set_tags(client, parent_id, {f"best.{k}": v for k, v in expand_uv(best.params).items()}
                 | {"best_run_id": best.user_attrs.get("mlflow_run_id", "")})
    log_metrics(client, parent_id, {f"trials_{k.lower()}": v for k, v in outcome.counts.items()})
    outcome.importances, note = param_importances(study, cfg.sweep.seed)
    if outcome.importances:
        log_metrics(client, parent_id, {f"importance/{k}": v for k, v in outcome.importances.items()})
    set_tags(client, parent_id, {"importance_evaluator": "fANOVA"} | ({"importance_note": note} if note else {}))
    with tempfile.TemporaryDirectory(prefix="acrmdn-sweep-") as tmp:
        if sweep_figures(study, Path(tmp), importance_evaluator(cfg.sweep.seed)):
            client.log_artifacts(parent_id, tmp, "figures")
    outcome.seconds = time.perf_counter() - start
    client.set_tag(parent_id, NOTE_TAG, outcome.note())
    client.set_terminated(parent_id, "FINISHED" if not outcome.failed else "FAILED")
    return outcome


def unrecovered_failures(trials) -> list:
    """FAIL trials whose re-queued copy (after a dead worker or a killed sweep) did not end
    COMPLETE or PRUNED."""
    from optuna.trial import TrialState

    recovered = {n for t in trials if t.state in (TrialState.COMPLETE, TrialState.PRUNED)
                 for n in retry_history(t)}
    return [t for t in trials if t.state == TrialState.FAIL and t.number not in recovered]
