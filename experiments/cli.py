"""`python -m experiments {ablation,sweep,smoothing,idm,milestones,scaling,ui}`.

Exit codes: 0 success; 1 some cells/trials failed (summary printed); 2 bad configuration
(one line naming the field and its allowed values, or the study name rule of
experiments/runtime/study_names.py, printed before anything is written; a study of more than
MAX_CELLS cells without --yes too); 3 a store (MLflow, Optuna) did not answer after bounded
retries (nothing written), or failed mid-study: read-only, a full disk, its file gone (a summary
and one line; the unfinished runs resumable: experiments/runtime/store_faults.py); 130 Ctrl-C.
`--dry-run` checks all that is checked before a study starts, prints what would run, and stops.
"""

from __future__ import annotations

import argparse
import logging
import signal
import sys

from experiments.runtime.processes import (
    add_device_option,
    add_threads_option,
    checked_device,
    default_workers,
    set_training_threads,
)
from experiments.runtime.study_names import RULE, check_study_name
from experiments.study_config import ConfigError, StudyConfig, available_profiles, load_profile

MAX_CELLS = 10_000  # cells of an ablation study run without --yes

log = logging.getLogger("experiments")


class _Parser(argparse.ArgumentParser):
    def error(self, message: str):  # one line, exit code 2 (argparse's own code for usage errors)
        self.exit(2, f"error: {message} (see `python -m experiments {self.prog.split()[-1]} --help`)\n")


def _one_line(message: str) -> str:
    """Field names and values come from the command line: keep their line breaks from
    splitting the one-line error."""
    return message.replace("\r", "\\r").replace("\n", "\\n")


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--profile", default="quick", help=f"config profile: {', '.join(available_profiles())}, "
                   "or the path of your own TOML file (see experiments/profiles/)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE",
                   help="override any config field, e.g. --set train.iters=2000 --set per_task.pick-place.model."
                        "mixtures=20 (repeatable)")
    p.add_argument("--workers", type=int, default=None,
                   help="worker processes, busy ones at most: an evaluating cell plays its physics on the idle "
                        "ones too (default: $ACRMDN_WORKERS, else one per core)")
    add_threads_option(p)
    add_device_option(p, "train and roll out")
    p.add_argument("--dry-run", action="store_true", help="check the config and the study name, print what would "
                   "run, and stop: nothing is written")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="python -m experiments", description=__doc__,
                     formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True, parser_class=_Parser)

    ab = sub.add_parser("ablation", help="run an ablation study (tasks x variants x seeds)")
    _common(ab)
    ab.add_argument("--tasks", nargs="+", default=None, help="training tasks (default: the profile's)")
    ab.add_argument("--variants", nargs="+", default=None, help="variants (default: the profile's)")
    ab.add_argument("--seeds", type=int, default=None, help="number of seeds 0..N-1")
    ab.add_argument("--pack", type=int, default=None, metavar="K", help="train up to K seeds of a cell group "
                    "(task x variant) together as one packed model (default: all of them, split into smaller "
                    "packs while a worker process would otherwise idle; 1: each cell alone)")
    ab.add_argument("--study-name", default=None, help="parent run name (default: from the profile and config): "
                    f"{RULE}")
    ab.add_argument("--yes", action="store_true", help=f"run a study of more than {MAX_CELLS:,} cells (without it "
                    "such a study is refused: a typo in --seeds would otherwise fill the store)")
    ab.add_argument("--resume-from-weights", action="store_true", help="a cell whose run has no resume checkpoint "
                    "but kept models (weights_at/N/, from an imported export with models) resumes at the largest N "
                    "below train.iters from those weights, with a fresh optimiser and random streams (run tag "
                    "resumed_from_weights; not the run an uninterrupted cell would have been); a cell with a "
                    "checkpoint resumes from it regardless")
    ab.add_argument("--worker", action="store_true", help="pull cells from a queue shared with other worker "
                    "commands (other hosts too; see docs/scale-out.md); --workers K local processes")
    ab.add_argument("--queue", default=None, help="with --worker: Optuna RDB URL of the cell queue, e.g. "
                    "postgresql://... (default: queue.db next to a local mlflow.db)")

    sw = sub.add_parser("sweep", help="Optuna sweep of mixture count and auto-conditioning schedule")
    _common(sw)
    sw.add_argument("--task", default=None)
    sw.add_argument("--variant", default=None)
    sw.add_argument("--space", default=None, help="comma-separated subset of m,u,v,feedback,sigma_min")
    sw.add_argument("--trials", type=int, default=None, help="total trials; a re-run continues to this many")
    sw.add_argument("--sampler", default=None, help="tpe | grid | random")
    sw.add_argument("--storage", default=None, help="Optuna storage URL (default: journal file next to mlflow.db)")
    sw.add_argument("--study-name", default=None, help=f"Optuna study and parent run name: {RULE}")

    from experiments.control_studies import add_parsers

    add_parsers(sub)  # smoothing, idm
    from experiments.milestones import add_parser as add_milestones

    add_milestones(sub)
    from experiments.scaling import add_parser as add_scaling

    add_scaling(sub)

    ui = sub.add_parser("ui", help="MLflow UI on 127.0.0.1:5000 over the study store")
    ui.add_argument("--host", default="127.0.0.1")
    ui.add_argument("--port", type=int, default=5000)
    return parser


def _split(values: list[str] | None) -> list[str] | None:
    if values is None:
        return None
    return [v for item in values for v in item.split(",") if v]


def load_config(args: argparse.Namespace) -> StudyConfig:
    """The validated, resolved config of a command (variant/schedule conflicts included: the
    config checks them), and for a sweep a dry resolution of its trial configs, so that errors
    are reported before anything is written."""
    if args.workers is None:
        default_workers()  # a bad $ACRMDN_WORKERS: one line now, not once the study has started
    if args.study_name is not None:
        check_study_name(args.study_name, "--study-name")
    device = checked_device(args.device)
    if args.command == "ablation":
        cfg = load_profile(args.profile, args.overrides, tasks=_split(args.tasks), variants=_split(args.variants),
                           seeds=args.seeds, workers=args.workers, pack=args.pack,
                           study_name=args.study_name, device=device,
                           resume_from_weights=args.resume_from_weights or None)
        checked_device(cfg.device)  # a profile's or --set device
        _check_cell_count(cfg, args.yes)
        return cfg
    space = args.space.split(",") if args.space else None
    cfg = load_profile(args.profile, args.overrides, workers=args.workers, device=device, **{
        "sweep.task": args.task, "sweep.variant": args.variant, "sweep.space": space,
        "sweep.trials": args.trials, "sweep.sampler": args.sampler, "sweep.storage": args.storage,
        "sweep.study_name": args.study_name})
    from experiments.sweeps.runner import check_sweep

    check_sweep(cfg)
    checked_device(cfg.device)
    return cfg


def _check_cell_count(cfg: StudyConfig, yes: bool) -> None:
    n = len(cfg.tasks) * len(cfg.variants) * cfg.seeds
    if n > MAX_CELLS and not yes:
        raise ConfigError(f"seeds: the study would have {n:,} cells ({len(cfg.tasks)} task(s) x {len(cfg.variants)} "
                          f"variant(s) x {cfg.seeds} seed(s)), more than {MAX_CELLS:,}; add --yes to run it")


def _dry_run(cfg: StudyConfig, command: str) -> int:
    """What the command would run, once its config and names are checked; nothing is written."""
    if command == "ablation":
        n = len(cfg.tasks) * len(cfg.variants) * cfg.seeds
        print(f"study {cfg.resolved_study_name()!r}: {n} cell(s) ({', '.join(cfg.tasks)} x {', '.join(cfg.variants)} "
              f"x {cfg.seeds} seed(s)); dry run, nothing written")
    else:
        from experiments.sweeps.runner import planned_trials, study_name

        print(f"sweep {study_name(cfg)!r}: {planned_trials(cfg)} trial(s) of {cfg.sweep.task} / {cfg.sweep.variant}; "
              "dry run, nothing written")
    return 0


def main(argv: list[str] | None = None) -> int:
    if signal.getsignal(signal.SIGINT) is signal.SIG_IGN:
        # started in the background by a shell (`cmd &`), which ignores SIGINT for it: `kill -INT` stops a
        # study then as Ctrl-C does (each cell checkpointed and KILLED), not only its workers
        signal.signal(signal.SIGINT, signal.default_int_handler)
    args = build_parser().parse_args(argv)
    level = logging.DEBUG if getattr(args, "verbose", False) else logging.INFO
    logging.basicConfig(level=level, format="%(asctime)s %(name)s: %(message)s", stream=sys.stderr)
    for noisy in ("alembic", "mlflow", "urllib3", "matplotlib"):
        logging.getLogger(noisy).setLevel(logging.WARNING)
    from experiments.cell_run import quiet_store_errors

    quiet_store_errors(level)
    try:
        return _command(args)
    except Exception as exc:  # a store fault mid-command (experiments/runtime/store_faults.py): one line, exit 3
        from experiments.runtime.store_faults import fault_reason

        reason = fault_reason(exc)
        if reason is None:
            raise
        return store_fault_exit(exc, reason)


def store_fault_exit(exc: BaseException, reason: str) -> int:
    """What a command stopped by a store fault prints: the summary of what finished (stdout), then one error line
    naming the fault and the file that holds its traceback (stderr); exit code 3."""
    from experiments.runtime.store_faults import ADVICE, StoreFault, write_details

    outcome = getattr(exc, "outcome", None) if isinstance(exc, StoreFault) else None
    if outcome is not None:
        from experiments.ablation import fault_summary

        print(fault_summary(outcome, exc.unfinished))
    details = write_details(exc)
    where = f" (traceback in {details})" if details else ""
    print(_one_line(f"error: the MLflow store failed: {reason}; {ADVICE}{where}"), file=sys.stderr)
    return 3


def _command(args: argparse.Namespace) -> int:
    try:
        set_training_threads(getattr(args, "threads", None))
    except ConfigError as e:
        print(_one_line(f"error: {e}"), file=sys.stderr)
        return 2

    if args.command in ("smoothing", "idm"):
        from experiments.control_studies import main as postprocess_main

        return postprocess_main(args)

    if args.command == "milestones":
        from experiments.milestones import main as milestones_main

        args.tasks, args.variants = _split(args.tasks), _split(args.variants)
        return milestones_main(args)

    if args.command == "scaling":
        from experiments.scaling import main as scaling_main

        try:
            return scaling_main(args)
        except ConfigError as e:
            print(_one_line(f"error: {e}"), file=sys.stderr)
            return 2

    if args.command == "ui":
        from experiments.ui import serve

        return serve(args.host, args.port)

    try:
        cfg = load_config(args)
    except ConfigError as e:
        print(_one_line(f"error: {e}"), file=sys.stderr)
        return 2

    queue = None
    if getattr(args, "worker", False):
        from experiments.runtime.cell_queue import resolve_queue

        try:
            queue = resolve_queue(args.queue)
        except ConfigError as e:
            print(_one_line(f"error: {e}"), file=sys.stderr)
            return 2
    if args.dry_run:
        return _dry_run(cfg, args.command)
    from experiments.runtime.store_check import StoreUnavailable, wait_for_stores
    from experiments.runtime.tracking import tracking_uri

    try:  # a locked store or a server that is down: bounded retries, then one line, nothing written
        wait_for_stores(tracking_uri(), tuple(u for u in (queue, cfg.sweep.storage if args.command == "sweep"
                                                           else None) if u))
    except StoreUnavailable as e:
        print(_one_line(f"error: {e}"), file=sys.stderr)
        return 3

    if args.command == "ablation":
        from experiments.ablation import run_study, summary_text
        from experiments.runtime.tracking import Client

        try:
            if queue:
                from experiments.runtime.cell_queue import run_worker

                outcome = run_worker(cfg, queue)
            else:
                outcome = run_study(cfg)
        except KeyboardInterrupt:
            print("interrupted; re-run the same command to resume the unfinished cells", file=sys.stderr)
            return 130
        print(summary_text(outcome, Client()))
        return 1 if outcome.failures else 0

    from experiments.sweeps.runner import run_sweep

    outcome = run_sweep(cfg)
    print(outcome.summary())
    return 1 if outcome.failed else 0
