"""Quality check at small scale: train the variants on a task's demonstrations under
the same wall-clock budget, then roll out N episodes and run them in pybullet.

    python -m stm.quality [--task reacher] [--minutes 5] [--episodes 100] [--variants ...] [--json out.json]
"""

from __future__ import annotations

import argparse
import json
import logging
import os
import time

import numpy as np
import torch

from envs.datasets import load_demos
from envs.tasks import get_task
from stm.config import ModelConfig, TrainConfig
from stm.registry import VARIANTS, get_variant
from stm.rollout import evaluate, generate
from stm.train import train

log = logging.getLogger("stm.quality")


def run_variant(name: str, task_name: str, minutes: float, episodes: int, model_cfg: ModelConfig,
                train_cfg: TrainConfig, seed: int = 0, feedback: str = "component_mean") -> dict:
    task = get_task(task_name)
    model_task = get_task(task.model_task)
    demos = load_demos(model_task, seed=0)
    m, t = get_variant(name).configs(model_cfg, TrainConfig.from_dict(
        {**train_cfg.to_dict(), "max_seconds": minutes * 60.0, "seed": seed}))
    res = train(m, t, model_task, demos)
    eps = task.episodes(episodes, seed=12345)
    ro = generate(res.model, task, eps, feedback=feedback)
    start = time.perf_counter()
    metrics = evaluate(task, ro, eps)
    physics = time.perf_counter() - start
    success = [r["success"] for r in metrics]
    return {"variant": name, "task": task_name, "iterations": res.iterations, "train_seconds": res.seconds,
            "model": m.to_dict(), "train": t.to_dict(),
            "final_loss": float(np.mean(res.history["train/loss"][-20:])), "success_rate": float(np.mean(success)),
            "n_rollouts": len(success), "final_distance_mean": float(np.mean([r["final_distance"] for r in metrics])),
            "generation_seconds": ro.seconds, "physics_seconds": physics}


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="reacher")
    ap.add_argument("--minutes", type=float, default=5.0)
    ap.add_argument("--episodes", type=int, default=100)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS))
    ap.add_argument("--hidden", type=int, default=64)
    ap.add_argument("--mixtures", type=int, default=3)
    ap.add_argument("--lr", type=float, default=2e-3)
    ap.add_argument("--batch", type=int, default=45)
    ap.add_argument("--u", type=int, default=5)
    ap.add_argument("--v", type=int, default=5)
    ap.add_argument("--sigma-min", type=float, default=ModelConfig.sigma_min)
    ap.add_argument("--feedback", default="component_mean", help="what the MDN feeds back, in training and rollouts")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--json", default=None)
    args = ap.parse_args(argv)
    logging.basicConfig(level=logging.INFO, format="%(asctime)s %(name)s %(message)s")
    torch.set_num_threads(args.threads)
    model_cfg = ModelConfig(hidden_size=args.hidden, num_layers=3, mixtures=args.mixtures, sigma_min=args.sigma_min)
    train_cfg = TrainConfig(iters=10**7, batch_size=args.batch, lr=args.lr, u=args.u, v=args.v, log_every=0,
                            checkpoint_every=0, feedback=args.feedback)
    results = []
    for name in args.variants:
        load = os.getloadavg()[0]
        r = run_variant(name, args.task, args.minutes, args.episodes, model_cfg, train_cfg, args.seed, args.feedback)
        r["load_average_at_start"] = load
        r["load_average_at_end"] = os.getloadavg()[0]
        log.info("%s", json.dumps(r))
        results.append(r)
        if args.json:
            with open(args.json, "w") as f:
                json.dump({"args": vars(args), "results": results}, f, indent=1)
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
