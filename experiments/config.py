"""Typed, validated study configs: profiles (TOML files in experiments/profiles/) plus
`--set a.b=value` overrides, checked field by field before anything is written.

A study config holds study-level fields (tasks, variants, seeds, workers), the model and
training overrides that go into `stm.config.ModelConfig` / `TrainConfig` (with per-task
overrides, since the paper sizes the reacher and pick-and-place models differently), the
evaluation protocol and the sweep settings. Every error is a `ConfigError` whose message is
one line naming the field and the allowed values.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import re
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

PROFILES_DIR = Path(__file__).parent / "profiles"
FEEDBACK_MODES = ("sample", "component_mean", "mixture_mean")
SAMPLERS = ("tpe", "grid", "random")
OBJECTIVES = ("val", "final_distance", "failure_rate")
SWEEP_PARAMS = ("m", "u", "v", "feedback", "sigma_min")


class ConfigError(ValueError):
    """A bad config value; str() is the one-line message shown to the user."""


@dataclass(frozen=True)
class EvalConfig:
    """How every trained model is evaluated in pybullet."""

    rollouts: int = 50  # evaluation episodes per evaluated task
    seed: int = 10_000  # episode seed; training seed s is evaluated on episodes of seed + s (same for every variant)
    feedback: str = "component_mean"  # fed back by an MDN in rollouts (one trained sampling samples)
    # read by the circle task itself (envs.tasks.circle.Circle.eval_options); kept here so config hashes stay
    circle_radii: tuple[float, ...] = (0.05, 0.10, 0.15)  # m; the paper's evaluation radii
    circle_unseen_radii: tuple[float, ...] = (0.075, 0.125)  # m; radii absent from the demos
    figures: int = 4  # rollouts drawn in each task's figure (0: no figures)


@dataclass(frozen=True)
class SweepConfig:
    """An Optuna sweep of one (task, variant); ranges are documented in experiments.sweep."""

    task: str = "reacher"
    variant: str = "ac-lstm-mdn"
    space: tuple[str, ...] = SWEEP_PARAMS
    trials: int = 20
    sampler: str = "tpe"
    storage: str = ""  # "" -> JournalFileBackend file next to mlflow.db; or postgresql://...
    objective: str = "val"  # "val": last validation metric; "final_distance": rollout goal error; "failure_rate"
    eval_rollouts: int = 10  # episodes for the final_distance / failure_rate objectives
    seed: int = 0
    study_name: str = ""  # "" -> "<task>-<variant>-<profile>"
    warmup_steps: int = 0  # median pruner: iterations before pruning may start
    startup_trials: int = 2  # median pruner: trials completed before pruning may start
    heartbeat: int = 10  # s; RDB storages (postgresql://, sqlite:///): a trial's process beats this often
    grace_period: int = 60  # s without a beat before a trial counts as dead (its worker was killed)
    max_retry: int = 2  # a dead worker's trial is re-queued with the same parameters this many times


@dataclass(frozen=True)
class StudyConfig:
    profile: str
    tasks: tuple[str, ...]  # training tasks; each model is evaluated on every task whose model_task it is
    variants: tuple[str, ...]
    seeds: int = 2  # seeds 0..seeds-1
    workers: int = 0  # 0: one per CPU core
    study_name: str = ""  # "" -> derived from the profile (and the config hash if overridden)
    model: dict[str, Any] = field(default_factory=dict)  # -> stm.config.ModelConfig
    train: dict[str, Any] = field(default_factory=dict)  # -> stm.config.TrainConfig
    per_task: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)  # task -> {model, train, data}
    eval: EvalConfig = field(default_factory=EvalConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)

    def to_dict(self) -> dict[str, Any]:
        return _jsonable(dataclasses.asdict(self))

    def data_options(self, task: str) -> dict[str, Any]:
        """Constructor options of a training task's dataset (per_task.<task>.data; {} = the task's defaults)."""
        return dict(self.per_task.get(task, {}).get("data", {}))

    def stm_dicts(self, task: str) -> tuple[dict[str, Any], dict[str, Any]]:
        """Model and train overrides for one training task (profile-wide, then per-task)."""
        extra = self.per_task.get(task, {})
        return {**self.model, **extra.get("model", {})}, {**self.train, **extra.get("train", {})}

    def study_hash(self) -> str:
        """Hash of everything that shapes results (not tasks/variants/seeds/workers, which select cells)."""
        d = self.to_dict()
        payload = {k: d[k] for k in ("model", "train", "per_task", "eval")}
        return config_hash(payload)

    def resolved_study_name(self) -> str:
        if self.study_name:
            return self.study_name
        base = load_profile(self.profile, overrides=())
        if base.study_hash() == self.study_hash():
            return self.profile
        return f"{self.profile}-{self.study_hash()[:8]}"


def config_hash(payload: Any) -> str:
    blob = json.dumps(_jsonable(payload), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _jsonable(x: Any) -> Any:
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


# ---------------------------------------------------------------- loading and overrides


def available_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILES_DIR.glob("*.toml"))


def load_profile(name: str, overrides: list[str] | tuple[str, ...] = (), **cli: Any) -> StudyConfig:
    """Profile file -> `--set` overrides -> explicit CLI options (None = not given) -> validated config."""
    profiles = available_profiles()
    if name not in profiles:
        raise ConfigError(f"profile: unknown profile {name!r}; allowed: {', '.join(profiles)}")
    with open(PROFILES_DIR / f"{name}.toml", "rb") as f:
        raw = tomllib.load(f)
    raw["profile"] = name
    for item in overrides:
        path, value = parse_override(item)
        set_path(raw, path, value)
    for key, value in cli.items():
        if value is not None:
            set_path(raw, key.split("."), value)
    return from_dict(raw)


def parse_override(item: str) -> tuple[list[str], Any]:
    """'a.b=value' -> (['a', 'b'], value); the value is read as TOML (ints, floats, bools,
    lists, quoted strings), anything else is a bare string."""
    if "=" not in item:
        raise ConfigError(f"--set: expected FIELD=VALUE, got {item!r}")
    key, text = item.split("=", 1)
    path = [p for p in key.strip().split(".")]
    if not all(path):
        raise ConfigError(f"--set: bad field name {key!r}")
    try:
        value = tomllib.loads(f"v = {text.strip()}")["v"]
    except tomllib.TOMLDecodeError:
        value = text.strip()
    return path, value


def set_path(raw: dict[str, Any], path: list[str], value: Any) -> None:
    node = raw
    for part in path[:-1]:
        child = node.setdefault(part, {})
        if not isinstance(child, dict):
            raise ConfigError(f"{'.'.join(path)}: {part!r} is a value, not a section")
        node = child
    node[path[-1]] = value


# ---------------------------------------------------------------- validation


def _coerce(name: str, value: Any, default: Any, annotation: str) -> Any:
    """Check one value against the type of its default (ints accepted for floats)."""
    if isinstance(default, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{name}: expected true or false, got {value!r}")
        return value
    if isinstance(default, int) and not isinstance(default, bool):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{name}: expected an integer, got {value!r}")
        return value
    if isinstance(default, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{name}: expected a number, got {value!r}")
        return float(value)
    if isinstance(default, str):
        if not isinstance(value, str):
            raise ConfigError(f"{name}: expected a string, got {value!r}")
        return value
    if isinstance(default, tuple):
        if isinstance(value, (str, int, float)):
            value = [value]
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{name}: expected a list, got {value!r}")
        inner = default[0] if default else ("" if "str" in annotation else 0.0)
        return tuple(_coerce(name, v, inner, annotation) for v in value)
    return value


def _build(cls: type, raw: dict[str, Any], prefix: str) -> Any:
    fields = {f.name: f for f in dataclasses.fields(cls)}
    unknown = sorted(set(raw) - set(fields))
    if unknown:
        raise ConfigError(f"{prefix}{unknown[0]}: unknown field; allowed: {', '.join(fields)}")
    defaults = cls()
    kwargs = {k: _coerce(prefix + k, v, getattr(defaults, k), str(fields[k].type)) for k, v in raw.items()}
    return cls(**kwargs)


def _check_positive(name: str, value: int | float, minimum: int | float = 1) -> None:
    if value < minimum:
        raise ConfigError(f"{name}: {value!r} is not allowed; allowed: integers >= {minimum}")


def _check_choice(name: str, value: Any, allowed: tuple[str, ...] | list[str]) -> None:
    if value not in allowed:
        raise ConfigError(f"{name}: {value!r} is not allowed; allowed: {', '.join(allowed)}")


def _check_stm_section(name: str, values: dict[str, Any], cls: type) -> dict[str, Any]:
    """Model/train overrides: known field names, values of the default's type, and whatever
    the stm dataclass itself checks (its from_dict/__post_init__ raise ValueError)."""
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: expected a section of FIELD = VALUE")
    defaults = cls()
    allowed = [f.name for f in dataclasses.fields(cls)]
    out = {}
    for key, value in values.items():
        if key not in allowed:
            raise ConfigError(f"{name}.{key}: unknown field; allowed: {', '.join(allowed)}")
        out[key] = _coerce(f"{name}.{key}", value, getattr(defaults, key), "")
    try:
        cls.from_dict({**defaults.to_dict(), **out})
    except (ValueError, TypeError) as e:
        msg = str(e).replace(f"{cls.__name__}.", f"{name}.")  # stm names fields ClassName.field
        # stm says "F must be one of (...), got X" / "F must be >= 0, got X": restate in our one-line form
        m = re.fullmatch(r"(\S+) must be (?:one of )?(.+), got (.+)", msg)
        if m:
            allowed = m.group(2).strip("()").replace("'", "")
            msg = f"{m.group(1)}: {m.group(3)} is not allowed; allowed: {allowed}"
        raise ConfigError(msg if msg.startswith(f"{name}.") else f"{name}: {msg}") from None
    return out


def _check_data_section(name: str, task: str, values: dict[str, Any]) -> dict[str, Any]:
    """Dataset options of a training task: keyword arguments of its constructor (e.g. n_demos),
    checked by building the task (it validates its own values)."""
    import inspect

    from envs.tasks import get_task
    from envs.tasks.base import TASKS

    if not isinstance(values, dict):
        raise ConfigError(f"{name}: expected a section of FIELD = VALUE")
    params = inspect.signature(TASKS[task].__init__).parameters
    allowed = [k for k in params if k != "self"]
    out = {}
    for key, value in values.items():
        if key not in allowed:
            raise ConfigError(f"{name}.{key}: unknown field; allowed: {', '.join(allowed) or 'none'}")
        default = params[key].default
        out[key] = _coerce(f"{name}.{key}", value, default, "") if default is not inspect.Parameter.empty else value
    try:
        get_task(task, **out)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{name}: {e}") from None
    return out


def known_tasks() -> dict[str, str]:
    """Registered task name -> its model_task."""
    from envs.tasks import TASKS  # importing the package registers the built-in tasks

    return {name: (cls.model_task or name) for name, cls in sorted(TASKS.items())}


def training_tasks() -> list[str]:
    return [name for name, model_task in known_tasks().items() if model_task == name]


def evaluation_tasks(training_task: str) -> list[str]:
    """Every task evaluated with the model trained on `training_task` (itself first)."""
    others = [n for n, m in known_tasks().items() if m == training_task and n != training_task]
    return [training_task, *others]


def known_variants() -> list[str]:
    from stm.registry import VARIANTS

    return list(VARIANTS)


def from_dict(raw: dict[str, Any]) -> StudyConfig:
    raw = copy.deepcopy(raw)
    from stm.config import ModelConfig, TrainConfig

    eval_cfg = _build(EvalConfig, raw.pop("eval", {}) or {}, "eval.")
    sweep_cfg = _build(SweepConfig, raw.pop("sweep", {}) or {}, "sweep.")
    model = _check_stm_section("model", raw.pop("model", {}) or {}, ModelConfig)
    train = _check_stm_section("train", raw.pop("train", {}) or {}, TrainConfig)

    tasks_allowed = training_tasks()
    per_task_raw = raw.pop("per_task", {}) or {}
    per_task: dict[str, dict[str, dict[str, Any]]] = {}
    for task, sections in per_task_raw.items():
        _check_choice("per_task", task, tasks_allowed)
        unknown = sorted(set(sections) - {"model", "train", "data"})
        if unknown:
            raise ConfigError(f"per_task.{task}.{unknown[0]}: unknown section; allowed: model, train, data")
        per_task[task] = {
            "model": _check_stm_section(f"per_task.{task}.model", sections.get("model", {}), ModelConfig),
            "train": _check_stm_section(f"per_task.{task}.train", sections.get("train", {}), TrainConfig),
        }
        if sections.get("data"):
            per_task[task]["data"] = _check_data_section(f"per_task.{task}.data", task, sections["data"])

    study_defaults = {"tasks": tuple(tasks_allowed), "variants": tuple(known_variants())}
    fields = {f.name for f in dataclasses.fields(StudyConfig)} - {"eval", "sweep", "model", "train", "per_task"}
    unknown = sorted(set(raw) - fields)
    if unknown:
        allowed = sorted(fields | {"eval", "sweep", "model", "train", "per_task"})
        raise ConfigError(f"{unknown[0]}: unknown field; allowed: {', '.join(allowed)}")
    template = StudyConfig(profile="", **study_defaults)
    kwargs = {k: _coerce(k, v, getattr(template, k), "str") for k, v in raw.items()}
    kwargs = {**study_defaults, **kwargs}
    cfg = StudyConfig(model=model, train=train, per_task=per_task, eval=eval_cfg, sweep=sweep_cfg, **kwargs)
    validate(cfg)
    return cfg


def validate(cfg: StudyConfig) -> None:
    tasks_allowed = training_tasks()
    all_tasks = list(known_tasks())
    variants_allowed = known_variants()
    if not cfg.tasks:
        raise ConfigError(f"tasks: empty; allowed: {', '.join(tasks_allowed)}")
    for t in cfg.tasks:
        if t in all_tasks and t not in tasks_allowed:
            raise ConfigError(f"tasks: {t!r} is evaluated with the {known_tasks()[t]!r} model, not trained; "
                              f"allowed: {', '.join(tasks_allowed)}")
        _check_choice("tasks", t, tasks_allowed)
    if not cfg.variants:
        raise ConfigError(f"variants: empty; allowed: {', '.join(variants_allowed)}")
    for v in cfg.variants:
        _check_choice("variants", v, variants_allowed)
    _check_positive("seeds", cfg.seeds)
    _check_positive("workers", cfg.workers, 0)
    e = cfg.eval
    _check_positive("eval.rollouts", e.rollouts)
    _check_positive("eval.figures", e.figures, 0)
    _check_choice("eval.feedback", e.feedback, FEEDBACK_MODES)
    from envs.tasks import task_class

    for name in all_tasks:  # each task checks the eval options it reads (Task.eval_options: the circle's radii)
        try:
            task_class(name).eval_options(dataclasses.asdict(e))
        except ValueError as exc:
            raise ConfigError(str(exc)) from None
    s = cfg.sweep
    _check_choice("sweep.task", s.task, tasks_allowed)
    _check_choice("sweep.variant", s.variant, variants_allowed)
    for p in s.space:
        _check_choice("sweep.space", p, SWEEP_PARAMS)
    if not s.space:
        raise ConfigError(f"sweep.space: empty; allowed: {', '.join(SWEEP_PARAMS)}")
    _check_positive("sweep.trials", s.trials)
    _check_positive("sweep.eval_rollouts", s.eval_rollouts)
    _check_positive("sweep.warmup_steps", s.warmup_steps, 0)
    _check_positive("sweep.startup_trials", s.startup_trials, 0)
    _check_positive("sweep.heartbeat", s.heartbeat)
    _check_positive("sweep.max_retry", s.max_retry, 0)
    if s.grace_period <= s.heartbeat:
        raise ConfigError(f"sweep.grace_period: {s.grace_period!r} is not allowed; allowed: integers > "
                          f"sweep.heartbeat ({s.heartbeat})")
    _check_choice("sweep.sampler", s.sampler, SAMPLERS)
    _check_choice("sweep.objective", s.objective, OBJECTIVES)
    if s.storage and not s.storage.startswith(("postgresql://", "postgresql+", "sqlite:///", "journal:")):
        raise ConfigError(f"sweep.storage: unsupported URL {s.storage!r}; allowed: postgresql://..., "
                          "sqlite:///..., journal:<path>, or empty for the journal file next to mlflow.db")
