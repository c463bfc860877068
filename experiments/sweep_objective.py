"""What one sweep trial does: sample the swept values, train the (task, variant) with them in
an MLflow child run under the sweep's parent run, and return the value Optuna minimises.

Objective: "val" = the last validation metric reported by `stm.train` (the closed-loop error
of rollouts on fresh task episodes), "final_distance" = the mean of the task's primary error
metric over `sweep.eval_rollouts` pybullet rollouts (`Task.sweep_objective`), or "failure_rate" = 1 - their
success rate (robust where one knocked-off block makes a mean distance of metres, as in
pick-and-place). The median pruner watches the validation metric through `on_validation`.
"""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path
from typing import Any

from experiments.config import StudyConfig
from experiments.sweep_storage import worker_id
from experiments.tracking import (
    PARENT_TAG,
    Client,
    MetricBuffer,
    flatten,
    log_metrics,
    log_params,
    provenance_params,
    set_tags,
)

GRID = {"m": [1, 3, 5, 10, 20], "u": [1, 2, 5, 10], "v": [0, 1, 2, 5, 10],
        "feedback": ["sample", "component_mean", "mixture_mean"], "sigma_min": [1e-4, 1e-3, 1e-2]}
FIELDS = {"m": ("model", "mixtures"), "u": ("train", "u"), "v": ("train", "v"),
          "feedback": ("train", "feedback"), "sigma_min": ("model", "sigma_min")}


def suggest(trial, space: tuple[str, ...]) -> dict[str, Any]:
    """Sample the swept parameters (see the table in experiments/sweep.py)."""
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
            self._client = Client(self.uri)
        return self._client

    def start(self, trial) -> str:
        tags = {**self.tags, PARENT_TAG: self.parent_id, "role": "trial", "trial": str(trial.number),
                "optuna_study": trial.study.study_name}
        frozen = next(t for t in trial.study.get_trials(deepcopy=False) if t.number == trial.number)
        retried = frozen.system_attrs.get("failed_trial")  # set by the retry callback (sweep_storage)
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
            return task.sweep_objective(cfg.sweep.objective, metrics)  # the task knows its error metric
        if "val" not in last:
            raise RuntimeError("training reported no validation metric (train.val_every > train.iters?)")
        return last["val"]

    return objective
