"""`python -m experiments smoothing|idm`: the post-processing studies (stm.smoothing,
stm.idm_study) as tracked MLflow studies.

One experiment per kind ("smoothing", "idm"); each study is one parent run (tags kind,
profile, study_name, role=parent, skeleton_source) holding the study's metrics (step 0),
its config as params (plus git commit and package versions), and its figures (PNG + PDF
under figures/; the IDM's checkpoints under idm/). A re-run of the same study name reuses
the run: metrics get new values, changed params become `changed.<key>` tags.

Skeletons / plans: with `skeletons = "auto"` (default) the newest FINISHED ablation cell
for reacher with variant ac-lstm-mdn that has a checkpoint artifact supplies the STM
(stm.plans.stm_plans to the four reacher goals); without one, the documented stand-in
(smoothing: stm.plans.jittery_skeletons of the IK expert's plans; idm: the IK expert's
plans, stm.plans.straight_line_plans). "stm" requires the STM, "stand-in" never looks.
The tag `skeleton_source` says which was used.

Config: a profile (smoke | quick | paper) plus `--set FIELD=VALUE` overrides, validated
field by field before anything is written; a bad value is a one-line error, exit code 2.
"""

from __future__ import annotations

import argparse
import contextlib
import dataclasses
import logging
import math
import os
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from experiments.config import (
    ConfigError,
    _build,
    _check_choice,
    _check_positive,
    config_hash,
    parse_override,
    set_path,
)

log = logging.getLogger(__name__)

KINDS = ("smoothing", "idm")
PROFILES = ("smoke", "quick", "paper")
SKELETON_SOURCES = ("auto", "stm", "stand-in")
STM_TASK, STM_VARIANT = "reacher", "ac-lstm-mdn"


# ---------------------------------------------------------------- configs


@dataclass(frozen=True)
class SmoothingSettings:
    """Arguments of stm.smoothing.smoothing_study plus where the skeletons come from."""

    gamma: float = 5.0  # weight of the velocity term
    goal_weight: float = 50.0  # weight of the final-tip goal term (gd_goal variant)
    iters: int = 300  # gradient-descent iterations
    steps: int = 60  # skeleton length T (STM horizon / IK expert steps)
    step_seconds: float = 0.1  # the STM's step, for jerk and speed in SI units
    seed: int = 0  # stand-in jitter draw
    skeletons: str = "auto"  # auto | stm | stand-in
    study_name: str = ""  # "" -> smoothing-<profile>[-<hash>]


@dataclass(frozen=True)
class IDMSettings:
    """Top-level fields of stm.idm_study.IDMStudyConfig not covered by its data/idm sections."""

    skeletons: str = "auto"
    study_name: str = ""  # "" -> idm-<profile>[-<hash>]


SMOOTHING_PROFILES = {
    "smoke": SmoothingSettings(iters=50, steps=20),
    "quick": SmoothingSettings(),
    "paper": SmoothingSettings(iters=2000),
}


@dataclass(frozen=True)
class PostConfig:
    kind: str
    profile: str
    study: Any  # SmoothingSettings | stm.idm_study.IDMStudyConfig
    skeletons: str
    study_name: str

    def params(self) -> dict[str, Any]:
        if self.kind == "idm":
            return {k: (",".join(map(str, v)) if isinstance(v, (list, tuple)) else v)
                    for k, v in self.study.params().items()}
        return {k: v for k, v in dataclasses.asdict(self.study).items() if k not in ("skeletons", "study_name")}

    def resolved_study_name(self, from_stm: bool = False) -> str:
        """<kind>-<profile>[-stm][-<hash of the params if they differ from the profile's>]: plans from a
        trained STM and from the stand-in are separate studies."""
        if self.study_name:
            return self.study_name
        same = load_config(self.kind, self.profile, []).params() == self.params()
        return (f"{self.kind}-{self.profile}" + ("-stm" if from_stm else "")
                + ("" if same else f"-{config_hash(self.params())[:8]}"))


def _idm_profile(profile: str):
    from stm.idm_study import study_profile

    return study_profile(profile)


def load_config(kind: str, profile: str, overrides: list[str]) -> PostConfig:
    """Profile -> `--set` overrides -> validated config (ConfigError with a one-line message)."""
    _check_choice("kind", kind, KINDS)
    _check_choice("profile", profile, PROFILES)
    raw: dict[str, Any] = {}
    for item in overrides:
        path, value = parse_override(item)
        set_path(raw, path, value)
    if kind == "smoothing":
        base = dataclasses.asdict(SMOOTHING_PROFILES[profile])
        study = _build(SmoothingSettings, {**base, **raw}, "")
        _check_positive("iters", study.iters)
        _check_positive("steps", study.steps, 3)  # jerk needs 4 points
        for name in ("gamma", "goal_weight"):
            if not (math.isfinite(getattr(study, name)) and getattr(study, name) >= 0):
                raise ConfigError(f"{name}: {getattr(study, name)!r} is not allowed; allowed: numbers >= 0")
        if not study.step_seconds > 0:
            raise ConfigError(f"step_seconds: {study.step_seconds!r} is not allowed; allowed: numbers > 0")
        _check_choice("skeletons", study.skeletons, SKELETON_SOURCES)
        return PostConfig(kind, profile, study, study.skeletons, study.study_name)
    return _idm_config(profile, raw)


def _idm_config(profile: str, raw: dict[str, Any]) -> PostConfig:
    from stm.idm import IDMConfig
    from stm.idm_data import ExplorationConfig

    base = _idm_profile(profile)
    data_raw = raw.pop("data", {})
    idm_raw = raw.pop("idm", {})
    if not isinstance(data_raw, dict) or not isinstance(idm_raw, dict):
        raise ConfigError("data, idm: expected sections of FIELD = VALUE (e.g. --set idm.epochs=5)")
    if "dynamics" in data_raw:
        raise ConfigError("data.dynamics: not settable; the perturbed robot is set by real_seed, real_mass, "
                          "real_damping, real_friction")
    settings = _build(IDMSettings, {k: raw.pop(k) for k in list(raw) if k in ("skeletons", "study_name")}, "")
    _check_choice("skeletons", settings.skeletons, SKELETON_SOURCES)
    top_fields = [f.name for f in dataclasses.fields(base) if f.name not in ("data", "idm")]
    unknown = sorted(set(raw) - set(top_fields))
    if unknown:
        allowed = ", ".join(["data.<field>", "idm.<field>", *top_fields, "skeletons", "study_name"])
        raise ConfigError(f"{unknown[0]}: unknown field; allowed: {allowed}")
    data_set = _build(_plain_fields(ExplorationConfig, exclude=("dynamics",)), data_raw, "data.")
    with _stm_errors("data", "ExplorationConfig"):
        data = dataclasses.replace(base.data, **{k: getattr(data_set, k) for k in data_raw})
    idm_set = _build(_plain_fields(IDMConfig, exclude=()), idm_raw, "idm.")
    with _stm_errors("idm", "IDMConfig"):
        idm = dataclasses.replace(base.idm, **{k: getattr(idm_set, k) for k in idm_raw})
    top_set = _build(_plain_fields(type(base), exclude=("data", "idm")), raw, "")
    top = {f: getattr(top_set if f in raw else base, f) for f in top_fields}
    with _stm_errors("", type(base).__name__):
        study = type(base)(data=data, idm=idm, **top)
    _check_positive("plan_steps", study.plan_steps, 2)
    _check_positive("real_episodes", study.real_episodes)
    _check_positive("finetune_epochs", study.finetune_epochs, 0)
    _check_positive("torch_threads", study.torch_threads)
    if not 0 <= study.real_mass < 1:
        raise ConfigError(f"real_mass: {study.real_mass!r} is not allowed; allowed: 0 <= real_mass < 1")
    for name in ("real_damping", "real_friction"):
        lo_hi = getattr(study, name)
        if len(lo_hi) != 2 or not 0 <= lo_hi[0] <= lo_hi[1]:
            raise ConfigError(f"{name}: {list(lo_hi)!r} is not allowed; allowed: [low, high] with 0 <= low <= high")
    if not study.step_seconds > 0 or study.step_seconds < study.data.control_period:
        raise ConfigError(f"step_seconds: {study.step_seconds!r} is not allowed; allowed: >= data.control_period "
                          f"({study.data.control_period})")
    return PostConfig("idm", profile, study, settings.skeletons, settings.study_name)


@contextlib.contextmanager
def _stm_errors(section: str, class_name: str):
    """The stm dataclasses' own checks (ValueError) restated as one-line ConfigErrors naming the section."""
    try:
        yield
    except (ValueError, TypeError) as e:
        msg = str(e).splitlines()[0].replace(f"{class_name}.", f"{section}." if section else "")
        msg = msg.removeprefix(f"{class_name}: ")
        raise ConfigError(msg if not section or msg.startswith(f"{section}.") else f"{section}: {msg}") from None


def _plain_fields(cls: type, exclude: tuple[str, ...]) -> type:
    """A frozen dataclass with cls's fields minus `exclude` (defaults kept), so that
    experiments.config._build checks names and types without running cls's own checks."""
    fields = [(f.name, f.type, dataclasses.field(default=f.default) if f.default is not dataclasses.MISSING
               else dataclasses.field(default_factory=f.default_factory))
              for f in dataclasses.fields(cls) if f.name not in exclude]
    return dataclasses.make_dataclass(f"{cls.__name__}Fields", fields, frozen=True)


# ---------------------------------------------------------------- skeleton source


def find_stm_checkpoint(client) -> tuple[str, str] | None:
    """(run id, artifact path) of the newest FINISHED reacher ac-lstm-mdn ablation cell with a
    checkpoint, or None."""
    from experiments.worker import CHECKPOINT_DIR, CHECKPOINT_NAME

    exp = client.get_experiment_by_name("ablation")
    if exp is None:
        return None
    runs = client.search_runs([exp.experiment_id], filter_string=(
        f"tags.task = '{STM_TASK}' and tags.variant = '{STM_VARIANT}' and attributes.status = 'FINISHED'"),
        order_by=["attributes.end_time DESC"], max_results=50)
    for run in runs:
        names = {Path(f.path).name for f in client.list_artifacts(run.info.run_id, CHECKPOINT_DIR)}
        if CHECKPOINT_NAME in names:
            return run.info.run_id, f"{CHECKPOINT_DIR}/{CHECKPOINT_NAME}"
    return None


def stm_skeletons(client, found: tuple[str, str], steps: int, work: Path):
    """The STM's plans to the four reacher goals (B, steps+1, 7) from a checkpoint artifact."""
    from stm.checkpoint import load_model
    from stm.plans import FOUR_GOALS, stm_plans

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one small file: no bar
    local = client.download_artifacts(found[0], found[1], str(work))
    model = load_model(Path(local))
    return stm_plans(model, FOUR_GOALS, horizon=steps)


# ---------------------------------------------------------------- running


def _split_results(res: dict[str, Any]) -> tuple[dict[str, float], dict[str, str], list[str], list[str]]:
    """metrics (numbers), tags (strings, flattened dicts), figure and other artifact paths."""
    from experiments.tracking import flatten

    metrics, tags = {}, {}
    for k, v in res.items():
        if k in ("figures", "artifacts"):
            continue
        if isinstance(v, bool) or isinstance(v, (int, float)):
            metrics[k] = float(v)
        elif isinstance(v, dict):
            tags.update(flatten(v, f"{k}."))
        else:
            tags[k] = str(v)
    return metrics, tags, list(res.get("figures", [])), list(res.get("artifacts", []))


def run_postprocess(cfg: PostConfig, progress: bool | None = None) -> tuple[str, str, dict[str, float]]:
    """Run one study into the tracking store; returns (parent run id, study name, metrics)."""
    import numpy as np

    from experiments.tracking import (
        Client,
        get_or_create_experiment,
        get_or_create_parent_run,
        log_metrics,
        log_params,
        provenance_params,
        set_tags,
        sqlite_path,
        tracking_uri,
    )

    start = time.perf_counter()
    uri = tracking_uri()
    db = sqlite_path(uri)
    fresh = db is not None and not db.exists()  # no store yet: no STM in it
    client = None if fresh and cfg.skeletons == "stm" else Client(uri)  # (opening one creates it)
    found = find_stm_checkpoint(client) if cfg.skeletons != "stand-in" and not fresh else None
    if cfg.skeletons == "stm" and found is None:
        raise ConfigError(f"skeletons: 'stm' needs a FINISHED ablation run for {STM_TASK} / {STM_VARIANT} with a "
                          "checkpoint artifact in the store; allowed: auto, stand-in")
    study_name = cfg.resolved_study_name(from_stm=found is not None)
    experiment_id = get_or_create_experiment(client, cfg.kind)
    source = f"stm:{found[0]}" if found else ("stand-in:jittery-ik-expert" if cfg.kind == "smoothing"
                                              else "stand-in:ik-expert")
    parent_id = get_or_create_parent_run(client, experiment_id, study_name,
                                         {"kind": cfg.kind, "profile": cfg.profile, "skeleton_source": source,
                                          "error": ""})  # a re-run clears an earlier failure's error
    log_params(client, parent_id, {"profile": cfg.profile, "study_name": study_name, **cfg.params(),
                                   **provenance_params()})
    log.info("%s study %r (skeletons: %s); store %s", cfg.kind, study_name, source, client.uri)
    try:
        with tempfile.TemporaryDirectory(prefix=f"{cfg.kind}-") as tmp:
            work = Path(tmp)
            if cfg.kind == "smoothing":
                from stm.plans import FOUR_GOALS
                from stm.smoothing import smooth_gd, smoothing_study

                s = cfg.study
                # torch.optim's first step pays one-off lazy imports (~3 s measured, vs 0.07 s for 300
                # iterations after): warm up so that time_gd_s compares the methods, not the imports
                smooth_gd(np.zeros((1, 4, 7)), s.gamma, iters=2)
                skeletons = stm_skeletons(client, found, s.steps, work) if found else None
                res = smoothing_study(skeletons, FOUR_GOALS if found else None, gamma=s.gamma,
                                      goal_weight=s.goal_weight, iters=s.iters, step_seconds=s.step_seconds,
                                      seed=s.seed, steps=s.steps, out_dir=work / "out")
            else:
                from stm.idm_study import idm_study
                from stm.plans import FOUR_GOALS

                plans = stm_skeletons(client, found, cfg.study.plan_steps, work) if found else None
                res = idm_study(cfg.study, plans, FOUR_GOALS if found else None, out_dir=work / "out",
                                progress=progress)
            metrics, tags, figures, artifacts = _split_results(res)
            metrics["time/study_seconds"] = time.perf_counter() - start
            log_metrics(client, parent_id, metrics)
            set_tags(client, parent_id, tags)
            for path in figures:
                client.log_artifact(parent_id, path, "figures")
            for path in artifacts:
                client.log_artifact(parent_id, path, cfg.kind)
    except KeyboardInterrupt:
        client.set_terminated(parent_id, "KILLED")
        raise
    except Exception as exc:
        set_tags(client, parent_id, {"error": f"{type(exc).__name__}: {exc}".splitlines()[0]})
        client.set_terminated(parent_id, "FAILED")
        raise
    bad = [k for k, v in metrics.items() if not np.isfinite(v)]
    if bad:
        log.warning("non-finite metrics: %s", ", ".join(bad))
    client.set_terminated(parent_id, "FINISHED")
    return parent_id, study_name, metrics


SUMMARY_KEYS = {
    "smoothing": ["skeleton/mean_sq_jerk", "gd_goal/mean_sq_jerk", "skeleton/peak_joint_speed",
                  "gd_goal/peak_joint_speed", "gd_goal/deviation_rad", "skeleton/goal_error_m",
                  "gd_goal/goal_error_m", "time_exact_s", "time_gd_s", "gd_vs_exact_max_abs_rad"],
    "idm": ["position/tip_rmse_vs_plan_m", "sim/tip_rmse_vs_position_m", "real_sim_idm/tip_rmse_vs_position_m",
            "real_finetuned/tip_rmse_vs_position_m", "sim/success_rate", "real_sim_idm/success_rate",
            "real_finetuned/success_rate", "latency_fast_ms"],
}


# ---------------------------------------------------------------- command line


def add_parsers(sub) -> None:
    """The `smoothing` and `idm` subcommands (called by experiments.cli.build_parser)."""
    helps = {"smoothing": "trajectory smoothing study (stm.smoothing) as a tracked MLflow run",
             "idm": "inverse dynamics model study (stm.idm_study) as a tracked MLflow run"}
    for kind in KINDS:
        p = sub.add_parser(kind, help=helps[kind])
        p.add_argument("--profile", default="quick", help=f"config profile: {', '.join(PROFILES)}")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="override a config field, e.g. --set iters=500 (smoothing), --set idm.epochs=5 "
                            "(idm), --set skeletons=stand-in (repeatable)")
        p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def main(args: argparse.Namespace) -> int:
    """Run `args.command` (smoothing | idm); exit codes like the ablation's: 1 the study failed
    (recorded on its run), 2 bad config, 3 store unavailable."""
    try:
        cfg = load_config(args.command, args.profile, args.overrides)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    from experiments.stores import StoreUnavailable, wait_for_stores
    from experiments.tracking import tracking_uri

    try:  # the ablation's probe: a locked store or a server that is down is one line, exit 3
        wait_for_stores(tracking_uri())
    except StoreUnavailable as e:
        print(f"error: {e}", file=sys.stderr)
        return 3
    try:
        run_id, name, metrics = run_postprocess(cfg)
    except ConfigError as e:
        print(f"error: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted; the study's run is marked KILLED", file=sys.stderr)
        return 130
    except Exception as e:  # noqa: BLE001 - recorded on the run (tag error, FAILED); one line here
        print(f"{cfg.kind} study failed: {type(e).__name__}: {e}".splitlines()[0], file=sys.stderr)
        return 1
    lines = [f"{cfg.kind} study {name!r} (run {run_id}):"]
    lines += [f"  {k} = {metrics[k]:.6g}" for k in SUMMARY_KEYS[cfg.kind] if k in metrics]
    lines.append(f"report: `python -m reports --experiment {cfg.kind}` writes reports/out/{name}/index.html")
    print("\n".join(lines))
    return 0
