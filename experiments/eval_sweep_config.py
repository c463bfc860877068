"""The [eval] and [sweep] sections of a study config, and the registries their values come from
(tasks of envs.tasks, variants of stm.variants). Types and ranges are pydantic's (stm.config.STRICT);
experiments.study_config re-exports everything here."""

from __future__ import annotations

from typing import Annotated, Any, Literal, get_args

from pydantic import BeforeValidator, Field, ValidationInfo, field_validator
from pydantic.dataclasses import dataclass

from experiments.config_errors import as_tuple
from experiments.runtime.study_names import optional_study_name
from stm.config import STRICT, NonNegativeInt, PositiveInt

Sampler = Literal["tpe", "grid", "random"]
Objective = Literal["val", "final_distance", "failure_rate"]
Pruner = Literal["median", "none"]
SweepParam = Literal["m", "u", "v", "feedback", "sigma_min"]
# what a rollout may feed back (stm.rollout.FEEDBACKS): a model trains with a Feedback, and its rollouts may
# also commit to one component per segment (segment_component, segment_track) or draw one per step
RolloutFeedback = Literal["component_mean", "mixture_mean", "sample", "sample_component", "segment_component",
                          "segment_track"]
# which episodes an evaluation draws: the headline's ("test") or those protocol choices are made on ("validation")
Split = Literal["test", "validation"]
StackRestart = Literal["place_pose", "start"]  # where stacking restarts the model between blocks (envs.tasks.stack)
SuccessCriterion = Literal["strict", "placed"]  # what pick-and-place's success holds (envs.tasks.pickplace)
SPLITS: tuple[str, ...] = get_args(Split)
VALIDATION_SEED_OFFSET = 10_000  # validation episodes: eval seed + this + training seed (20,000 + s by default)
VALIDATION_ROLLOUTS = 34  # episodes per seed and task of a validation evaluation unless told (milestones --split)
# eval fields left out of a cell's and a study's hash at these defaults: studies from before each field keep theirs
UNHASHED_DEFAULTS: dict[str, object] = {"mode_repeats": 0, "split": "test", "stack_restart": "place_pose",
                                        "success": "strict"}
SAMPLERS: tuple[str, ...] = get_args(Sampler)
OBJECTIVES: tuple[str, ...] = get_args(Objective)
SWEEP_PARAMS: tuple[str, ...] = get_args(SweepParam)


# integer ranges of the swept values (TPE / random draw from them; grid values must lie in them)
INT_RANGES: dict[str, tuple[int, int]] = {"m": (1, 20), "u": (1, 10), "v": (0, 10)}
IntGrid = Annotated[tuple[int, ...], BeforeValidator(as_tuple)]
Radii = Annotated[tuple[Annotated[float, Field(allow_inf_nan=False)], ...], BeforeValidator(as_tuple)]


@dataclass(frozen=True, config=STRICT)
class EvalConfig:
    """How every trained model is evaluated in pybullet."""

    rollouts: PositiveInt = 50  # evaluation episodes per evaluated task
    seed: int = 10_000  # episode seed; training seed s is evaluated on episodes of seed + s (same for every variant)
    feedback: RolloutFeedback = "component_mean"  # fed back by an MDN in rollouts (one trained sampling samples)
    # read by the circle task itself (envs.tasks.circle.Circle.eval_options); kept here so config hashes stay
    circle_radii: Radii = (0.05, 0.10, 0.15)  # m; the paper's evaluation radii
    circle_unseen_radii: Radii = (0.075, 0.125)  # m; radii absent from the demos
    figures: NonNegativeInt = 4  # rollouts drawn in each task's figure (0: no figures)
    # tasks with modes: each episode rolled out this many times with distinct sampling seeds, mode use per
    # episode measured (experiments.mode_repeats); 0: not measured. Left out of the hash when 0.
    mode_repeats: NonNegativeInt = 0
    # "validation": the episodes of eval seed + VALIDATION_SEED_OFFSET + training seed, disjoint from the headline's
    # ("test"), for choosing a protocol; never for a headline table (experiments.evaluation.split_seed). Left out
    # of the hash when "test".
    split: Split = "test"
    # stacking between the blocks: "place_pose" (restart where the last place ended) or "start" (a scripted lift and
    # move to a drawn start configuration first; envs.tasks.stack_protocol). Left out of the hash at "place_pose".
    stack_restart: StackRestart = "place_pose"
    # pick-and-place (and its changing goal): what an episode's success holds, "strict" (the block placed and the
    # last grip command open) or "placed" (the block judged alone); both are recorded per episode either way
    # (envs.tasks.pickplace.run_pick_place). Left out of the hash at "strict".
    success: SuccessCriterion = "strict"


@dataclass(frozen=True, config=STRICT)
class SweepConfig:
    """An Optuna sweep of one (task, variant); ranges are documented in experiments.sweeps.runner."""

    task: str = "reacher"
    variant: str = "ac-lstm-mdn"
    space: Annotated[tuple[SweepParam, ...], BeforeValidator(as_tuple)] = SWEEP_PARAMS
    trials: PositiveInt = 20
    sampler: Sampler = "tpe"
    storage: str = ""  # "" -> JournalFileBackend file next to mlflow.db; or postgresql://...
    objective: Objective = "val"  # "val": last validation metric; "final_distance": rollout goal error; "failure_rate"
    eval_rollouts: PositiveInt = 10  # episodes for the final_distance / failure_rate objectives
    seed: int = 0
    study_name: str = ""  # "" -> "<task>-<variant>-<profile>"
    warmup_steps: NonNegativeInt = 0  # median pruner: iterations before pruning may start
    startup_trials: NonNegativeInt = 2  # median pruner: trials completed before pruning may start
    pruner: Pruner = "median"  # "none": every trial trains to the end (a grid whose every point counts)
    heartbeat: PositiveInt = 10  # s; RDB storages (postgresql://, sqlite:///): a trial's process beats this often
    grace_period: int = 60  # s without a beat before a trial counts as dead (its worker was killed)
    max_retry: NonNegativeInt = 2  # a dead worker's trial is re-queued with the same parameters this many times
    seeds: PositiveInt = 1  # training seeds per trial (seed .. seed+seeds-1, packed); the objective is their mean
    tpe_startup: PositiveInt | None = None  # TPE's random start-up trials; None: max(1, trials // 3)
    # the grid sampler's values (experiments.sweeps.runner); grid_uv: (u, v) pairs swept together instead of
    # grid_u x grid_v
    grid_m: IntGrid = (1, 3, 5, 10, 20)
    grid_u: IntGrid = (1, 2, 5, 10)
    grid_v: IntGrid = (0, 1, 2, 5, 10)
    grid_uv: tuple[tuple[int, int], ...] = ()

    @field_validator("task")
    @classmethod
    def _task(cls, task: str) -> str:
        return choice(task, training_tasks())

    @field_validator("variant")
    @classmethod
    def _variant(cls, variant: str) -> str:
        return choice(variant, known_variants())

    @field_validator("study_name")
    @classmethod
    def _study_name(cls, name: str) -> str:
        return optional_study_name(name)

    @field_validator("space")
    @classmethod
    def _space(cls, space: tuple[str, ...]) -> tuple[str, ...]:
        if not space:
            raise ValueError(f"empty; allowed: {', '.join(SWEEP_PARAMS)}")
        return space

    @field_validator("storage")
    @classmethod
    def _storage(cls, url: str) -> str:
        if url and not url.startswith(("postgresql://", "postgresql+", "sqlite:///", "journal:")):
            raise ValueError(f"unsupported URL {url!r}; allowed: postgresql://..., sqlite:///..., journal:<path>, "
                             "or empty for the journal file next to mlflow.db")
        return url

    @field_validator("grid_m", "grid_u", "grid_v")
    @classmethod
    def _grid(cls, values: tuple[int, ...], info: ValidationInfo) -> tuple[int, ...]:
        return grid_values(values, info.field_name.removeprefix("grid_"))

    @field_validator("grid_uv", mode="before")
    @classmethod
    def _uv_shape(cls, pairs: Any) -> Any:
        if not isinstance(pairs, (list, tuple)) or any(not isinstance(p, (list, tuple)) or len(p) != 2 for p in pairs):
            shown = [list(x) if isinstance(x, tuple) else x for x in pairs] if isinstance(pairs, tuple) else pairs
            raise ValueError(f"{shown!r} is not allowed; allowed: a list of [u, v] pairs, e.g. [[1, 9], [5, 5]]")
        return pairs

    @field_validator("grid_uv")
    @classmethod
    def _grid_uv(cls, pairs: tuple[tuple[int, int], ...]) -> tuple[tuple[int, int], ...]:
        for u, v in pairs:
            grid_values((u,), "u", "u of a pair")
            grid_values((v,), "v", "v of a pair")
        if len(set(pairs)) != len(pairs):
            raise ValueError("a (u, v) pair appears twice; allowed: distinct pairs [u, v]")
        return pairs

    def tpe_startup_trials(self) -> int:
        """TPE's n_startup_trials: `tpe_startup`, else a third of the trials (at least one)."""
        return self.tpe_startup if self.tpe_startup is not None else max(1, self.trials // 3)

    @field_validator("grace_period")
    @classmethod
    def _grace(cls, grace: int, info: ValidationInfo) -> int:
        beat = info.data.get("heartbeat")
        if beat is not None and grace <= beat:
            raise ValueError(f"{grace!r} is not allowed; allowed: integers > sweep.heartbeat ({beat})")
        return grace


def known_tasks() -> dict[str, str]:
    """Registered task name -> its model_task."""
    from envs.tasks import model_task_of, task_names

    return {name: model_task_of(name) for name in sorted(task_names())}


def training_tasks() -> list[str]:
    from envs.tasks import training_tasks

    return training_tasks()


def evaluation_tasks(training_task: str) -> list[str]:
    """Every task evaluated with the model trained on `training_task` (itself first)."""
    from envs.tasks import evaluation_tasks

    return evaluation_tasks(training_task)


def known_variants() -> list[str]:
    from stm.variants import VARIANTS

    return list(VARIANTS)


def grid_values(values: tuple[int, ...], param: str, what: str = "") -> tuple[int, ...]:
    """Grid values of an integer swept parameter: distinct, within its range (INT_RANGES)."""
    low, high = INT_RANGES[param]
    if not values:
        raise ValueError(f"empty; allowed: integers {low}..{high}")
    for x in values:
        if isinstance(x, bool) or not isinstance(x, int) or not low <= x <= high:
            raise ValueError(f"{x!r} is not allowed{' as ' + what if what else ''}; allowed: integers {low}..{high}")
    if len(set(values)) != len(values):
        raise ValueError(f"a value appears twice in {list(values)}; allowed: distinct integers {low}..{high}")
    return values


def choice(value: Any, allowed: list[str] | tuple[str, ...]) -> Any:
    if value not in allowed:
        raise ValueError(f"{value!r} is not allowed; allowed: {', '.join(allowed)}")
    return value


def hashed_eval(values: dict[str, Any]) -> dict[str, Any]:
    """An eval section as hashed: the fields of UNHASHED_DEFAULTS left out where they hold their default."""
    return {k: v for k, v in values.items() if k not in UNHASHED_DEFAULTS or v != UNHASHED_DEFAULTS[k]}
