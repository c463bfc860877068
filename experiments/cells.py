"""Cells of an ablation study: one (training task, variant, seed) with its fully resolved, typed
model/train/eval configs and the hash that identifies it across re-runs."""

from __future__ import annotations

import dataclasses
import functools
from dataclasses import dataclass, field
from typing import Any

from experiments.study_config import EvalConfig, StudyConfig, config_hash, evaluation_tasks, hashed_eval
from stm.config import ModelConfig, TrainConfig


@dataclass(frozen=True)
class Cell:
    task: str  # training task
    variant: str
    seed: int
    model: ModelConfig  # variant applied
    train: TrainConfig  # variant applied, seed set
    eval: EvalConfig
    eval_tasks: tuple[str, ...]
    profile: str
    study_name: str
    dataset_seed: int = 0  # the demonstrations are the same for every training seed
    data: dict[str, Any] = field(default_factory=dict)  # training task's constructor options (e.g. n_demos)
    keep_checkpoints: int = 0  # StudyConfig.keep_checkpoints (not hashed: it shapes no result)
    device: str = "cpu"  # StudyConfig.device: where it trains (not hashed; the run's param "device")
    resume_from_weights: bool = False  # StudyConfig.resume_from_weights (not hashed: experiments/weights_resume.py)

    @property
    def key(self) -> str:
        return f"{self.task}/{self.variant}/seed{self.seed}"

    @property
    def resolved(self) -> dict[str, Any]:
        """Everything that shapes this cell's results: hashed, logged as params and config.json."""
        out = {"task": self.task, "variant": self.variant, "seed": self.seed, "model": self.model.hashed_dict(),
               "train": self.train.hashed_dict(), "eval": self.eval_dict(), "eval_tasks": list(self.eval_tasks),
               "dataset_seed": self.dataset_seed}
        if self.data:  # absent when default: cells of profiles without data options keep their hashes
            out["data"] = self.data
        return out

    def eval_dict(self) -> dict[str, Any]:
        out = {k: list(v) if isinstance(v, tuple) else v for k, v in dataclasses.asdict(self.eval).items()}
        return hashed_eval(out)  # options at their default absent: cells of studies before them keep their hashes

    @functools.cached_property  # (a frozen cell: computed once; a study of 20,000 cells asks for each twice)
    def config_hash(self) -> str:
        return config_hash(self.resolved)

    def to_dict(self) -> dict[str, Any]:
        return dataclasses.asdict(self)

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> Cell:
        """The inverse of to_dict (plain data, e.g. JSON)."""
        return cls(**{**d, "model": ModelConfig.from_dict(d["model"]), "train": TrainConfig.from_dict(d["train"]),
                      "eval": EvalConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d["eval"].items()}),
                      "eval_tasks": tuple(d["eval_tasks"])})


def resolve_stm_configs(cfg: StudyConfig, task: str, variant: str, seed: int) -> tuple[ModelConfig, TrainConfig]:
    """(ModelConfig, TrainConfig) for one cell: the task's resolved configs <- seed <- variant."""
    from stm.variants import get_variant

    tc = cfg.task_config(task)
    return get_variant(variant).configs(tc.model, dataclasses.replace(tc.train, seed=seed))


def build_cells(cfg: StudyConfig) -> list[Cell]:
    study_name = cfg.resolved_study_name()
    cells = []
    for task in cfg.tasks:
        eval_tasks = tuple(evaluation_tasks(task))
        for variant in cfg.variants:
            for seed in range(cfg.seeds):
                model, train = resolve_stm_configs(cfg, task, variant, seed)
                cells.append(Cell(task=task, variant=variant, seed=seed, model=model, train=train, eval=cfg.eval,
                                  eval_tasks=eval_tasks, profile=cfg.profile, study_name=study_name,
                                  data=cfg.data_options(task), keep_checkpoints=cfg.keep_checkpoints,
                                  device=cfg.device, resume_from_weights=cfg.resume_from_weights))
    return cells
