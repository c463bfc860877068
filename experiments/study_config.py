"""Typed, validated study configs: a profile (a TOML file: one of experiments/profiles/ by name,
or any file by path) plus `--set a.b=value` overrides, resolved and typed once, before anything
is written.

A study config holds study-level fields (tasks, variants, seeds, workers), the model and
training overrides that go into `stm.config.ModelConfig` / `TrainConfig` (profile-wide and per
task, since the paper sizes the reacher and pick-and-place models differently), the evaluation
protocol and the sweep settings. `StudyConfig.task_configs` holds each training task's resolved
(ModelConfig, TrainConfig, dataset options). Field types and ranges are pydantic's
(stm.config.STRICT); every error is a `ConfigError` whose message is one line naming the field
and the allowed values (experiments.config_errors). A profile's [smoothing] and [idm] sections
belong to experiments.control_studies.
"""

from __future__ import annotations

import copy
import dataclasses
import hashlib
import json
import logging
import tomllib
from dataclasses import field
from pathlib import Path
from typing import Annotated, Any

from pydantic import BeforeValidator, field_validator
from pydantic.dataclasses import dataclass

from experiments.config_errors import ConfigError, as_tuple, tuples, validated
from experiments.eval_sweep_config import (  # noqa: F401 - re-exported: the config's names live here
    OBJECTIVES,
    SAMPLERS,
    SWEEP_PARAMS,
    EvalConfig,
    SweepConfig,
    choice,
    evaluation_tasks,
    hashed_eval,
    known_tasks,
    known_variants,
    training_tasks,
)
from experiments.runtime.study_names import RULE, is_study_name, optional_study_name, shown
from stm.config import STRICT, ModelConfig, NonNegativeInt, PositiveInt, TrainConfig

log = logging.getLogger(__name__)

PROFILES_DIR = Path(__file__).parent / "profiles"
POSTPROCESS_SECTIONS = ("smoothing", "idm")  # profile sections of experiments.control_studies
STM_SECTIONS = {"model": ModelConfig, "train": TrainConfig}

@dataclasses.dataclass(frozen=True)
class TaskConfig:
    """One training task's resolved configs: defaults <- profile-wide <- per_task (no variant yet)."""

    model: ModelConfig
    train: TrainConfig
    data: dict[str, Any]  # constructor options of the task's dataset (per_task.<task>.data; {} = defaults)


def _all_or_tuple(value: Any, known) -> Any:
    """`"all"` (or `["all"]`) selects every registered name, so a new task or variant joins such profiles."""
    return tuple(known()) if value == "all" or list(as_tuple(value)) == ["all"] else as_tuple(value)


@dataclass(frozen=True, config=STRICT)
class StudyConfig:
    profile: str
    # training tasks; each model is evaluated on every task whose model_task it is ("all": every one)
    tasks: Annotated[tuple[str, ...], BeforeValidator(lambda v: _all_or_tuple(v, training_tasks))]
    variants: Annotated[tuple[str, ...], BeforeValidator(lambda v: _all_or_tuple(v, known_variants))]  # or "all"
    seeds: PositiveInt = 2  # seeds 0..seeds-1
    workers: NonNegativeInt = 0  # 0: one per CPU core
    pack: NonNegativeInt = 0  # seeds of a cell group trained together (experiments/pack.py); 0: all, 1: unpacked
    # every N iterations a copy of each cell's checkpoint stays in its run (artifact checkpoint_at/<iteration>/),
    # so that a long run's intermediate models can be evaluated later (success vs iterations); 0: none. Not hashed.
    keep_checkpoints: NonNegativeInt = 0
    # where the cells train: auto | cpu | cuda | cuda:N (stm.device); --device; not hashed (the same study on
    # any machine), recorded as each run's param "device"
    device: str = "cpu"
    resume_from_weights: bool = False  # --resume-from-weights (experiments/weights_resume.py); not hashed
    study_name: str = ""  # the parent run's name; load_profile derives it (see derived_study_name)
    model: dict[str, Any] = field(default_factory=dict)  # the profile's (and --set) ModelConfig values
    train: dict[str, Any] = field(default_factory=dict)  # ... TrainConfig values
    per_task: dict[str, dict[str, dict[str, Any]]] = field(default_factory=dict)  # task -> {model, train, data}
    eval: EvalConfig = field(default_factory=EvalConfig)
    sweep: SweepConfig = field(default_factory=SweepConfig)
    # resolved from the fields above by from_dict, for every training task (not part of to_dict)
    task_configs: dict[str, Any] = field(default_factory=dict, repr=False, compare=False)

    @field_validator("tasks")
    @classmethod
    def _tasks(cls, tasks: tuple[str, ...]) -> tuple[str, ...]:
        allowed = training_tasks()
        if not tasks:
            raise ValueError(f"empty; allowed: {', '.join(allowed)}")
        for t in tasks:
            model_task = known_tasks().get(t)
            if model_task is not None and t not in allowed:
                raise ValueError(f"{t!r} is evaluated with the {model_task!r} model, not trained; "
                                 f"allowed: {', '.join(allowed)}")
            choice(t, allowed)
        return tasks

    @field_validator("study_name")
    @classmethod
    def _study_name(cls, name: str) -> str:
        return optional_study_name(name)

    @field_validator("device")
    @classmethod
    def _device(cls, device: str) -> str:
        from stm.device import check_device_name

        return check_device_name(device)

    @field_validator("variants")
    @classmethod
    def _variants(cls, variants: tuple[str, ...]) -> tuple[str, ...]:
        if not variants:
            raise ValueError(f"empty; allowed: {', '.join(known_variants())}")
        for v in variants:
            choice(v, known_variants())
        return variants

    def to_dict(self) -> dict[str, Any]:
        """Plain data (from_dict(to_dict()) is this config); the resolved task configs are left out."""
        return _jsonable({f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name != "task_configs"})

    def task_config(self, task: str) -> TaskConfig:
        return self.task_configs[task]

    def data_options(self, task: str) -> dict[str, Any]:
        """Constructor options of a training task's dataset (per_task.<task>.data; {} = the task's defaults)."""
        return dict(self.task_configs[task].data)

    def study_hash(self) -> str:
        """Hash of everything that shapes results (not tasks/variants/seeds, which select cells, nor
        workers/pack/keep_checkpoints/device/resume_from_weights)."""
        d = self.to_dict()
        d["eval"] = hashed_eval(d["eval"])  # options at their default absent, as in Cell.eval_dict: earlier hashes stay
        for key in TrainConfig.UNHASHED:  # a route, as in Cell.resolved: the same study on either
            d["train"].pop(key, None)
            for task, sections in list(d["per_task"].items()):
                if key in sections.get("train", {}):  # and the sections it leaves empty, as if never written
                    del sections["train"][key]
                    if not sections["train"]:
                        del sections["train"]
                    if not any(sections.values()):
                        del d["per_task"][task]
        return config_hash({k: d[k] for k in ("model", "train", "per_task", "eval")})

    def resolved_study_name(self) -> str:
        if self.study_name:
            return self.study_name
        if self.profile in available_profiles():  # a config built by from_dict alone: compare with its profile
            return derived_study_name(self, load_profile(self.profile))
        return self.profile


def derived_study_name(cfg: StudyConfig, base: StudyConfig) -> str:
    """The profile's name for the profile as it is; else <profile>-<hash> of what differs: the
    config (study_hash), and the tasks and variants when they are not the profile's, so that
    studies of other cells never share (and overwrite) one parent run. Seeds and workers select
    cells of the same study (a re-run with more seeds continues it). A study evaluated on the validation episodes
    (eval.split) says so at the end of its name."""
    suffix = "-validation" if cfg.eval.split == "validation" and base.eval.split != "validation" else ""
    same_cells = (sorted(cfg.tasks), sorted(cfg.variants)) == (sorted(base.tasks), sorted(base.variants))
    if same_cells:
        same = cfg.study_hash() == base.study_hash()
        return cfg.profile if same else f"{cfg.profile}-{cfg.study_hash()[:8]}{suffix}"
    selection = config_hash({"study": cfg.study_hash(), "tasks": sorted(cfg.tasks), "variants": sorted(cfg.variants)})
    return f"{cfg.profile}-{selection[:8]}{suffix}"


def config_hash(payload: Any) -> str:
    blob = json.dumps(_jsonable(payload), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(blob.encode()).hexdigest()[:16]


def _jsonable(x: Any) -> Any:
    if dataclasses.is_dataclass(x) and not isinstance(x, type):
        return _jsonable(dataclasses.asdict(x))
    if isinstance(x, dict):
        return {str(k): _jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [_jsonable(v) for v in x]
    return x


# ---------------------------------------------------------------- profiles and overrides


def available_profiles() -> list[str]:
    return sorted(p.stem for p in PROFILES_DIR.glob("*.toml"))


def read_profile(name: str) -> tuple[str, dict[str, Any]]:
    """(profile name, the file's TOML): a profile of experiments/profiles/ by name, or any TOML file
    by path (its name is the file's stem)."""
    path = Path(name)
    if name.endswith(".toml") or len(path.parts) > 1:
        profile = path.stem
        builtin = PROFILES_DIR / f"{profile}.toml"
        if profile in available_profiles() and path.resolve() != builtin.resolve():
            raise ConfigError(f"profile: {name}: a built-in profile is called {profile!r} (its studies would "
                              "mix with this file's); rename the file")
    elif name in available_profiles():
        path, profile = PROFILES_DIR / f"{name}.toml", name
    else:
        raise ConfigError(f"profile: unknown profile {name!r}; allowed: {', '.join(available_profiles())}, "
                          "or the path of a .toml file")
    try:
        text = path.read_bytes().decode("utf-8")
    except OSError as e:
        raise ConfigError(f"profile: cannot read {name}: {e.strerror or e}") from None
    except UnicodeDecodeError:
        raise ConfigError(f"profile: {name}: not UTF-8 text") from None
    try:
        return profile, tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:  # its message ends with "(at line L, column C)"
        raise ConfigError(f"profile: {name}: {e}") from None


def load_profile(name: str, overrides: list[str] | tuple[str, ...] = (), **cli: Any) -> StudyConfig:
    """Profile file -> `--set` overrides -> explicit CLI options (None = not given) -> validated,
    resolved config with its study name."""
    profile, raw = read_profile(name)
    return study_config(profile, raw, overrides, **cli)


def study_config(profile: str, file_raw: dict[str, Any], overrides: list[str] | tuple[str, ...] = (),
                 **cli: Any) -> StudyConfig:
    file_raw = {k: v for k, v in file_raw.items() if k not in POSTPROCESS_SECTIONS}
    raw = {**copy.deepcopy(file_raw), "profile": profile}
    parsed = [(item, *parse_override(item)) for item in overrides]
    notes = [note for item, path, _ in parsed if (note := _command_line_wins(raw, path, item))]
    for _, path, value in parsed:
        set_path(raw, path, value)
    for key, value in cli.items():
        if value is not None:
            set_path(raw, key.split("."), value)
    cfg = from_dict(raw)
    if not cfg.study_name:
        name = derived_study_name(cfg, from_dict({**file_raw, "profile": profile}))
        if not is_study_name(name):  # a profile file whose stem is no study name (a space, a quote, too long)
            raise ConfigError(f"profile: the study name it gives, {shown(name)}, is not allowed ({RULE}); rename "
                              "the profile file or pass --study-name")
        cfg = dataclasses.replace(cfg, study_name=name)
    for note in notes:  # once the config is valid: a command that is refused prints its one error line only
        log.warning("%s", note)
    return cfg


def _command_line_wins(raw: dict[str, Any], path: list[str], item: str) -> str:
    """`--set train.u=3` is for every task: a per_task value of the profile for the same field would
    shadow it, so it is dropped for this run; the line that says so ("" when nothing was dropped)."""
    if len(path) != 2 or path[0] not in STM_SECTIONS or not isinstance(raw.get("per_task"), dict):
        return ""
    section, key = path
    dropped = []
    for task, sections in raw["per_task"].items():
        values = sections.get(section) if isinstance(sections, dict) else None
        if isinstance(values, dict) and key in values:
            dropped.append(f"per_task.{task}.{section}.{key} = {values.pop(key)!r}")
    if not dropped:
        return ""
    return f"--set {item} applies to every task: it replaces the profile's {', '.join(dropped)} for this run"


def parse_override(item: str) -> tuple[list[str], Any]:
    """'a.b=value' -> (['a', 'b'], value); the value is read as TOML (ints, floats, bools,
    lists, quoted strings), anything else is a bare string."""
    if "=" not in item:
        raise ConfigError(f"--set: expected FIELD=VALUE, got {item!r}")
    key, text = item.split("=", 1)
    path = key.strip().split(".")
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

def from_dict(raw: dict[str, Any]) -> StudyConfig:
    """A study config from plain data (a profile with its overrides, or to_dict's output)."""
    raw = tuples(copy.deepcopy(raw))
    sections = {name: _section(name, raw.pop(name, None)) for name in ("eval", "sweep", "model", "train")}
    eval_cfg = validated(EvalConfig, sections["eval"], "eval")
    _check_eval_options(eval_cfg)
    sweep_cfg = validated(SweepConfig, sections["sweep"], "sweep")
    stm = {name: _stm_values(name, sections[name], cls) for name, cls in STM_SECTIONS.items()}
    per_task = _per_task(_section("per_task", raw.pop("per_task", None)))
    task_configs = {}
    for task in training_tasks():
        own = per_task.get(task, {})
        task_configs[task] = TaskConfig(ModelConfig(**{**stm["model"], **own.get("model", {})}),
                                        TrainConfig(**{**stm["train"], **own.get("train", {})}),
                                        dict(own.get("data", {})))
    raw.setdefault("tasks", tuple(training_tasks()))
    raw.setdefault("variants", tuple(known_variants()))
    cfg = validated(StudyConfig, {**raw, "model": stm["model"], "train": stm["train"], "per_task": per_task,
                                  "eval": eval_cfg, "sweep": sweep_cfg, "task_configs": task_configs}, "",
                    hidden=("task_configs",))
    _check_variants(cfg)
    return cfg


def _section(name: str, values: Any) -> dict[str, Any]:
    if values is None:
        return {}
    if not isinstance(values, dict):
        raise ConfigError(f"{name}: expected a section of FIELD = VALUE")
    return values


def _stm_values(name: str, values: dict[str, Any], cls: type) -> dict[str, Any]:
    """The section's values as the stm dataclass types them (checked against its defaults). A study trains at least
    one iteration: with none a cell would evaluate an untrained model and report it as a result (stm's TrainConfig
    allows 0 for its own callers)."""
    iters = values.get("iters")
    if cls is TrainConfig and isinstance(iters, int) and not isinstance(iters, bool) and iters < 1:
        raise ConfigError(f"{name}.iters: {iters!r} is not allowed; allowed: integers >= 1")
    typed = validated(cls, values, name)
    return {k: getattr(typed, k) for k in values}


def _per_task(raw: dict[str, Any]) -> dict[str, dict[str, dict[str, Any]]]:
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for task, sections in raw.items():
        try:
            choice(task, training_tasks())
        except ValueError as e:
            raise ConfigError(f"per_task: {e}") from None
        sections = _section(f"per_task.{task}", sections)
        unknown = sorted(set(sections) - {"model", "train", "data"})
        if unknown:
            raise ConfigError(f"per_task.{task}.{unknown[0]}: unknown section; allowed: model, train, data")
        out[task] = {name: _stm_values(f"per_task.{task}.{name}", _section(f"per_task.{task}.{name}",
                                                                             sections.get(name)), cls)
                     for name, cls in STM_SECTIONS.items()}
        if sections.get("data"):
            out[task]["data"] = _data_options(f"per_task.{task}.data", task, _section(f"per_task.{task}.data",
                                                                                      sections["data"]))
    return out


def _data_options(name: str, task: str, values: dict[str, Any]) -> dict[str, Any]:
    """Dataset options of a training task: keyword arguments of its constructor (e.g. n_demos),
    typed by its signature, then checked by building the task (it validates its own values)."""
    from envs.tasks import get_task
    from experiments.config_errors import signature_model

    typed = validated(signature_model(task), values, name)
    out = {k: getattr(typed, k) for k in values}
    try:
        get_task(task, **out)
    except (ValueError, TypeError) as e:
        raise ConfigError(f"{name}: {e}") from None
    return out


def _check_eval_options(eval_cfg: EvalConfig) -> None:
    """Each task checks the eval options it reads (Task.eval_options: the circle's radii)."""
    from envs.tasks import task_class

    for name in known_tasks():
        try:
            task_class(name).eval_options(dataclasses.asdict(eval_cfg))
        except ValueError as exc:
            raise ConfigError(str(exc).splitlines()[0]) from None


def _check_variants(cfg: StudyConfig) -> None:
    """A variant that contradicts the config (auto-conditioning with v = 0) fails now, not in a worker."""
    from stm.variants import get_variant

    for task in cfg.tasks:
        tc = cfg.task_configs[task]
        for variant in cfg.variants:
            try:
                get_variant(variant).configs(tc.model, tc.train)
            except ValueError as e:
                name = f"per_task.{task}.train.v" if "v" in cfg.per_task.get(task, {}).get("train", {}) else "train.v"
                raise ConfigError(f"{name}: {str(e).splitlines()[0]}") from None
