"""What one sweep trial does: sample the swept values, train the (task, variant) with them in
an MLflow child run under the sweep's parent run, and return the value Optuna minimises.

Objective: "val" = the last validation metric reported by `stm.training.loop` (the closed-loop error
of rollouts on fresh task episodes), "final_distance" = the mean of the task's primary error
metric over `sweep.eval_rollouts` pybullet rollouts (`Task.sweep_objective`), or "failure_rate" = 1 - their
success rate (robust where one knocked-off block makes a mean distance of metres, as in
pick-and-place). The median pruner watches the validation metric through `on_validation`.

Seeds (`sweep.seeds` = K): each trial trains seeds sweep.seed .. sweep.seed+K-1 of the same
configuration (K > 1: together, with stm.training.loop.train_packed, which gives each seed what
`train` would) and returns the mean of the K per-seed objectives ("objective/seed<s>" on the
trial's run): "val" the mean of each seed's last validation metric; "final_distance" and
"failure_rate" over each seed's own evaluation episodes (evaluate_model picks them from the
seed, as in an ablation). The pruner sees, at each validation step, the mean over the seeds
(logged as "val/metric"; each seed's as "seed<s>/val/metric"), so that a trial is pruned on the
same quantity it is ranked by.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from experiments.eval_sweep_config import INT_RANGES
from experiments.runtime.optuna_storage import retried_trial_number, worker_id
from experiments.runtime.tracking import (
    PARENT_TAG,
    Client,
    MetricBuffer,
    flatten,
    log_metrics,
    log_params,
    provenance_params,
    set_tags,
)
from experiments.study_config import StudyConfig, SweepConfig

# grid values of the swept parameters that are not integers (m, u, v: the sweep.grid_* fields)
GRID = {"feedback": ["sample", "component_mean", "mixture_mean"], "sigma_min": [1e-4, 1e-3, 1e-2]}
FIELDS = {"m": ("model", "mixtures"), "u": ("train", "u"), "v": ("train", "v"),
          "feedback": ("train", "feedback"), "sigma_min": ("model", "sigma_min")}
UV = "uv"  # the grid sampler's parameter for (u, v) pairs swept together (sweep.grid_uv), values "u/v"


def uv_pairs(s: SweepConfig) -> tuple[tuple[int, int], ...]:
    """The (u, v) pairs the grid sampler sweeps together: sweep.grid_uv on a grid over u and v, else ()."""
    return s.grid_uv if s.sampler == "grid" and {"u", "v"} <= set(s.space) else ()


def uv_choices(pairs: tuple[tuple[int, int], ...]) -> list[str]:
    """The (u, v) pairs as the values of the grid's parameter "uv": "u/v"."""
    return [f"{u}/{v}" for u, v in pairs]


def expand_uv(params: dict[str, Any]) -> dict[str, Any]:
    """A trial's parameters with the grid's (u, v) pair "u/v" as u and v (what the configs get)."""
    out = {k: v for k, v in params.items() if k != UV}
    if UV in params:
        out["u"], out["v"] = (int(x) for x in str(params[UV]).split("/"))
    return out


def grid_space(s: SweepConfig) -> dict[str, list]:
    """The grid sampler's search space: each swept parameter's grid values; u and v as one
    parameter "uv" (values "u/v") when sweep.grid_uv gives pairs."""
    grids = {"m": list(s.grid_m), "u": list(s.grid_u), "v": list(s.grid_v), **GRID}
    pairs = uv_pairs(s)
    space = {p: grids[p] for p in s.space if not (pairs and p in ("u", "v"))}
    if pairs:
        space[UV] = uv_choices(pairs)
    return space


def suggest(trial, space: tuple[str, ...], pairs: tuple[tuple[int, int], ...] = ()) -> dict[str, Any]:
    """Sample the swept parameters (see the table in experiments/sweeps/runner.py); `pairs`: u and v as
    one (u, v) pair (uv_pairs)."""
    out: dict[str, Any] = {}
    if "m" in space:
        out["m"] = trial.suggest_int("m", *INT_RANGES["m"], log=True)
    if pairs:
        out.update(expand_uv({UV: trial.suggest_categorical(UV, uv_choices(pairs))}))
    else:
        if "u" in space:
            out["u"] = trial.suggest_int("u", *INT_RANGES["u"])
        if "v" in space:
            out["v"] = trial.suggest_int("v", *INT_RANGES["v"])
    if "feedback" in space:
        out["feedback"] = trial.suggest_categorical("feedback", GRID["feedback"])
    if "sigma_min" in space:
        out["sigma_min"] = trial.suggest_float("sigma_min", 1e-4, 1e-1, log=True)
    return out


def trial_configs(cfg: StudyConfig, params: dict[str, Any], seed: int):
    """(ModelConfig, TrainConfig) of one trial: profile -> variant -> swept values."""
    from experiments.cells import resolve_stm_configs

    model, train = resolve_stm_configs(cfg, cfg.sweep.task, cfg.sweep.variant, seed)
    model_over = {FIELDS[k][1]: v for k, v in params.items() if FIELDS[k][0] == "model"}
    train_over = {FIELDS[k][1]: v for k, v in params.items() if FIELDS[k][0] == "train"}
    return dataclasses.replace(model, **model_over), dataclasses.replace(train, **train_over)


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
            self._client = Client(self.uri, create=False)
        return self._client

    def start(self, trial) -> str:
        tags = {**self.tags, PARENT_TAG: self.parent_id, "role": "trial", "trial": str(trial.number),
                "optuna_study": trial.study.study_name}
        frozen = next(t for t in trial.study.get_trials(deepcopy=False) if t.number == trial.number)
        retried = retried_trial_number(frozen)
        if retried is not None:
            tags["retry_of_trial"] = str(retried)
        name = f"{self.tags.get('task', 'trial')}/{self.tags.get('variant', '')}/trial{trial.number}"
        run = self.client.create_run(self.experiment_id, run_name=name, tags=tags)
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
        from experiments.cell_run import seed_everything
        from stm.device import resolve_device

        run_id = link.start(trial)
        client = link.client
        params = suggest(trial, cfg.sweep.space, uv_pairs(cfg.sweep))
        seeds = [cfg.sweep.seed + k for k in range(cfg.sweep.seeds)]
        configs = [trial_configs(cfg, params, s) for s in seeds]
        model_cfg, train_cfg = configs[0]
        log_params(client, run_id, {**{f"trial.{k}": v for k, v in params.items()},
                                    **flatten({"model": model_cfg.to_dict(), "train": train_cfg.to_dict()}),
                                    "seeds": ",".join(map(str, seeds)), "task": cfg.sweep.task,
                                    "variant": cfg.sweep.variant, "device": str(resolve_device(cfg.device)),
                                    **provenance_params()})
        task = get_task(cfg.sweep.task, **cfg.data_options(cfg.sweep.task))
        demos = load_demos(task, seed=0)
        seed_everything(seeds[0])
        buffer = MetricBuffer(client, run_id)
        watch = SeedValidation(trial, seeds, buffer)
        try:
            models, seconds, iterations = train_seeds(model_cfg, [c[1] for c in configs], task, demos, buffer, watch,
                                                      cfg.device)
        except PackPruned as pruned:
            buffer.flush()
            raise optuna.TrialPruned(f"pruned at iteration {pruned.iteration}") from None
        buffer.flush()
        log_metrics(client, run_id, {"time/train_seconds": seconds})
        if watch.pruned:
            raise optuna.TrialPruned(f"pruned at iteration {iterations}")
        if cfg.sweep.objective in ("final_distance", "failure_rate"):
            per_seed = evaluate_seeds(cfg, models, seeds, train_cfg, task, client, run_id)
        else:
            if len(watch.last) < len(seeds):
                raise RuntimeError("training reported no validation metric (train.val_every > train.iters?)")
            per_seed = [watch.last[k] for k in range(len(seeds))]
        log_metrics(client, run_id, {f"objective/seed{s}": v for s, v in zip(seeds, per_seed, strict=True)})
        return float(np.mean(per_seed))

    return objective


class PackPruned(Exception):
    """Raised from a packed training's validation callback: the trial is pruned, every seed stops."""

    def __init__(self, iteration: int):
        super().__init__(f"pruned at iteration {iteration}")
        self.iteration = iteration


class SeedValidation:
    """The validation callback of a trial's seeds: keeps each seed's last value and, once every
    seed has reported an iteration, reports their mean to the pruner."""

    def __init__(self, trial, seeds: list[int], buffer: MetricBuffer):
        self.trial, self.seeds, self.buffer = trial, seeds, buffer
        self.last: dict[int, float] = {}
        self.pending: dict[int, dict[int, float]] = {}
        self.pruned = False

    def __call__(self, k: int, iteration: int, value: float) -> bool:
        self.last[k] = value
        K = len(self.seeds)
        if K > 1:
            self.buffer.add(iteration, {f"seed{self.seeds[k]}/val/metric": value})
        got = self.pending.setdefault(iteration, {})
        got[k] = value
        if len(got) < K:
            return False
        mean = float(np.mean(list(self.pending.pop(iteration).values())))
        self.buffer.add(iteration, {"val/metric": mean})
        if not math.isfinite(mean):
            return False
        self.trial.report(mean, iteration)
        if not self.trial.should_prune():
            return False
        self.pruned = True
        if K > 1:  # the callback stops one seed; a pruned trial stops them all at once
            raise PackPruned(iteration)
        return True


def train_seeds(model_cfg, train_cfgs: list, task, demos, buffer: MetricBuffer,
                watch: SeedValidation, device: str = "cpu") -> tuple[list, float, int]:
    """Train one model per train config (seed) on `device`, as one pack (one seed: a pack of one);
    (models, training seconds, iterations). A seed whose training diverged fails the trial."""
    from stm.training.loop import train_packed

    seeds = [c.seed for c in train_cfgs]
    # one seed's metrics are logged as they are, several seeds' as seed<s>/<name> (as evaluate_seeds does)
    prefixes = [""] if len(seeds) == 1 else [f"seed{s}/" for s in seeds]

    def on_metrics(k: int, iteration: int, metrics: dict[str, float]) -> None:
        buffer.add(iteration, {f"{prefixes[k]}{name}": v for name, v in metrics.items()})

    with tempfile.TemporaryDirectory(prefix="acrmdn-trial-") as tmp:
        results = train_packed(model_cfg, train_cfgs, task, demos, resume=False,
                               checkpoint_paths=[Path(tmp) / f"seed{s}.pt" for s in seeds],
                               on_metrics=on_metrics, on_validation=watch, device=device)
    for s, r in zip(seeds, results, strict=True):
        if r.failure is not None:
            if len(seeds) == 1:
                raise r.failure  # what stm.training.loop.train raises for a single model
            raise RuntimeError(f"seed {s}: {r.failure}") from r.failure
    return [r.model for r in results], max(r.seconds for r in results), max(r.iterations for r in results)


def evaluate_seeds(cfg: StudyConfig, models: list, seeds: list[int], train_cfg, task, client: Client,
                   run_id: str) -> list[float]:
    """Each seed's evaluation objective, on that seed's own episodes (as an ablation evaluates a
    cell: its dataset's options, its feedback); one seed's metrics are logged as they are, several
    seeds' as seed<s>/<name> plus their mean under <name>."""
    from experiments.evaluation import evaluate_model
    from stm.device import resolve_device

    ev = {**dataclasses.asdict(cfg.eval), "rollouts": cfg.sweep.eval_rollouts}
    per_seed, logged = [], []
    for model, seed in zip(models, seeds, strict=True):
        model = model.to(resolve_device(cfg.device))
        metrics, _ = evaluate_model(model, [cfg.sweep.task], ev, seed=seed, phi_mode=train_cfg.phi_mode,
                                    data=cfg.data_options(cfg.sweep.task), train_feedback=train_cfg.feedback,
                                    temperature=train_cfg.temperature, timings=False)
        per_seed.append(task.sweep_objective(cfg.sweep.objective, metrics))  # the task knows its error metric
        logged.append(metrics)
    if len(seeds) == 1:
        log_metrics(client, run_id, logged[0])
    else:
        shared = set.intersection(*(set(m) for m in logged))
        log_metrics(client, run_id, {**{f"seed{s}/{k}": v for s, m in zip(seeds, logged, strict=True)
                                        for k, v in m.items()},
                                     **{k: float(np.mean([m[k] for m in logged])) for k in sorted(shared)}})
    return per_seed
