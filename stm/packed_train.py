"""Training K models of one config on one dataset together: stm.train.train for each seed,
in one packed loop (stm.packed).

Each seed keeps what it has alone: its initialisation (torch.manual_seed(seed) then an
STM, as train does), its batch generator (data order, input noise, samples), its Adam
state, step count and learning rate, its gradient clipping, its tf_warmup and (u, v)
schedule position, its checkpoint (an ordinary single-model checkpoint, so `train` and
`train_packed` resume each other's), history, validation and early stop. Seeds at the
same schedule step share one unroll; a seed whose loss or gradient goes non-finite is
flagged (`PackedResult.failure`, a TrainingDiverged) and leaves the pack, the others go on.
"""

from __future__ import annotations

import dataclasses
import logging
import math
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from envs.tasks.base import Demos, Task
from stm.checkpoint import check_resumable, checkpoint_payload, load_checkpoint, save_checkpoint
from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.interrupts import whole_step
from stm.model import STM, normalization_stats
from stm.packed import PackedAdam, PackedSTM, clip_per_model, packed_unroll
from stm.train import (
    Batch,
    DemoTensors,
    TrainingDiverged,
    TrainResult,
    Validation,
    _sample_indices,
)
from stm.windows import Windows

log = logging.getLogger(__name__)

# fields that may differ between the seeds of a pack (the rest shape one shared unroll)
PER_SEED = {"seed", "iters", "lr", "grad_clip", "u", "v", "tf_warmup", "checkpoint_every", "log_every", "val_every",
            "val_episodes", "max_seconds"}


@dataclass
class PackedResult(TrainResult):
    """One seed's TrainResult; failure: why it left the pack (None when it trained to the end)."""

    failure: TrainingDiverged | None = None


@dataclass
class _Seed:
    cfg: TrainConfig
    gen: torch.Generator
    rng_torch: torch.Tensor  # the global torch RNG after its initialisation (what train checkpoints)
    history: dict
    path: Path | None
    iteration: int = 0
    seconds_before: float = 0.0
    stopped_early: bool = False
    failure: TrainingDiverged | None = None
    done: bool = False
    saved: int = 0  # the iteration its checkpoint on disk holds


def check_packable(model_cfgs: list[ModelConfig], train_cfgs: list[TrainConfig]) -> None:
    """One line ValueError unless the seeds can share a pack."""
    if not train_cfgs or len(model_cfgs) != len(train_cfgs):
        raise ValueError(f"a pack needs one model and one train config per seed, got {len(model_cfgs)} "
                         f"and {len(train_cfgs)}")
    if any(m != model_cfgs[0] for m in model_cfgs):
        raise ValueError("the seeds of a pack must share one model config")
    shared = [{k: v for k, v in c.to_dict().items() if k not in PER_SEED} for c in train_cfgs]
    if any(s != shared[0] for s in shared):
        diff = sorted(k for s in shared for k in s if s[k] != shared[0][k])
        raise ValueError(f"the seeds of a pack differ in {', '.join(sorted(set(diff)))}; only "
                         f"{', '.join(sorted(PER_SEED))} may differ")


def _init_models(model_cfg: ModelConfig, cfgs: list[TrainConfig], task: Task, stats) -> tuple[list[STM], list]:
    models, rngs = [], []
    for cfg in cfgs:  # as train: seed the global RNG, then build (its RNG state is what train checkpoints)
        torch.manual_seed(cfg.seed)
        models.append(STM(model_cfg, task.layout, *stats, phi_mode=cfg.phi_mode))
        rngs.append(torch.get_rng_state())
    return models, rngs


def _batch(data: DemoTensors, idx: list[torch.Tensor], windows: list[Windows] | None = None) -> Batch:
    """Per-seed batches stacked (K, B, T+1, .), padded to the longest, or per-seed windows of them (stm.windows)."""
    ix = torch.stack(idx)
    if windows is not None:
        return data.window_batch(ix, Windows(*(torch.stack([getattr(w, f.name) for w in windows])
                                               for f in dataclasses.fields(Windows))))
    T = int(data.lengths[ix].max())
    mask = torch.arange(T)[None, None, :] < data.lengths[ix][..., None]
    return Batch(data.states[ix, : T + 1], data.q[ix, : T + 1], data.psi[ix, : T + 1], mask)


def train_packed(model_cfg: ModelConfig, train_cfgs: list[TrainConfig], task: Task, demos: Demos, *,
                 checkpoint_paths: list[Path | None] | None = None, resume: bool = True,
                 on_metrics: Callable[[int, int, dict[str, float]], None] | None = None,
                 on_checkpoint: Callable[[int, Path, int], None] | None = None,
                 on_validation: Callable[[int, int, float], bool] | None = None) -> list[PackedResult]:
    """Train one STM per train config (seed) on `demos`, packed; one result per seed, in order.

    Callbacks get the seed's index in the pack first: on_metrics(k, iteration, metrics),
    on_checkpoint(k, path, iteration), on_validation(k, iteration, value) -> stop seed k."""
    model_cfgs = [model_cfg] * len(train_cfgs)
    check_packable(model_cfgs, train_cfgs)
    K = len(train_cfgs)
    paths = [Path(p) if p is not None else None for p in (checkpoint_paths or [None] * K)]
    if len(paths) != K:
        raise ValueError(f"{len(paths)} checkpoint paths for {K} seeds")
    kin = default_tip_kinematics(torch.float32)
    demos = demos.with_hold(train_cfgs[0].hold_steps)  # one for the pack (check_packable)
    data = DemoTensors.build(task, demos)
    N = len(demos)
    valid = torch.arange(data.states.shape[1])[None, :] <= data.lengths[:, None]
    models, rngs = _init_models(model_cfg, train_cfgs, task, normalization_stats(data.states, valid, task.layout))
    pack = PackedSTM.from_models(models)
    params = list(pack.stacked)
    opt = PackedAdam(params, [c.lr for c in train_cfgs])
    adam_template = torch.optim.Adam(models[0].parameters(), lr=train_cfgs[0].lr).state_dict()
    seeds = [_Seed(cfg, torch.Generator().manual_seed(cfg.seed), rngs[k],
                   {"train/loss": [], "train/grad_norm": [], "val/iteration": [], "val/metric": []}, paths[k])
             for k, cfg in enumerate(train_cfgs)]
    for k, s in enumerate(seeds):
        if s.path is not None and resume and s.path.exists():
            _resume(k, s, pack, opt, model_cfg, task)
    validation = {n: Validation.build(task, demos, n) for n in {c.val_episodes for c in train_cfgs if c.val_every}}
    clips = torch.tensor([c.grad_clip if c.grad_clip > 0 else math.inf for c in train_cfgs])
    t0 = time.perf_counter()

    def elapsed(s: _Seed) -> float:
        return s.seconds_before + time.perf_counter() - t0

    def save(k: int) -> None:
        s = seeds[k]
        if s.path is None:
            return
        model = pack.extract(k)
        opt_state = opt.model_state(k, adam_template)
        payload = checkpoint_payload(model, _StateDict(opt_state), model_cfg, s.cfg, task, s.iteration, s.gen,
                                      s.history, elapsed(s), s.stopped_early)
        payload["rng"]["torch"] = s.rng_torch
        save_checkpoint(payload, s.path)
        s.saved = s.iteration
        if on_checkpoint is not None:
            on_checkpoint(k, s.path, s.iteration)

    def finish(k: int) -> None:
        seeds[k].done = True
        if seeds[k].failure is None:
            save(k)

    for k, s in enumerate(seeds):
        if s.iteration >= s.cfg.iters or s.stopped_early:  # resumed complete: saved again, as train does
            finish(k)
    try:
        while True:
            for k, s in enumerate(seeds):
                if not s.done and s.cfg.max_seconds and elapsed(s) >= s.cfg.max_seconds:
                    log.info("seed %d: time budget of %.0f s reached at iteration %d", s.cfg.seed,
                             s.cfg.max_seconds, s.iteration)
                    finish(k)
            active = [k for k, s in enumerate(seeds) if not s.done]
            if not active:
                break
            with whole_step():  # a Ctrl-C waits for the step: what is checkpointed below is one iteration's
                losses = _step(pack, data, N, task, kin, seeds, active, opt, clips)
                for k in active:
                    s = seeds[k]
                    if s.failure is None:
                        s.iteration += 1
                        s.history["train/loss"].append(losses[k][0])
                        s.history["train/grad_norm"].append(losses[k][1])
            for k in active:
                s = seeds[k]
                if s.failure is not None:
                    log.warning("seed %d left the pack: %s", s.cfg.seed, s.failure)
                    s.done = True
                    continue
                _after_step(k, s, pack, task, validation, on_metrics, on_validation, elapsed(s))
                if s.cfg.checkpoint_every and s.iteration % s.cfg.checkpoint_every == 0 and not s.stopped_early:
                    save(k)
                if s.iteration >= s.cfg.iters or s.stopped_early:
                    finish(k)
    except KeyboardInterrupt:  # no finished iteration is lost: each seed checkpointed where it stands
        for k, s in enumerate(seeds):
            if not s.done and s.failure is None and s.iteration != s.saved:
                log.info("seed %d interrupted at iteration %d: checkpointed there", s.cfg.seed, s.iteration)
                save(k)
        raise
    return [PackedResult(model=pack.extract(k), history=s.history, seconds=elapsed(s), iterations=s.iteration,
                         stopped_early=s.stopped_early, checkpoint_path=s.path, failure=s.failure)
            for k, s in enumerate(seeds)]


class _StateDict:
    """What checkpoint_payload reads of an optimiser: state_dict()."""

    def __init__(self, state: dict):
        self.state = state

    def state_dict(self) -> dict:
        return self.state


def _resume(k: int, s: _Seed, pack: PackedSTM, opt: PackedAdam, model_cfg: ModelConfig, task: Task) -> None:
    ckpt = load_checkpoint(s.path)
    check_resumable(ckpt, model_cfg, s.cfg, task, s.path)
    pack.load_model_state(k, ckpt["model"])
    opt.load_model_state(k, ckpt["optimizer"])
    s.rng_torch = ckpt["rng"]["torch"]
    s.gen.set_state(ckpt["rng"]["batch"])
    s.history = {key: list(v) for key, v in ckpt["history"].items()}
    s.iteration, s.seconds_before = int(ckpt["iteration"]), float(ckpt["seconds"])
    s.saved = s.iteration
    s.stopped_early = bool(ckpt.get("stopped_early", False))
    log.info("seed %d: resuming from %s at iteration %d", s.cfg.seed, s.path, s.iteration)


def _step(pack: PackedSTM, data: DemoTensors, N: int, task: Task, kin, seeds: list[_Seed], active: list[int],
          opt: PackedAdam, clips: torch.Tensor) -> dict[int, tuple[float, float]]:
    """One iteration of the active seeds: per seed (loss, grad norm); sets failure where non-finite."""
    idx = {k: _sample_indices(N, seeds[k].cfg.batch_size, seeds[k].gen) for k in active}
    windows = {k: data.windows(idx[k], s.cfg.window, s.cfg.burn_in, s.gen) for k in active  # after idx, as train
               if (s := seeds[k]).cfg.window}
    groups: dict[tuple[int, int], list[int]] = {}
    for k in active:  # seeds at the same schedule step share one unroll
        c = seeds[k].cfg
        groups.setdefault((c.u, 0 if seeds[k].iteration < c.tf_warmup else c.v), []).append(k)
    for p in pack.stacked:
        p.grad = None
    total, out = 0.0, {}
    for (u, v), ks in groups.items():
        cfg = dataclasses.replace(seeds[ks[0]].cfg, u=u, v=v)
        sel = None if ks == list(range(pack.K)) else torch.tensor(ks)
        view = pack.view(sel)
        batch = _batch(data, [idx[k] for k in ks], [windows[k] for k in ks] if windows else None)
        steps = [int(m.sum(-1).max()) for m in batch.mask]  # each seed's own T: its noise and samples
        raw = packed_unroll(view, batch.states, batch.q, batch.psi, steps, task, cfg, kin, [seeds[k].gen for k in ks],
                            burn=batch.burn)
        losses = view.losses(raw, view.normalize(batch.states[:, :, 1:]), batch.mask)
        finite = torch.isfinite(losses.detach())
        for j, k in enumerate(ks):
            if not finite[j]:
                seeds[k].failure = TrainingDiverged(seeds[k].iteration + 1, "loss")
            out[k] = (losses[j].item(), math.nan)
        total = total + losses[finite].sum()
    if isinstance(total, torch.Tensor) and total.requires_grad:
        total.backward()
    ok = [k for k in active if seeds[k].failure is None]
    if not ok:
        return out
    for p in pack.stacked:
        if p.grad is None:
            p.grad = torch.zeros_like(p)
    norms = clip_per_model(list(pack.stacked), clips)
    for k in ok:
        if not math.isfinite(norms[k].item()):
            seeds[k].failure = TrainingDiverged(seeds[k].iteration + 1, "gradient")
        out[k] = (out[k][0], norms[k].item())
    ok = [k for k in ok if seeds[k].failure is None]
    if ok:
        opt.step(torch.tensor(ok))
    return out


def _after_step(k: int, s: _Seed, pack: PackedSTM, task: Task, validation, on_metrics, on_validation,
                seconds: float) -> None:
    cfg, it = s.cfg, s.iteration
    if cfg.log_every and it % cfg.log_every == 0 and on_metrics is not None:
        window = s.history["train/loss"][-cfg.log_every:]
        on_metrics(k, it, {"train/loss": float(np.mean(window)), "train/grad_norm": s.history["train/grad_norm"][-1],
                           "train/seconds": seconds})
    if cfg.val_every and it % cfg.val_every == 0:
        value = validation[cfg.val_episodes].error(pack.extract(k), task)
        s.history["val/iteration"].append(float(it))
        s.history["val/metric"].append(value)
        if on_validation is not None and on_validation(k, it, value):
            s.stopped_early = True
            log.info("seed %d stopped early at iteration %d (validation %.4g)", cfg.seed, it, value)
