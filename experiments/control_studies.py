"""`python -m experiments smoothing|idm`: the post-processing studies (stm.control.smoothing,
stm.control.idm_study) as tracked MLflow studies.

One experiment per kind ("smoothing", "idm"); each study is one parent run (tags kind,
profile, study_name, role=parent, skeleton_source) holding the study's metrics (step 0),
its config as params (plus git commit and package versions), and its figures (PNG + PDF
under figures/; the IDM's checkpoints under idm/). A re-run of the same study name reuses
the run: metrics get new values, changed params become `changed.<key>` tags.

Skeletons / plans: with `skeletons = "auto"` (default) the newest FINISHED ablation cell
for reacher with variant ac-lstm-mdn that has a checkpoint artifact supplies the STM
(stm.control.plans.stm_plans to the four reacher goals); without one, the documented stand-in
(smoothing: stm.control.plans.jittery_skeletons of the IK expert's plans; idm: the IK expert's
plans, stm.control.plans.straight_line_plans). "stm" requires the STM, "stand-in" never looks.
The tag `skeleton_source` says which was used.

Config: the [smoothing] or [idm] section of a profile (the ablation's TOML files, smoke | quick |
results | paper, or a file by path) plus `--set FIELD=VALUE` overrides (names relative to the
section), validated field by field before anything is written; a bad value is a one-line error,
exit code 2.
"""

from __future__ import annotations

import argparse
import copy
import dataclasses
import logging
import os
import sys
import tempfile
import time
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import Field, field_validator
from pydantic.dataclasses import dataclass

from experiments.config_errors import ConfigError, validated
from experiments.runtime.study_names import check_study_name, optional_study_name
from experiments.study_config import available_profiles, config_hash, parse_override, read_profile, set_path
from stm.config import STRICT, NonNegativeFloat, PositiveFloat, PositiveInt

log = logging.getLogger(__name__)

KINDS = ("smoothing", "idm")
Skeletons = Literal["auto", "stm", "stand-in"]
STM_TASK, STM_VARIANT = "reacher", "ac-lstm-mdn"
SETTINGS = ("skeletons", "study_name")  # fields of both kinds that are not parameters of the study


# ---------------------------------------------------------------- configs


@dataclass(frozen=True, config=STRICT)
class SmoothingSettings:
    """Arguments of stm.control.smoothing.smoothing_study plus where the skeletons come from."""

    gamma: NonNegativeFloat = 5.0  # weight of the velocity term
    goal_weight: NonNegativeFloat = 50.0  # weight of the final-tip goal term (gd_goal variant)
    iters: PositiveInt = 300  # gradient-descent iterations
    steps: Annotated[int, Field(ge=3)] = 60  # skeleton length T (STM horizon / IK expert steps); jerk needs 4 points
    step_seconds: PositiveFloat = 0.1  # the STM's step, for jerk and speed in SI units
    seed: int = 0  # stand-in jitter draw
    skeletons: Skeletons = "auto"
    study_name: str = ""  # "" -> smoothing-<profile>[-<hash>]

    @field_validator("study_name")
    @classmethod
    def _study_name(cls, name: str) -> str:
        return optional_study_name(name)


@dataclass(frozen=True, config=STRICT)
class IDMSettings:
    """Fields of an [idm] section that are not stm.control.idm_study.IDMStudyConfig's."""

    skeletons: Skeletons = "auto"
    study_name: str = ""  # "" -> idm-<profile>[-<hash>]

    @field_validator("study_name")
    @classmethod
    def _study_name(cls, name: str) -> str:
        return optional_study_name(name)


@dataclasses.dataclass(frozen=True)
class PostConfig:
    kind: str
    profile: str
    study: Any  # SmoothingSettings | stm.control.idm_study.IDMStudyConfig
    skeletons: str
    study_name: str  # --set study_name, else derived from the profile by load_config
    overridden: bool = False  # the study's parameters differ from the profile's

    def params(self) -> dict[str, Any]:
        if self.kind == "idm":
            return {k: (",".join(map(str, v)) if isinstance(v, (list, tuple)) else v)
                    for k, v in self.study.params().items()}
        return {k: v for k, v in dataclasses.asdict(self.study).items() if k not in SETTINGS}

    def resolved_study_name(self, from_stm: bool = False) -> str:
        """<kind>-<profile>[-stm][-<hash of the params if they differ from the profile's>]: plans from a
        trained STM and from the stand-in are separate studies."""
        if self.study_name:
            return self.study_name
        return (f"{self.kind}-{self.profile}" + ("-stm" if from_stm else "")
                + (f"-{config_hash(self.params())[:8]}" if self.overridden else ""))


def load_config(kind: str, profile: str, overrides: list[str]) -> PostConfig:
    """The profile's [smoothing] or [idm] section (read once) -> `--set` overrides (field names
    relative to the section) -> validated config (ConfigError with a one-line message)."""
    if kind not in KINDS:
        raise ConfigError(f"kind: {kind!r} is not allowed; allowed: {', '.join(KINDS)}")
    name, raw = read_profile(profile)
    section = raw.get(kind, {})
    if not isinstance(section, dict):
        raise ConfigError(f"{kind}: expected a section of FIELD = VALUE in the profile")
    values = copy.deepcopy(section)
    for item in overrides:
        path, value = parse_override(item)
        set_path(values, path, value)
    build = _smoothing if kind == "smoothing" else _idm
    study, settings = build(values)
    cfg = PostConfig(kind, name, study, settings.skeletons, settings.study_name)
    if overrides and not settings.study_name:
        base, _ = build(copy.deepcopy(section))
        cfg = dataclasses.replace(cfg, overridden=cfg.params() != dataclasses.replace(cfg, study=base).params())
    for from_stm in (False, True):  # the name a profile file's stem gives (which one is known once the store is read)
        check_study_name(cfg.resolved_study_name(from_stm), "study name (from the profile's name; rename the file "
                         "or --set study_name=...)")
    return cfg


def _smoothing(values: dict[str, Any]) -> tuple[SmoothingSettings, SmoothingSettings]:
    study = validated(SmoothingSettings, values, "")
    return study, study


def _idm(values: dict[str, Any]) -> tuple[Any, IDMSettings]:
    from stm.control.idm import IDMConfig
    from stm.control.idm_study import ExplorationSettings, IDMStudyConfig

    settings = validated(IDMSettings, {k: values.pop(k) for k in SETTINGS if k in values}, "")
    sections = {k: values.pop(k, None) or {} for k in ("data", "idm")}
    if not all(isinstance(v, dict) for v in sections.values()):
        raise ConfigError("data, idm: expected sections of FIELD = VALUE (e.g. --set idm.epochs=5)")
    if "dynamics" in sections["data"]:
        raise ConfigError("data.dynamics: not settable; the perturbed robot is set by real_seed, real_mass, "
                          "real_damping, real_friction")
    data = validated(ExplorationSettings, sections["data"], "data")
    idm = validated(IDMConfig, sections["idm"], "idm")
    return validated(IDMStudyConfig, {**values, "data": data, "idm": idm}, ""), settings


# ---------------------------------------------------------------- skeleton source


def find_stm_checkpoint(client) -> tuple[str, str] | None:
    """(run id, artifact path) of the newest FINISHED reacher ac-lstm-mdn ablation cell with a
    checkpoint, or None."""
    from experiments.cell_run import CHECKPOINT_DIR, CHECKPOINT_NAME

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
    from stm.control.plans import FOUR_GOALS, stm_plans
    from stm.training.checkpoint import load_model

    os.environ.setdefault("MLFLOW_ENABLE_ARTIFACTS_PROGRESS_BAR", "false")  # one small file: no bar
    local = client.download_artifacts(found[0], found[1], str(work))
    model = load_model(Path(local))
    return stm_plans(model, FOUR_GOALS, horizon=steps)


# ---------------------------------------------------------------- running


def _split_results(res: dict[str, Any]) -> tuple[dict[str, float], dict[str, str], list[str], list[str]]:
    """metrics (numbers), tags (strings, flattened dicts), figure and other artifact paths."""
    from experiments.runtime.tracking import flatten

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

    from experiments.runtime.tracking import (
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
                from stm.control.plans import FOUR_GOALS
                from stm.control.smoothing import smooth_gd, smoothing_study

                s = cfg.study
                # torch.optim's first step pays one-off lazy imports (~3 s measured, vs 0.07 s for 300
                # iterations after): warm up so that time_gd_s compares the methods, not the imports
                smooth_gd(np.zeros((1, 4, 7)), s.gamma, iters=2)
                skeletons = stm_skeletons(client, found, s.steps, work) if found else None
                res = smoothing_study(skeletons, FOUR_GOALS if found else None, gamma=s.gamma,
                                      goal_weight=s.goal_weight, iters=s.iters, step_seconds=s.step_seconds,
                                      seed=s.seed, steps=s.steps, out_dir=work / "out")
            else:
                from stm.control.idm_study import idm_study
                from stm.control.plans import FOUR_GOALS

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
        from experiments.runtime.store_faults import fault_reason

        if fault_reason(exc) is None:  # a store fault writes nothing more: the run stays as it was
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
    helps = {"smoothing": "trajectory smoothing study (stm.control.smoothing) as a tracked MLflow run",
             "idm": "inverse dynamics model study (stm.control.idm_study) as a tracked MLflow run"}
    for kind in KINDS:
        p = sub.add_parser(kind, help=helps[kind])
        p.add_argument("--profile", default="quick", help=f"config profile: {', '.join(available_profiles())}, "
                       f"or the path of a TOML file (its [{kind}] section)")
        p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                       help="override a config field, e.g. --set iters=500 (smoothing), --set idm.epochs=5 "
                            "(idm), --set skeletons=stand-in (repeatable)")
        p.add_argument("--dry-run", action="store_true", help="check the config and the study name, print them, "
                       "and stop: nothing is written")
        p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def main(args: argparse.Namespace) -> int:
    """Run `args.command` (smoothing | idm); exit codes like the ablation's: 1 the study failed
    (recorded on its run), 2 bad config, 3 store unavailable."""
    try:
        cfg = load_config(args.command, args.profile, args.overrides)
    except ConfigError as e:
        print(f"error: {e}".replace("\n", "\\n"), file=sys.stderr)
        return 2
    if args.dry_run:
        names = dict.fromkeys((cfg.resolved_study_name(False), cfg.resolved_study_name(True)))
        print(f"{cfg.kind} study {' or '.join(map(repr, names))} (with the stand-in or a trained STM); dry run, "
              "nothing written")
        return 0
    from experiments.runtime.store_check import StoreUnavailable, wait_for_stores
    from experiments.runtime.tracking import report_index, tracking_uri

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
        from experiments.runtime.store_faults import fault_reason

        if fault_reason(e) is not None:  # the store itself failed: experiments.cli reports it (exit code 3)
            raise
        print(f"{cfg.kind} study failed: {type(e).__name__}: {e}".splitlines()[0], file=sys.stderr)
        return 1
    lines = [f"{cfg.kind} study {name!r} (run {run_id}):"]
    lines += [f"  {k} = {metrics[k]:.6g}" for k in SUMMARY_KEYS[cfg.kind] if k in metrics]
    lines.append(f"report: `python -m reports --experiment {cfg.kind}` writes {report_index(name)}")
    print("\n".join(lines))
    return 0
