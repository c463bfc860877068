"""The training iteration on a checkpoint's weights: `python -m stm.speed.bench --weights CHECKPOINT`.

The main bench times freshly initialised models; some costs appear only once a model has trained. A mixture head
fitted to teacher-forced demonstrations grows sharply peaked, and its gradients fill with subnormal floats, which
the CPU multiplies on a slow path (stm.training.subnormals). This times a pack of K copies of the checkpoint's
model on its task's demonstrations, under the schedule and kernel it trained with, with subnormals flushed (as
stm.training.loop trains) and kept (IEEE), interleaved round by round: subnormal_slowdown = kept / flushed.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

from stm.config import ModelConfig, TrainConfig
from stm.training.checkpoint import load_checkpoint
from stm.training.loop import pack_iteration
from stm.training.subnormals import subnormals_flushed


def trained_weights_bench(path: Path, rounds: int, reps: int) -> dict:
    from envs.datasets import load_demos
    from envs.tasks import get_task
    from stm.speed import bench

    ckpt = load_checkpoint(path)
    model_cfg, train_cfg = ModelConfig.from_dict(ckpt["model_config"]), TrainConfig.from_dict(ckpt["train_config"])
    task = get_task(ckpt["task"])
    demos = load_demos(task, 0)
    cfgs = [dataclasses.replace(train_cfg, seed=seed) for seed in range(bench.PACK)]
    step = pack_iteration(model_cfg, cfgs, task, demos, states=[ckpt["model"]] * bench.PACK, device=bench._device)

    def mode(flush: bool):
        def call():
            with subnormals_flushed(flush):
                step()
        return call

    cases = {"flushed": mode(True), "ieee": mode(False)}
    for fn in cases.values():  # warm-up
        fn()
    med = bench.interleaved_medians(cases, rounds, reps)
    return {"checkpoint": Path(path).name, "task": ckpt["task"], "iteration": int(ckpt["iteration"]),
            "head": model_cfg.head, "u": train_cfg.u, "v": train_cfg.v, "step_kernel": train_cfg.step_kernel,
            "packed_k": bench.PACK, "batch": min(train_cfg.batch_size, len(demos)),
            "steps": train_cfg.window or int(demos.lengths.max()) + train_cfg.hold_steps,
            "ms_per_iter": {k: round(v * 1e3, 2) for k, v in med.items()},
            "subnormal_slowdown": round(med["ieee"] / med["flushed"], 3)}
