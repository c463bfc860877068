"""Training: one loop for K seeds of one config on one dataset, trained together as a pack (stm.packed); a single
model is a pack of one (`train`).

Per iteration each seed draws its batch from its own generator (stm.training.batches); the seeds at the same
schedule step (stm.training.autoconditioning) share one unroll; each seed's loss is backpropagated, its gradient
clipped and an Adam step taken per model. Each seed keeps what it would have alone: its initialisation
(torch.manual_seed(seed), then an STM), its batch generator (data order, input noise, samples), its Adam state, step
count and learning rate, its clipping, its tf_warmup and (u, v) schedule position, its checkpoint (an ordinary
single-model checkpoint, stm.training.checkpoint, exact to resume), history, validation and early stop. A seed whose
loss or gradient goes non-finite leaves the pack with its result's `failure` (a TrainingDiverged, which `train`
raises) and its last good checkpoint on disk; the others go on. A Ctrl-C waits for the step in progress, then each
seed is checkpointed where it stands.

`device` (stm.device: auto, cpu, cuda[:N]) is where the pack, its optimiser, the batches and the tip kinematics
live; the models are initialised on the CPU (the same weights on any device), the data stays there and each
iteration's batch is moved; checkpoints and results come back on the CPU. On CUDA, iterations of static shapes
replay a captured CUDA graph (stm.training.cuda_graph).
"""

from __future__ import annotations

import dataclasses
import logging
import math
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import torch
from tqdm.auto import tqdm

from envs.tasks.base import Demos, Task
from stm.config import ModelConfig, TrainConfig
from stm.device import resolve_device
from stm.fk import default_tip_kinematics
from stm.model import STM, normalization_stats
from stm.packed import PackedAdam, PackedSTM, clip_per_model
from stm.training.autoconditioning import iteration_schedule, unroll
from stm.training.batches import DemoTensors
from stm.training.checkpoint import check_resumable, checkpoint_payload, load_checkpoint, save_checkpoint
from stm.training.cuda_graph import StepGraphs, capturable
from stm.training.interrupts import whole_step
from stm.training.subnormals import subnormals_flushed
from stm.training.validation import Validation

log = logging.getLogger(__name__)

# fields that may differ between the seeds of a pack (the rest shape one shared unroll)
PER_SEED = {"seed", "iters", "lr", "grad_clip", "u", "v", "tf_warmup", "checkpoint_every", "log_every", "val_every",
            "val_episodes", "max_seconds"}


class TrainingDiverged(RuntimeError):
    """The loss or the gradient became NaN/inf; the last good checkpoint is left on disk."""

    def __init__(self, iteration: int, what: str = "loss"):
        super().__init__(f"training diverged at iteration {iteration}: non-finite {what}")
        self.iteration = iteration


@dataclass
class TrainResult:
    """One seed's training; failure: why it left its pack (None when it trained to the end)."""

    model: STM
    history: dict[str, list[float]]
    seconds: float
    iterations: int
    stopped_early: bool = False
    checkpoint_path: Path | None = None
    failure: TrainingDiverged | None = None


def training_metrics(history: dict[str, list[float]], log_every: int, seconds: float) -> dict[str, float]:
    """What a seed reports to on_metrics every log_every iterations (a study logs it to the seed's run)."""
    return {"train/loss": float(np.mean(history["train/loss"][-log_every:])),
            "train/grad_norm": history["train/grad_norm"][-1], "train/seconds": seconds}


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


def train(model_cfg: ModelConfig, train_cfg: TrainConfig, task: Task, demos: Demos, *,
          checkpoint_path: Path | None = None, resume: bool = True,
          on_metrics: Callable[[int, dict[str, float]], None] | None = None,
          on_checkpoint: Callable[[Path, int], None] | None = None,
          on_validation: Callable[[int, float], bool] | None = None,
          progress: bool = False, device: str | torch.device = "cpu") -> TrainResult:
    """Train one STM on `demos` of `task` (a pack of one); raises TrainingDiverged where it diverges."""
    [result] = train_packed(
        model_cfg, [train_cfg], task, demos, checkpoint_paths=[checkpoint_path], resume=resume, progress=progress,
        device=device,
        on_metrics=None if on_metrics is None else lambda _k, it, metrics: on_metrics(it, metrics),
        on_checkpoint=None if on_checkpoint is None else lambda _k, path, it: on_checkpoint(path, it),
        on_validation=None if on_validation is None else lambda _k, it, value: on_validation(it, value))
    if result.failure is not None:
        raise result.failure
    return result


def train_packed(model_cfg: ModelConfig, train_cfgs: list[TrainConfig], task: Task, demos: Demos, *,
                 checkpoint_paths: list[Path | None] | None = None, resume: bool = True,
                 on_metrics: Callable[[int, int, dict[str, float]], None] | None = None,
                 on_checkpoint: Callable[[int, Path, int], None] | None = None,
                 on_validation: Callable[[int, int, float], bool] | None = None,
                 progress: bool = False, device: str | torch.device = "cpu") -> list[TrainResult]:
    """Train one STM per train config (seed) on `demos`, packed; one result per seed, in order.

    Callbacks get the seed's index in the pack first: on_metrics(k, iteration, metrics),
    on_checkpoint(k, path, iteration), on_validation(k, iteration, value) -> stop seed k."""
    check_packable([model_cfg] * len(train_cfgs), train_cfgs)
    K = len(train_cfgs)
    paths = [Path(p) if p is not None else None for p in (checkpoint_paths or [None] * K)]
    if len(paths) != K:
        raise ValueError(f"{len(paths)} checkpoint paths for {K} seeds")
    run = _PackRun(model_cfg, train_cfgs, task, demos.with_hold(train_cfgs[0].hold_steps), paths,
                   on_metrics, on_checkpoint, on_validation, resolve_device(device))
    if resume:
        for k, s in enumerate(run.seeds):
            if s.path is not None and s.path.exists():
                run.resume(k)
    show = progress and sys.stderr.isatty()
    with tqdm(total=sum(c.iters for c in train_cfgs), initial=sum(s.iteration for s in run.seeds), desc="train",
              disable=not show) as bar, subnormals_flushed():
        run.loop(bar)
    return [TrainResult(model=run.pack.extract(k), history=s.history, seconds=run.elapsed(s), iterations=s.iteration,
                        stopped_early=s.stopped_early, checkpoint_path=s.path, failure=s.failure)
            for k, s in enumerate(run.seeds)]


def pack_iteration(model_cfg: ModelConfig, train_cfgs: list[TrainConfig], task: Task, demos: Demos, *,
                   states: list[dict] | None = None, device: str | torch.device = "cpu") -> Callable[[], None]:
    """train_packed's iteration for these seeds, one per call (each seed draws its next batch and steps; no
    checkpoints, callbacks or end): what `python -m stm.speed.bench` times. states: STM state dicts the seeds start
    from (a checkpoint's weights and normalisation, one for all) instead of their initialisation. A seed that
    diverges raises its failure."""
    check_packable([model_cfg] * len(train_cfgs), train_cfgs)
    K = len(train_cfgs)
    run = _PackRun(model_cfg, train_cfgs, task, demos.with_hold(train_cfgs[0].hold_steps), [None] * K, None, None,
                   None, resolve_device(device))
    for k, state in enumerate(states or []):  # the checkpoint's normalisation, then its weights
        run.pack.state_mean.copy_(state["state_mean"])
        run.pack.state_std.copy_(state["state_std"])
        run.pack.load_model_state(k, state)
    active = list(range(K))

    def step() -> None:
        run.step(active)
        for s in run.seeds:
            if s.failure is not None:
                raise s.failure

    return step


def use_graphs(device: torch.device, cfg: TrainConfig) -> bool:
    """Whether a run replays captured CUDA graphs of its iterations (stm.training.cuda_graph)."""
    return device.type == "cuda" and capturable(cfg)


@dataclass
class _Seed:
    cfg: TrainConfig
    gen: torch.Generator
    rng_torch: torch.Tensor  # the global torch RNG after its initialisation (what its checkpoint holds)
    path: Path | None
    history: dict = field(default_factory=lambda: {"train/loss": [], "train/grad_norm": [], "val/iteration": [],
                                                   "val/metric": []})
    iteration: int = 0
    seconds_before: float = 0.0
    stopped_early: bool = False
    failure: TrainingDiverged | None = None
    done: bool = False
    saved: int = 0  # the iteration its checkpoint on disk holds


class _PackRun:
    """The state of one train_packed call: the pack, its optimiser, the seeds, the data and the callbacks."""

    def __init__(self, model_cfg: ModelConfig, cfgs: list[TrainConfig], task: Task, demos: Demos,
                 paths: list[Path | None], on_metrics, on_checkpoint, on_validation,
                 device: torch.device):
        self.model_cfg, self.task, self.device = model_cfg, task, device
        self.on_metrics, self.on_checkpoint, self.on_validation = on_metrics, on_checkpoint, on_validation
        self.kin = default_tip_kinematics(torch.float32).to(device)
        self.data = DemoTensors.build(task, demos)
        valid = torch.arange(self.data.states.shape[1])[None, :] <= self.data.lengths[:, None]
        stats = normalization_stats(self.data.states, valid, task.layout)
        models, self.seeds = [], []
        for cfg, path in zip(cfgs, paths, strict=True):  # each seed's init as alone: seed the global RNG, build
            torch.manual_seed(cfg.seed)
            models.append(STM(model_cfg, task.layout, *stats, phi_mode=cfg.phi_mode))
            self.seeds.append(_Seed(cfg, torch.Generator().manual_seed(cfg.seed), torch.get_rng_state(), path))
        self.pack = PackedSTM.from_models(models).to(device)
        self.opt = PackedAdam(list(self.pack.stacked), [c.lr for c in cfgs])
        self.graphs = StepGraphs(list(self.pack.stacked)) if use_graphs(device, cfgs[0]) else None
        self.adam_template = torch.optim.Adam(models[0].parameters(), lr=cfgs[0].lr).state_dict()
        self.clips = torch.tensor([c.grad_clip if c.grad_clip > 0 else math.inf for c in cfgs])
        self.validation = {n: Validation.build(task, demos, n) for n in {c.val_episodes for c in cfgs if c.val_every}}
        self.t0 = time.perf_counter()

    def elapsed(self, s: _Seed) -> float:
        return s.seconds_before + time.perf_counter() - self.t0

    def resume(self, k: int) -> None:
        s = self.seeds[k]
        ckpt = load_checkpoint(s.path)
        check_resumable(ckpt, self.model_cfg, s.cfg, self.task, s.path)
        self.pack.load_model_state(k, ckpt["model"])
        self.opt.load_model_state(k, ckpt["optimizer"])
        s.rng_torch = ckpt["rng"]["torch"]
        s.gen.set_state(ckpt["rng"]["batch"])
        s.history = {key: list(v) for key, v in ckpt["history"].items()}
        s.iteration, s.seconds_before = int(ckpt["iteration"]), float(ckpt["seconds"])
        s.saved = s.iteration
        s.stopped_early = bool(ckpt.get("stopped_early", False))
        log.info("seed %d: resuming from %s at iteration %d", s.cfg.seed, s.path, s.iteration)

    def save(self, k: int) -> None:
        s = self.seeds[k]
        if s.path is None:
            return
        payload = checkpoint_payload(self.pack.extract(k), _StateDict(self.opt.model_state(k, self.adam_template)),
                                     self.model_cfg, s.cfg, self.task, s.iteration, s.gen, s.history,
                                     self.elapsed(s), s.stopped_early)
        payload["rng"]["torch"] = s.rng_torch
        save_checkpoint(payload, s.path)
        s.saved = s.iteration
        if self.on_checkpoint is not None:
            self.on_checkpoint(k, s.path, s.iteration)

    def finish(self, k: int) -> None:
        self.seeds[k].done = True
        if self.seeds[k].failure is None:
            self.save(k)

    def loop(self, bar) -> None:
        for k, s in enumerate(self.seeds):
            if s.iteration >= s.cfg.iters or s.stopped_early:  # resumed complete: saved again
                self.finish(k)
        try:
            while True:
                for k, s in enumerate(self.seeds):
                    if not s.done and s.cfg.max_seconds and self.elapsed(s) >= s.cfg.max_seconds:
                        log.info("seed %d: time budget of %.0f s reached at iteration %d", s.cfg.seed,
                                 s.cfg.max_seconds, s.iteration)
                        self.finish(k)
                active = [k for k, s in enumerate(self.seeds) if not s.done]
                if not active:
                    return
                with whole_step():  # a Ctrl-C waits for the step: what is checkpointed below is one iteration's
                    self.step(active)
                for k in active:
                    self.after_step(k, bar)
        except KeyboardInterrupt:  # no finished iteration is lost: each seed checkpointed where it stands
            for k, s in enumerate(self.seeds):
                if not s.done and s.failure is None and s.iteration != s.saved:
                    log.info("seed %d interrupted at iteration %d: checkpointed there", s.cfg.seed, s.iteration)
                    self.save(k)
            raise

    def step(self, active: list[int]) -> None:
        """One iteration of the active seeds: each one's loss and gradient norm into its history, or its failure."""
        seeds, pack = self.seeds, self.pack
        draws = {k: self.data.draw(seeds[k].cfg, seeds[k].gen) for k in active}
        groups: dict[tuple[int, int], list[int]] = {}
        for k in active:  # seeds at the same schedule step share one unroll
            groups.setdefault(iteration_schedule(seeds[k].cfg, seeds[k].iteration), []).append(k)
        losses: dict[int, float] = {}
        if self.graphs is not None and self.graphed(groups, draws, losses):
            total = None  # the replayed graph left the gradients; every loss finite
        else:
            for p in pack.stacked:
                p.grad = None
            total, losses = self.forward(groups, draws)
        ok = [k for k in active if seeds[k].failure is None]
        if not ok:
            return
        if isinstance(total, torch.Tensor) and total.requires_grad:
            total.backward()
        self.update(ok, losses)

    def forward(self, groups: dict[tuple[int, int], list[int]], draws: dict) -> tuple[torch.Tensor | float, dict]:
        """The eager forward of an iteration: the sum of the finite losses to backpropagate, each seed's loss (a
        seed with a non-finite one gets its failure)."""
        seeds, pack = self.seeds, self.pack
        total, losses = 0.0, {}
        for (u, v), ks in groups.items():
            cfg = dataclasses.replace(seeds[ks[0]].cfg, u=u, v=v)
            view = pack.view(None if ks == list(range(pack.K)) else torch.tensor(ks))
            batch = self.data.stacked([draws[k] for k in ks])
            steps = [int(m.sum(-1).max()) for m in batch.mask]  # each seed's own T: its noise and samples
            batch = batch.to(self.device)
            raw = unroll(view, batch.states, batch.q, batch.psi, steps, self.task, cfg, self.kin,
                         [seeds[k].gen for k in ks], batch.burn)
            group = view.losses(raw, view.normalize(batch.states[:, :, 1:]), batch.mask, cfg.step_kernel)
            finite = torch.isfinite(group.detach())
            for j, k in enumerate(ks):
                losses[k] = group[j].item()
                if not finite[j]:
                    seeds[k].failure = TrainingDiverged(seeds[k].iteration + 1, "loss")
            total = total + group[finite].sum()
        return total, losses

    def graphed(self, groups: dict[tuple[int, int], list[int]], draws: dict, losses: dict) -> bool:
        """The iteration as a replayed CUDA graph (stm.training.cuda_graph): True with each seed's loss in `losses` and
        the gradients in place, False where it cannot be replayed or a loss is not finite (then run eagerly)."""
        seeds, pack, order = self.seeds, self.pack, list(groups.items())
        batches = [self.data.stacked([draws[k] for k in ks], full=True).to(self.device) for _, ks in order]
        idx = [None if ks == list(range(pack.K)) else torch.tensor(ks, device=self.device) for _, ks in order]

        def fn(static):
            out = []
            for ((u, v), ks), i, b in zip(order, idx, static, strict=True):
                view = pack.view(i)
                cfg = dataclasses.replace(seeds[ks[0]].cfg, u=u, v=v)
                raw = unroll(view, b.states, b.q, b.psi, [b.mask.shape[-1]] * len(ks), self.task, cfg, self.kin,
                             [None] * len(ks))
                out.append(view.losses(raw, view.normalize(b.states[:, :, 1:]), b.mask, cfg.step_kernel))
            sum(g.sum() for g in out).backward()
            return out

        out = self.graphs.run(tuple((uv, tuple(ks)) for uv, ks in order), fn, batches)
        if out is None:
            return False
        values = [g.tolist() for g in out]
        if not all(math.isfinite(x) for g in values for x in g):
            return False
        losses.update({k: g[j] for ((_, ks), g) in zip(order, values, strict=True) for j, k in enumerate(ks)})
        return True

    def update(self, ok: list[int], losses: dict) -> None:
        """Clipping and the Adam step of the seeds whose gradients are in place; their histories."""
        seeds, pack = self.seeds, self.pack
        for p in pack.stacked:
            if p.grad is None:
                p.grad = torch.zeros_like(p)
        norms = clip_per_model(list(pack.stacked), self.clips)
        for k in ok:
            if not math.isfinite(norms[k].item()):
                seeds[k].failure = TrainingDiverged(seeds[k].iteration + 1, "gradient")
        ok = [k for k in ok if seeds[k].failure is None]
        if ok:
            self.opt.step(torch.tensor(ok))
        for k in ok:
            s = seeds[k]
            s.iteration += 1
            s.history["train/loss"].append(losses[k])
            s.history["train/grad_norm"].append(norms[k].item())

    def after_step(self, k: int, bar) -> None:
        """A seed's metrics, validation, checkpoint and end after a step (or its leaving the pack)."""
        s = self.seeds[k]
        if s.failure is not None:
            log.warning("seed %d left the pack: %s", s.cfg.seed, s.failure)
            s.done = True
            return
        cfg, it = s.cfg, s.iteration
        bar.update(1)
        if cfg.log_every and it % cfg.log_every == 0:
            bar.set_postfix(loss=f"{s.history['train/loss'][-1]:.4g}")
            if self.on_metrics is not None:
                self.on_metrics(k, it, training_metrics(s.history, cfg.log_every, self.elapsed(s)))
        if cfg.val_every and it % cfg.val_every == 0:
            value = self.validation[cfg.val_episodes].error(self.pack.extract(k).to(self.device), self.task)
            s.history["val/iteration"].append(float(it))
            s.history["val/metric"].append(value)
            if self.on_validation is not None and self.on_validation(k, it, value):
                s.stopped_early = True
                log.info("seed %d stopped early at iteration %d (validation %.4g)", cfg.seed, it, value)
        if cfg.checkpoint_every and it % cfg.checkpoint_every == 0 and not s.stopped_early:
            self.save(k)
        if it >= cfg.iters or s.stopped_early:
            self.finish(k)


class _StateDict:
    """What checkpoint_payload reads of an optimiser: state_dict()."""

    def __init__(self, state: dict):
        self.state = state

    def state_dict(self) -> dict:
        return self.state
