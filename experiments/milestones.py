"""`python -m experiments milestones --study NAME`: success vs training iterations, measured on the
copies of each cell's checkpoint that an ablation study kept (StudyConfig.keep_checkpoints: artifacts
checkpoint_at/<iteration>/model.pt). The models are the study's own, so the curve costs evaluation only.

Each (cell, kept iteration) is evaluated in physics exactly as the cell's final model is (its eval
config, training seed, distinct episodes, feedback; `--rollouts` may lower the episode count and is
then logged) and becomes a child run of the study "<study>-milestones" in the experiment
"milestones": tags task, variant, seed, iteration, source_run; params the source cell's plus
`milestone.*`; the metric keys of an ablation cell; its rollouts artifact. The cell's final
iteration is not evaluated twice: a FINISHED cell's own evaluation is copied (tag copied = 1).
A re-run evaluates only what is new, e.g. the milestones a still-running study kept since, so it
can follow a study that trains across sessions.

`--feedback MODE` evaluates the same kept checkpoints (the final one included: nothing is copied) feeding
back MODE (stm.config.FEEDBACKS; an MDN's choice, a deterministic head has one output) instead of the
cells' eval.feedback, as the study "<study>-milestones-feedback-<MODE>": the feedback lever of a study's own
models, at the cost of evaluation only. Its runs log eval.feedback = MODE. With the cells' own MODE it is the
lever's reference arm: the same models evaluated anew at the current commit, which also records whatever
per-episode facts the tasks have gained since. `--iterations N ...` evaluates only the checkpoints kept at
those iterations (a final model's too).

`--split validation` evaluates the same models on the validation episodes instead of the headline's (eval seed +
VALIDATION_SEED_OFFSET + training seed: experiments.evaluation.split_seed; VALIDATION_ROLLOUTS per seed and task
unless --rollouts), final models included, as the study "<study>-milestones-validation[-feedback-<MODE>]": the
split protocol choices are made on, never a headline table's (reports refuse it there). Its runs log
eval.split = validation and every run of this command is tagged with its split.

`--stack-restart {place_pose,start}` evaluates the same models (final ones included: nothing is copied) with
eval.stack_restart set to that protocol between the blocks (envs/tasks/stack_protocol.py), on stacking alone, the
one task it changes: the cells whose model serves stacking, as the study "<study>-milestones[...]-stack-<value>"
(e.g. "<study>-milestones-validation-stack-start"), whose runs hold stacking's metrics only and log
eval.stack_restart = value.

Besides kept checkpoints, it evaluates the models a study export carries (reports.data.export `--with-models`:
weights alone, artifacts weights_at/<iteration>/weights.pt), once the export is imported into a store: in a fresh
clone, `python -m reports import reports/studies/NAME`, then this command, evaluates the study's models with the
same choices, to the same rollouts as from the original store."""

from __future__ import annotations

import dataclasses
import json
import logging
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, get_args

from experiments.cell_run import CHECKPOINT_NAME, KEPT_CHECKPOINT_DIR, WEIGHTS_DIR, WEIGHTS_NAME, setup_process
from experiments.config_errors import ConfigError
from experiments.eval_sweep_config import SPLITS, VALIDATION_ROLLOUTS, StackRestart, evaluation_tasks
from experiments.runtime.processes import add_device_option, add_threads_option, checked_device
from experiments.runtime.study_names import check_study_name
from experiments.runtime.tracking import (
    ABLATION,
    MILESTONE_ITERATION,
    MILESTONES,
    PARENT_TAG,
    Client,
    child_runs,
    find_parent_run,
    get_or_create_experiment,
    get_or_create_parent_run,
    log_metrics,
    log_params,
    provenance_params,
    set_tags,
    sqlite_path,
    tracking_uri,
)
from stm.config import FEEDBACKS

log = logging.getLogger(__name__)
STACK_RESTARTS: tuple[str, ...] = get_args(StackRestart)
STACK_TASK = "stack"  # the one eval task eval.stack_restart changes (envs.tasks.stack.Stack.eval_options)


class MilestoneError(Exception):
    """A bad selection (unknown study, no kept checkpoints), reported as one line (exit code 2)."""


@dataclass(frozen=True)
class Milestone:
    source_run: str
    task: str
    variant: str
    seed: str
    iteration: int
    final: bool  # the source cell FINISHED at this iteration: its own evaluation is copied
    artifact: str = ""  # the model's artifact on the source run (kept_models); "" for the kept checkpoint's

    @property
    def model_artifact(self) -> str:
        return self.artifact or f"{KEPT_CHECKPOINT_DIR}/{self.iteration}/{CHECKPOINT_NAME}"

    @property
    def key(self) -> str:
        return f"{self.task}/{self.variant}/seed{self.seed}@{self.iteration}"


def kept_iterations(client: Client, run_id: str) -> list[int]:
    """Iterations whose checkpoint copy the run kept (artifact folders checkpoint_at/<iteration>)."""
    out = []
    for f in client.list_artifacts(run_id, KEPT_CHECKPOINT_DIR):
        name = Path(f.path).name
        if f.is_dir and name.isdigit():
            out.append(int(name))
    return sorted(out)


def kept_models(client: Client, run_id: str) -> dict[int, str]:
    """The run's models by iteration: its kept checkpoints, and the weights an imported export with models brought
    (weights_at/<iteration>/weights.pt) where no checkpoint was kept at that iteration (the same weights)."""
    from experiments.weights_resume import weights_iterations

    out = {it: f"{WEIGHTS_DIR}/{it}/{WEIGHTS_NAME}" for it in weights_iterations(client, run_id)}
    out.update({it: f"{KEPT_CHECKPOINT_DIR}/{it}/{CHECKPOINT_NAME}" for it in kept_iterations(client, run_id)})
    return dict(sorted(out.items()))


def find_milestones(client: Client, study: str, tasks: list[str] | None, variants: list[str] | None,
                    iterations: list[int] | None = None) -> tuple[list[Milestone], str]:
    """The kept checkpoints (and models imported with an export) of the study's selected cells (at the selected
    iterations), and the study's profile."""
    experiment = client.get_experiment_by_name(ABLATION)
    parent = find_parent_run(client, experiment.experiment_id, study) if experiment else None
    if parent is None:
        raise MilestoneError(f"no ablation study named {study!r} in {client.uri}")
    out = []
    for run in child_runs(client, experiment.experiment_id, parent.info.run_id):
        tags = run.data.tags
        if (tasks and tags.get("task") not in tasks) or (variants and tags.get("variant") not in variants):
            continue
        done = int(run.data.metrics.get("train/iterations", -1)) if run.info.status == "FINISHED" else -1
        out += [Milestone(run.info.run_id, tags["task"], tags["variant"], tags["seed"], it, final=it == done,
                          artifact=path)
                for it, path in kept_models(client, run.info.run_id).items() if not iterations or it in iterations]
    if not out:
        at = f" at iterations {', '.join(map(str, iterations))}" if iterations else ""
        raise MilestoneError(f"study {study!r} has no kept checkpoints (checkpoint_at/) or imported models "
                             f"(weights_at/) for the selected cells{at}; run it with keep_checkpoints = N in its "
                             "profile or --set keep_checkpoints=N")
    return sorted(out, key=lambda m: (m.task, m.variant, m.seed, m.iteration)), parent.data.tags.get("profile", "?")


def _source_config(client: Client, run_id: str, work: Path) -> dict[str, Any]:
    local = client.download_artifacts(run_id, "config/config.json", str(work))
    return json.loads(Path(local).read_text())


def evaluate_milestone(uri: str, m: Milestone, run_id: str, rollouts: int | None, level: int,
                       threads: int | None, feedback: str | None = None, device: str = "cpu",
                       split: str = "test", stack_restart: str | None = None) -> tuple[str, str]:
    """Worker entry point: evaluate one kept checkpoint into its run, its rollouts on `device`, on the episodes of
    `split` (with `stack_restart`: on stacking alone, under that protocol); (status, error)."""
    import numpy as np

    from experiments.evaluation import evaluate_model, rollout_arrays
    from experiments.mode_repeats import write_mode_tables
    from stm.device import resolve_device
    from stm.training.checkpoint import load_model

    setup_process(level, threads)
    client = Client(uri, create=False)
    client.update_run(run_id, status="RUNNING")
    try:
        with tempfile.TemporaryDirectory(prefix="acrmdn-milestone-") as tmp:
            work = Path(tmp)
            cfg = _source_config(client, m.source_run, work / "config")
            eval_cfg = dict(cfg["eval"], rollouts=rollouts or split_rollouts(split, cfg["eval"]["rollouts"]),
                            feedback=feedback or cfg["eval"]["feedback"], split=split,
                            **({"stack_restart": stack_restart} if stack_restart else {}))
            tasks = [t for t in cfg["eval_tasks"] if not stack_restart or t == STACK_TASK]
            path = client.download_artifacts(m.source_run, m.model_artifact, str(work / "ckpt"))
            train = cfg["train"]
            start = time.perf_counter()
            set_tags(client, run_id, {"device": str(resolve_device(device))})
            metrics, details = evaluate_model(load_model(Path(path), device), tasks, eval_cfg,
                                              seed=int(cfg["seed"]), phi_mode=train.get("phi_mode"), timings=False,
                                              data=cfg.get("data"), train_feedback=train.get("feedback"),
                                              temperature=float(train.get("temperature", 1.0)))
            metrics["time/evaluation_seconds"] = time.perf_counter() - start
            log_metrics(client, run_id, metrics)
            roll_dir = work / "rollouts"
            roll_dir.mkdir()
            for d in details:
                np.savez_compressed(roll_dir / f"{d.task}.npz", **rollout_arrays(d))
            write_mode_tables(details, roll_dir)  # where the source cell measured mode use per episode
            client.log_artifacts(run_id, str(roll_dir), "rollouts")
        client.set_terminated(run_id, "FINISHED")
        return "FINISHED", ""
    except KeyboardInterrupt:
        client.set_terminated(run_id, "KILLED")
        raise
    except Exception as exc:  # one milestone's failure is its own; the others go on
        text = f"{type(exc).__name__}: {exc}".splitlines()[0][:500]
        log.error("milestone %s failed: %s", m.key, text)
        set_tags(client, run_id, {"error": text})
        client.set_terminated(run_id, "FAILED")
        return "FAILED", text


def _copy_final(client: Client, m: Milestone, run_id: str) -> None:
    """The source cell's own evaluation of its final model (metrics and rollouts artifacts)."""
    source = client.get_run(m.source_run)
    keep = {k: v for k, v in source.data.metrics.items() if not k.startswith(("train/", "val/", "time/"))}
    log_metrics(client, run_id, keep)
    with tempfile.TemporaryDirectory(prefix="acrmdn-milestone-") as tmp:
        local = client.download_artifacts(m.source_run, "rollouts", tmp)
        client.log_artifacts(run_id, local, "rollouts")
    set_tags(client, run_id, {"copied": 1})
    client.set_terminated(run_id, "FINISHED")


def milestones_study_name(study: str, feedback: str | None = None, split: str = "test",
                          stack_restart: str | None = None) -> str:
    return (f"{study}-milestones" + ("-validation" if split == "validation" else "")
            + (f"-feedback-{feedback}" if feedback else "") + (f"-stack-{stack_restart}" if stack_restart else ""))


def _cell_split(client: Client, m: Milestone) -> str:
    """The split the source cell was evaluated on (its param eval.split; absent: "test")."""
    return client.get_run(m.source_run).data.params.get("eval.split", "test")


def split_rollouts(split: str, cell_rollouts: int) -> int:
    """Episodes per seed and task when --rollouts is not given: the cell's for "test", VALIDATION_ROLLOUTS for
    "validation"."""
    return VALIDATION_ROLLOUTS if split == "validation" else int(cell_rollouts)


def prepare(client: Client, study: str, profile: str, milestones: list[Milestone], rollouts: int | None,
            feedback: str | None = None, split: str = "test", stack_restart: str | None = None
            ) -> tuple[str, list[tuple[Milestone, str]], int]:
    """The milestones study's parent run, (milestone, run id) still to evaluate, and how many are done."""
    experiment_id = get_or_create_experiment(client, MILESTONES)
    name = milestones_study_name(study, feedback, split, stack_restart)
    validation = split == "validation"
    parent_id = get_or_create_parent_run(client, experiment_id, name, {"kind": MILESTONES, "source_study": study,
                                                                       "profile": profile, "split": split})
    log_params(client, parent_id, {"source_study": study, "rollouts": rollouts or ("as the cells" if not validation
                                                                                   else VALIDATION_ROLLOUTS),
                                   **({"feedback": feedback} if feedback else {}),
                                   **({"stack_restart": stack_restart} if stack_restart else {}),
                                   **({"split": split} if validation else {}), **provenance_params()})
    existing = {(r.data.tags.get("source_run"), r.data.tags.get("iteration")): r
                for r in child_runs(client, experiment_id, parent_id)}
    todo, done = [], 0
    for m in milestones:
        run = existing.get((m.source_run, str(m.iteration)))
        if run is not None and run.info.status == "FINISHED":
            done += 1
            continue
        if run is None:
            tags = {PARENT_TAG: parent_id, "task": m.task, "variant": m.variant, "seed": m.seed,
                    "iteration": m.iteration, "source_run": m.source_run, "study_name": name, "role": "cell",
                    "split": split}
            run_id = client.create_run(experiment_id, run_name=m.key, tags={k: str(v) for k, v in tags.items()}
                                       ).info.run_id
            params = {k: v for k, v in client.get_run(m.source_run).data.params.items() if not k.startswith("claim.")}
            log_params(client, run_id, {**params, MILESTONE_ITERATION: m.iteration,
                                        "milestone.rollouts": rollouts or ("as the cell" if not validation
                                                                           else VALIDATION_ROLLOUTS),
                                        **({"eval.feedback": feedback} if feedback else {}),
                                        **({"eval.stack_restart": stack_restart} if stack_restart else {}),
                                        **({"eval.split": split} if validation else {})})
        else:
            run_id = run.info.run_id
        todo.append((m, run_id))
    return parent_id, todo, done


def run_milestones(study: str, tasks: list[str] | None = None, variants: list[str] | None = None,
                   rollouts: int | None = None, workers: int = 1, uri: str | None = None,
                   feedback: str | None = None, device: str = "cpu", iterations: list[int] | None = None,
                   split: str = "test", stack_restart: str | None = None) -> dict[str, int]:
    """Evaluate every kept checkpoint of the study not evaluated yet (feeding back `feedback` instead of the
    cells' own, on the episodes of `split`, on stacking alone under `stack_restart`: module docstring); counts by
    outcome."""
    from experiments.runtime.processes import training_threads, worker_pool

    start = time.perf_counter()
    db = sqlite_path(uri or tracking_uri())
    if db is not None and not db.exists():  # (opening one would create an empty store)
        raise MilestoneError(f"no MLflow store at {db} (run the ablation study first, or set MLFLOW_TRACKING_URI)")
    client = Client(uri)
    milestones, profile = find_milestones(client, study, tasks, variants, iterations)
    if stack_restart:
        milestones = [m for m in milestones if STACK_TASK in evaluation_tasks(m.task)]
        if not milestones:
            raise MilestoneError(f"study {study!r} has no selected cell whose model is evaluated on {STACK_TASK} "
                                 "(--stack-restart changes stacking alone)")
    # a final model's own evaluation is copied only where it is the one asked for: its feedback, on the same split,
    # all its tasks under their own protocol
    milestones = [m if not m.final or (not feedback and not stack_restart and _cell_split(client, m) == split)
                  else dataclasses.replace(m, final=False) for m in milestones]
    parent_id, todo, done = prepare(client, study, profile, milestones, rollouts, feedback, split, stack_restart)
    counts = {"FINISHED": 0, "FAILED": 0, "skipped": done}
    level = logging.getLogger().getEffectiveLevel()
    log.info("study %r: %d kept checkpoints (%d to evaluate, %d done)", study, len(milestones), len(todo), done)
    evaluate = [(m, r) for m, r in todo if not m.final]
    for m, run_id in todo:
        if m.final:  # the cell's own evaluation of this very model
            _copy_final(client, m, run_id)
            counts["FINISHED"] += 1
    with worker_pool(max(1, workers)) as pool:
        threads = training_threads()
        futures = [(m, pool.submit(evaluate_milestone, client.uri, m, r, rollouts, level, threads, feedback, device,
                                   split, stack_restart)) for m, r in evaluate]
        for m, fut in futures:
            status, error = fut.result()
            counts[status] += 1
            log.info("%s: %s %s", m.key, status, error)
    client.log_metric(parent_id, "time/study_seconds", time.perf_counter() - start)
    client.set_terminated(parent_id, "FAILED" if counts["FAILED"] else "FINISHED")
    return counts


def add_parser(sub) -> None:
    p = sub.add_parser("milestones", help="success vs training iterations on the checkpoints an ablation kept")
    p.add_argument("--study", required=True, help="the ablation study's name (its profile kept checkpoints)")
    p.add_argument("--tasks", nargs="+", default=None, help="training tasks (default: all of the study's)")
    p.add_argument("--variants", nargs="+", default=None, help="variants (default: all of the study's)")
    p.add_argument("--rollouts", type=int, default=None, help="episodes per seed and task (default: the cell's)")
    p.add_argument("--iterations", type=int, nargs="+", default=None, metavar="N",
                   help="only the checkpoints kept at these iterations (default: all)")
    p.add_argument("--workers", type=int, default=1, help="evaluation processes, busy ones at most (default 1)")
    add_threads_option(p)
    add_device_option(p, "roll out")
    p.add_argument("--feedback", choices=FEEDBACKS, default=None,
                   help="evaluate feeding back this instead of the cells' eval.feedback, final models included, "
                        "as the study <study>-milestones-feedback-<MODE>")
    p.add_argument("--split", choices=SPLITS, default="test",
                   help="the episodes: test (default: the headline's) or validation (disjoint ones, where protocol "
                        f"choices are made; {VALIDATION_ROLLOUTS} per seed and task unless --rollouts; final models "
                        "included), as the study <study>-milestones-validation[-feedback-<MODE>]")
    p.add_argument("--stack-restart", choices=STACK_RESTARTS, default=None,
                   help="evaluate stacking alone with this eval.stack_restart (the protocol between the blocks), "
                        "final models included, as the study <study>-milestones[...]-stack-<value>")
    p.add_argument("-v", "--verbose", action="store_true")


def main(args) -> int:
    """args.tasks / args.variants: lists, already split at commas (experiments.cli)."""
    if args.rollouts is not None and args.rollouts < 1:
        print(f"error: --rollouts must be >= 1, got {args.rollouts}", file=sys.stderr)
        return 2
    try:
        check_study_name(args.study, "--study")
        name = milestones_study_name(args.study, args.feedback, args.split, args.stack_restart)
        check_study_name(name, "the milestones study's name")
        device = checked_device(args.device) or "cpu"
        counts = run_milestones(args.study, args.tasks, args.variants, args.rollouts, args.workers,
                                feedback=args.feedback, device=device, iterations=args.iterations, split=args.split,
                                stack_restart=args.stack_restart)
    except (MilestoneError, ConfigError) as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"{name!r}: {counts['FINISHED']} evaluated, {counts['skipped']} already done, {counts['FAILED']} failed")
    return 1 if counts["FAILED"] else 0
