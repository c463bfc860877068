"""How a study's training throughput grows with worker processes: `python -m experiments scaling`.

The same study (a profile's tasks x variants x seeds, packed as `ablation` packs them) runs once per worker
count, each time into a fresh MLflow store in a temporary folder, with its demonstrations built beforehand (so no
arm pays for them) and, by default, few iterations and a token evaluation (so training dominates). Each arm's
figure is model-iterations per second: the iterations every cell trained, summed, over the study's wall time.
The ratio to the first worker count is the speed-up; on a machine with K idle cores and one thread per process
it should approach K (the packs of a study are spread over the processes, so every core trains).

Run it on otherwise idle cores: any other load takes cores from the arms with more workers.
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import sys
import tempfile
from pathlib import Path
from unittest.mock import patch

from experiments.runtime.processes import training_threads, usable_cores
from experiments.study_config import StudyConfig, load_profile

log = logging.getLogger(__name__)

# what makes an arm training-dominated unless the user says otherwise (--set wins: it comes later)
TRAINING_ONLY = ("train.val_every=0", "eval.rollouts=2", "eval.figures=1")


def add_parser(sub) -> None:
    p = sub.add_parser("scaling", help="a study's model-iterations per second with 1, 2, ... worker processes")
    p.add_argument("--profile", default="quick")
    p.add_argument("--tasks", nargs="+", default=["pick-place"])
    p.add_argument("--variants", nargs="+", default=["all"])
    p.add_argument("--seeds", type=int, default=2)
    p.add_argument("--iters", type=int, default=300, help="training iterations of every cell")
    p.add_argument("--workers", type=int, nargs="+", default=[1, 2], metavar="K",
                   help="worker counts to compare, the first is the reference (default: 1 2)")
    p.add_argument("--set", dest="overrides", action="append", default=[], metavar="FIELD=VALUE")
    p.add_argument("--json", type=Path, default=None, help="also write the result here")


def arm_config(args: argparse.Namespace, workers: int) -> StudyConfig:
    """The study of one arm: the same cells for every worker count."""
    iters = [f"per_task.{task}.train.iters={args.iters}" for task in args.tasks]
    return load_profile(args.profile, [*TRAINING_ONLY, f"train.iters={args.iters}", *iters, *args.overrides],
                        tasks=args.tasks, variants=args.variants, seeds=args.seeds, workers=workers,
                        study_name=f"scaling-{workers}-workers")


def run_arm(cfg: StudyConfig) -> dict:
    """Train cfg's study into a fresh store; its wall time and model-iterations per second."""
    from experiments.ablation import run_study
    from experiments.cells import build_cells

    cells = build_cells(cfg)
    model_iterations = sum(cell.train.iters for cell in cells)
    with tempfile.TemporaryDirectory(prefix="acrmdn-scaling-") as store, \
            patch.dict(os.environ, {"MLFLOW_TRACKING_URI": f"sqlite:///{store}/mlflow.db"}):
        outcome = run_study(cfg, progress=False)
    seconds = outcome.seconds
    if outcome.failures:
        raise RuntimeError(f"{len(outcome.failures)} cell(s) failed with {cfg.workers} worker(s): "
                           f"{outcome.failures[0].error}")
    return {"workers": cfg.workers, "cells": len(cells), "model_iterations": model_iterations,
            "seconds": round(seconds, 2), "model_iterations_per_s": round(model_iterations / seconds, 3)}


def measure(args: argparse.Namespace) -> dict:
    from experiments.cells import build_cells
    from experiments.runtime.schedule import prepare_datasets

    configs = [arm_config(args, k) for k in args.workers]
    prepare_datasets(build_cells(configs[0]))  # cached for every arm: none of them times the demonstrations
    arms = [run_arm(cfg) for cfg in configs]
    base = arms[0]["model_iterations_per_s"]
    for arm in arms:
        arm["speedup"] = round(arm["model_iterations_per_s"] / base, 3)
    return {"profile": args.profile, "tasks": args.tasks, "variants": args.variants, "seeds": args.seeds,
            "iters": args.iters, "threads_per_process": training_threads(), "cpus": usable_cores(),
            "load_before": os.getloadavg()[0], "arms": arms}


def main(args: argparse.Namespace) -> int:
    if len(set(args.workers)) != len(args.workers) or min(args.workers) < 1 or args.iters < 1:
        print("error: --workers takes distinct counts >= 1 and --iters >= 1", file=sys.stderr)
        return 2
    result = measure(args)
    text = json.dumps(result, indent=2)
    print(text)
    if args.json:
        args.json.write_text(text + "\n")
    for arm in result["arms"]:
        log.info("%d worker(s): %.1f model-iterations/s (%.2fx) in %.0f s", arm["workers"],
                 arm["model_iterations_per_s"], arm["speedup"], arm["seconds"])
    return 0
