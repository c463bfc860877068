"""Speed of the STM: training iterations and rollout throughput, side by side.

    python -m stm.speed.bench [--json] [--rounds 5] [--threads 1] [--sizes reacher pick-place] [--device cpu]

One training iteration = forward, loss, backward, Adam step, as stm.training.loop runs it (one model is a pack
of one), on a batch at the paper's sizes: pick-place (3x128 LSTM, 20 Gaussians, batch 32, 170 steps) and
reacher (3x64, 3 Gaussians, batch 32, 70 steps), with the task's state size.
Timed in the same run, interleaved round by round (the machine is shared, so medians of interleaved rounds
give fair ratios): teacher forcing (tf), auto-conditioning with u = v = 2 and u = v = 5 (tf and u = v = 5 also
with step_kernel "cpp": the C++ self-fed segment, stm.self_fed, and the fused NLL, stm.mdn_fused: *_cpp), and a
plain reference
(nn.LSTM + linear MDN head + mixture NLL + Adam with clipping, a dozen lines); and the same three schedules
for a pack of K = 3 models trained together (stm.packed): packed_speedup_* = (K x one model's ms/iter) / (the
pack's ms/iter), packed_speedup_ac the lower of the two auto-conditioned schedules';
window_speedup_packed_ac_u5v5 is a packed u = v = 5 iteration on the whole demos over one on windows of 40
steps after a 20-step burn-in (stm.training.windows); matmul_share_ac_u5v5 is the share of one model's a.c.
iteration spent in matrix products (torch.profiler; a lower bound) and packed_speedup_ceiling the most a pack
of K could then gain (Amdahl: products cost K-fold, the rest once); bf16_over_fp32: the tf and a.c. u = v = 5
iterations, single and packed, with bf16 matrix products (TrainConfig.matmul_dtype) over float32, timed in the same
rounds (the *_cpp ones: the C++ steps' bf16 products over their float32 ones); bf16_floor_ratio: ms per
model-iteration with bf16 products / the float32 iteration's fp32 floor. The floor (stm.speed.floor): the matrix
products of one tf and one a.c. u = v = 5 iteration, single and packed, recorded and replayed alone in fp32 and in
bf16, timed in the same rounds; floor_ratio = ms per model-iteration / its fp32 floor; floor_ratio_warm the same
over the warm replay (operands in cache: a lower bound under the floor). The training iterations run with subnormal
floats flushed to zero, as stm.training.loop trains; --weights CHECKPOINT also times a pack of a trained
checkpoint's copies with them flushed and kept (stm.speed.trained: on a peaked mixture head the difference is
large). The tip kinematics of the fed-back state (stm.fk) against
pytorch-kinematics, per call and in ATen calls. Then 1,000 reacher rollouts of 70 steps with FK grounding, and
3 models' rollouts batched (stm.packed_rollout) against one after the other, for 1,000 and for 34 episodes (an
evaluation cell's).

Times are CPU seconds of this process by default (--clock cpu): on a shared machine, wall
time also counts the other processes' load. Ratios are what to read.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import time
from pathlib import Path

import numpy as np
import torch

from envs.robot import NEUTRAL_Q
from envs.tasks.base import Episode
from stm import cpp_ext
from stm.config import ModelConfig, TrainConfig
from stm.device import DeviceError, resolve_device
from stm.fk import default_tip_kinematics
from stm.model import STM, normalization_stats
from stm.packed import PackedAdam, PackedSTM, clip_per_model
from stm.packed_rollout import generate_packed
from stm.rollout import generate
from stm.speed.bench_inputs import BenchTask, PlainMDN, bench_demos
from stm.speed.floor import record_matmuls, replayer
from stm.speed.summary import summary
from stm.speed.trained import trained_weights_bench
from stm.training.autoconditioning import unroll
from stm.training.batches import DemoTensors
from stm.training.subnormals import subnormals_flushed

SIZES = {  # paper sizes: (hidden, mixtures, batch, steps, gripper)
    "pick-place": dict(hidden=128, mixtures=20, batch=32, steps=170, gripper=True),
    "reacher": dict(hidden=64, mixtures=3, batch=32, steps=70, gripper=False),
}


PACK = 3  # models per pack
WINDOW = (40, 20)  # windowed training's case: window, burn-in (steps)
EVAL_EPISODES = 34  # episodes a cell evaluates per seed: where batching the K models pays (1,000 are compute-bound)
CLOCKS = {"cpu": time.process_time, "wall": time.perf_counter}
_clock = CLOCKS["cpu"]
_device = torch.device("cpu")  # --device: where the training iterations, their floors and the rollouts run


def _time_once(fn, reps: int) -> float:
    start = _clock()
    for _ in range(reps):
        fn()
    if _device.type == "cuda":  # the kernels queued, done
        torch.cuda.synchronize(_device)
    return (_clock() - start) / reps


def interleaved_medians(cases: dict, rounds: int, reps: int) -> dict:
    """Each case's median seconds per call over `rounds` rounds, every round timing every case in turn (so a load
    change hits every case alike)."""
    times: dict = {k: [] for k in cases}
    for _ in range(rounds):
        for k, fn in cases.items():
            times[k].append(_time_once(fn, reps))
    return {k: statistics.median(v) for k, v in times.items()}


def _packed_step(task, stats, model_cfg: ModelConfig, batch, kin, k: int = PACK, state: dict | None = None):
    """A training-iteration factory for a pack of k models (each its own seed's init, or each a copy of the weights
    `state` (normalisation included); one model is a pack of one, as stm.training.loop trains it), every model on
    the same batch: unroll, per-model losses, backward, per-model clipping, Adam."""
    models = []
    for seed in range(k):
        torch.manual_seed(seed)
        if state is None:
            models.append(STM(model_cfg, task.layout, *stats))
        else:
            models.append(STM(model_cfg, task.layout))
            models[-1].load_state_dict(state)
    pack, batch, kin = PackedSTM.from_models(models).to(_device), batch.to(_device), kin.to(_device)
    params = list(pack.stacked)
    opt, clips, active = PackedAdam(params, [1e-4] * k), torch.ones(k), torch.arange(k)
    gens = [torch.Generator().manual_seed(seed) for seed in range(k)]
    states, q, psi, mask = (t.expand(k, *t.shape) for t in (batch.states, batch.q, batch.psi, batch.mask))
    burn = None if batch.burn is None else tuple(t.expand(k, *t.shape) for t in batch.burn)
    steps = [batch.mask.shape[1]] * k

    def make(cfg: TrainConfig):
        def step():
            view = pack.view()
            raw = unroll(view, states, q, psi, steps, task, cfg, kin, gens, burn)
            losses = view.losses(raw, view.normalize(states[:, :, 1:]), mask, cfg.step_kernel)
            for p in params:
                p.grad = None
            losses.sum().backward()
            clip_per_model(params, clips)
            opt.step(active)
        return step

    return make


# timed with their matrix-product floors
FLOOR_CASES = ("tf", "tf_cpp", "ac_u5v5", "ac_u5v5_cpp", "packed_tf", "packed_tf_cpp", "packed_ac_u5v5",
               "packed_ac_u5v5_cpp")
BF16_CASES = FLOOR_CASES
MATMULS = {"aten::addmm", "aten::mm", "aten::bmm", "aten::baddbmm"}


def _op_events(fn):
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        fn()
    return prof.key_averages()


def aten_calls(fn) -> int:
    """ATen calls of one call of fn, nested ones included (torch.profiler)."""
    return sum(e.count for e in _op_events(fn) if e.key.startswith("aten::"))


def matmul_share(fn) -> float:
    """The share of one call's op time spent in matrix products (torch.profiler, self CPU time). The
    profiler's per-op cost inflates the other ops, so this is a lower bound of the share."""
    events = _op_events(fn)
    total = sum(e.self_cpu_time_total for e in events)
    return sum(e.self_cpu_time_total for e in events if e.key in MATMULS) / total if total else float("nan")


def packing_ceiling(share: float, k: int) -> float:
    """Amdahl: the speedup of packing k models if everything but the matrix products (whose arithmetic
    grows k-fold, packed or not) cost nothing extra per model."""
    return 1.0 / (share + (1.0 - share) / k)


def training_bench(size: str, rounds: int, reps: int) -> dict:
    spec = SIZES[size]
    task = BenchTask(size, spec["gripper"])
    demos = bench_demos(spec["batch"], spec["steps"], spec["gripper"])
    data = DemoTensors.build(task, demos)
    valid = torch.ones(data.states.shape[:2], dtype=torch.bool)
    stats = normalization_stats(data.states, valid)
    kin = default_tip_kinematics(torch.float32)
    batch = data.batch(torch.arange(spec["batch"]))
    torch.manual_seed(0)
    model = STM(ModelConfig(hidden_size=spec["hidden"], num_layers=3, mixtures=spec["mixtures"]), task.layout, *stats)
    plain = PlainMDN(task.layout.dim, spec["hidden"], 3, spec["mixtures"]).to(_device)
    plain_opt = torch.optim.Adam(plain.parameters(), lr=1e-4)
    x, y = (model.normalize(s).to(_device) for s in (batch.states[:, :-1], batch.states[:, 1:]))
    stm_step = _packed_step(task, stats, model.config, batch, kin, k=1)  # one model: stm.training.loop's pack of one
    cpp_ext.self_fed_extension()  # built (or loaded) before the timing

    def plain_step():
        loss = plain.loss(x, y)
        plain_opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(plain.parameters(), 1.0)  # like for like: the STM step clips too
        plain_opt.step()

    # *_cpp: step_kernel "cpp", the C++ self-fed segment (stm.self_fed) and the fused NLL (stm.mdn_fused)
    schedules = {"tf": TrainConfig(v=0), "tf_cpp": TrainConfig(v=0, step_kernel="cpp"),
                 "ac_u2v2": TrainConfig(u=2, v=2), "ac_u5v5": TrainConfig(u=5, v=5),
                 "ac_u5v5_cpp": TrainConfig(u=5, v=5, step_kernel="cpp")}
    packed = _packed_step(task, stats, model.config, batch, kin)
    window, burn_in = WINDOW
    windows = data.windows(torch.arange(spec["batch"]), window, burn_in, torch.Generator().manual_seed(0))
    windowed = _packed_step(task, stats, model.config, data.window_batch(torch.arange(spec["batch"]), windows), kin)
    cases = {"plain": plain_step, **{k: stm_step(c) for k, c in schedules.items()},
             **{f"packed_{k}": packed(c) for k, c in schedules.items()},
             "packed_ac_u5v5_window": windowed(schedules["ac_u5v5"]),
             **{f"bf16_{k}": (packed if "packed" in k else stm_step)(dataclasses.replace(
                 schedules[k.removeprefix("packed_")], matmul_dtype="bfloat16")) for k in BF16_CASES}}
    for fn in cases.values():  # warm-up
        fn()
    matmuls = {k: record_matmuls(cases[k]) for k in FLOOR_CASES}
    for k, calls in matmuls.items():  # the floors, timed in the same rounds
        cases[f"floor_fp32_{k}"], cases[f"floor_bf16_{k}"] = replayer(calls, device=_device), \
            replayer(calls, torch.bfloat16, _device)
        cases[f"floor_warm_{k}"] = replayer(calls, device=_device, warm=True)
    med = interleaved_medians(cases, rounds, reps)
    per_model = {k: med[k] / (PACK if "packed" in k else 1) for k in med}  # floors too
    share = matmul_share(cases["ac_u5v5"])
    speedup = {k: round(PACK * med[k] / med[f"packed_{k}"], 3) for k in ("tf", "ac_u2v2", "ac_u5v5")}
    return {
        "size": size, "state_dim": task.layout.dim, **{k: spec[k] for k in ("hidden", "mixtures", "batch", "steps")},
        "ms_per_iter": {k: round(v * 1e3, 2) for k, v in med.items() if not k.startswith("floor")},
        # the floor: the same iteration's matrix products replayed alone (stm.speed.floor), per model-iteration
        # (a pack's divided by its K); floor_ratio = ms per model-iteration / the fp32 floor
        "ms_per_model_iter": {k: round(per_model[k] * 1e3, 2) for k in FLOOR_CASES},
        "floor_ms_per_model_iter": {k: {dt: round(per_model[f"floor_{dt}_{k}"] * 1e3, 2)
                                        for dt in ("fp32", "bf16", "warm")} for k in FLOOR_CASES},
        "floor_ratio": {k: round(med[k] / med[f"floor_fp32_{k}"], 3) for k in FLOOR_CASES},
        # against the warm replay (fp32, one operand per layout, in cache): the products at their best
        "floor_ratio_warm": {k: round(med[k] / med[f"floor_warm_{k}"], 3) for k in FLOOR_CASES},
        "bf16_floor_over_fp32_floor": {k: round(med[f"floor_bf16_{k}"] / med[f"floor_fp32_{k}"], 3)
                                       for k in FLOOR_CASES},
        "matmuls_per_iter": {k: len(v) for k, v in matmuls.items()},
        # TrainConfig.matmul_dtype "bfloat16": the same iteration's ms over float32's, timed in the same rounds
        "bf16_over_fp32": {k: round(med[f"bf16_{k}"] / med[k], 3) for k in BF16_CASES},
        # with bf16 products against the fp32 floor (the float32 iteration's products replayed alone)
        "bf16_ms_per_model_iter": {k: round(per_model[f"bf16_{k}"] * 1e3, 2) for k in BF16_CASES},
        "bf16_floor_ratio": {k: round(med[f"bf16_{k}"] / med[f"floor_fp32_{k}"], 3) for k in BF16_CASES},
        "aten_calls_per_iter": {k: aten_calls(cases[k]) for k in ("tf", "tf_cpp", "ac_u5v5", "ac_u5v5_cpp")},
        "ratio_ac_u2v2_over_tf": round(med["ac_u2v2"] / med["tf"], 3),
        "ratio_ac_u5v5_over_tf": round(med["ac_u5v5"] / med["tf"], 3),
        # step_kernel "cpp" (python where the extension cannot be built: cpp_kernel says which ran)
        "cpp_kernel": cpp_ext.self_fed_extension() is not None, "cpp_load_seconds": cpp_ext.load_seconds,
        "ratio_ac_u5v5_cpp_over_tf": round(med["ac_u5v5_cpp"] / med["tf"], 3),
        "packed_ratio_ac_u5v5_cpp_over_tf": round(med["packed_ac_u5v5_cpp"] / med["packed_tf"], 3),
        "speedup_cpp_tf": round(med["tf"] / med["tf_cpp"], 3),
        "speedup_cpp_packed_tf": round(med["packed_tf"] / med["packed_tf_cpp"], 3),
        "speedup_cpp_ac_u5v5": round(med["ac_u5v5"] / med["ac_u5v5_cpp"], 3),
        "speedup_cpp_packed_ac_u5v5": round(med["packed_ac_u5v5"] / med["packed_ac_u5v5_cpp"], 3),
        "ratio_tf_over_plain": round(med["tf"] / med["plain"], 3),
        "packed_k": PACK,
        **{f"packed_speedup_{k}": speedup[k] for k in ("tf", "ac_u2v2", "ac_u5v5")},
        "packed_speedup_ac": min(speedup["ac_u2v2"], speedup["ac_u5v5"]),
        # what packing could gain if only the matrix products' arithmetic grew K-fold (an upper bound)
        "matmul_share_ac_u5v5": round(share, 3),
        "packed_speedup_ceiling": round(packing_ceiling(share, PACK), 3),
        "packed_ratio_ac_u2v2_over_tf": round(med["packed_ac_u2v2"] / med["packed_tf"], 3),
        "packed_ratio_ac_u5v5_over_tf": round(med["packed_ac_u5v5"] / med["packed_tf"], 3),
        # windowed training (stm.training.windows): an iteration on windows of `window` steps after a burn-in, against
        # one on the whole demos (the paper's); how much it learns per iteration is the lever study's question
        "window": window, "burn_in": burn_in,
        "window_speedup_packed_ac_u5v5": round(med["packed_ac_u5v5"] / med["packed_ac_u5v5_window"], 3),
        # the clock's seconds per 1,000 auto-conditioned iterations of the whole pack (CPU seconds with --clock cpu)
        "packed_seconds_per_1000_ac_iters": {k: round(med[f"packed_{k}"] * 1e3, 1) for k in ("ac_u2v2", "ac_u5v5")},
    }


FK_BATCHES = {"train": SIZES["pick-place"]["batch"], "train_packed": PACK * SIZES["pick-place"]["batch"],
              "rollouts": 1000}  # the first two forward and backward, rollouts forward alone


def fk_bench(rounds: int) -> dict:
    """The fed-back state's tip position (stm.fk, closed form) against pytorch-kinematics (envs.kinematics):
    CPU microseconds and ATen calls per call, at one model's and a pack's training batch and a rollout batch."""
    fk = default_tip_kinematics(torch.float32)
    gen = torch.Generator().manual_seed(0)
    cases = {}
    for name, batch in FK_BATCHES.items():
        q = fk.kin.neutral + 0.2 * torch.randn(batch, 7, generator=gen)
        for impl, kin in (("closed_form", fk), ("pytorch_kinematics", fk.kin)):
            cases[name, impl] = _fk_call(kin, q, grad=name != "rollouts")
    times: dict[tuple, list[float]] = {k: [] for k in cases}
    for _ in range(rounds):
        for k, fn in cases.items():
            times[k].append(_time_once(fn, max(10, 6400 // FK_BATCHES[k[0]])))
    us = {k: statistics.median(v) * 1e6 for k, v in times.items()}
    impls = ("closed_form", "pytorch_kinematics")
    return {"batch": FK_BATCHES, "backward": {name: name != "rollouts" for name in FK_BATCHES},
            "us_per_call": {name: {i: round(us[name, i], 1) for i in impls} for name in FK_BATCHES},
            "aten_calls": {name: {i: aten_calls(cases[name, i]) for i in impls} for name in FK_BATCHES},
            "speedup_over_pytorch_kinematics": {name: round(us[name, impls[1]] / us[name, impls[0]], 2)
                                                for name in FK_BATCHES}}


def _fk_call(kin, q: torch.Tensor, grad: bool):
    q = q.detach().requires_grad_(grad)
    ones = torch.ones(q.shape[0], 3)

    def call():
        if grad:
            kin.tip_position(q).backward(ones)
        else:
            with torch.no_grad():
                kin.tip_position(q)
    call()  # warm-up
    return call


def rollout_bench(n: int = 1000, steps: int = 70, rounds: int = 3) -> dict:
    task = BenchTask("reacher", False)
    torch.manual_seed(0)
    demos = bench_demos(8, steps, False)
    data = DemoTensors.build(task, demos)
    stats = normalization_stats(data.states, torch.ones(data.states.shape[:2], dtype=torch.bool))
    model = STM(ModelConfig(hidden_size=64, num_layers=3, mixtures=3), task.layout, *stats).eval().to(_device)
    rng = np.random.default_rng(0)
    episodes = [Episode(q0=NEUTRAL_Q + rng.uniform(-0.2, 0.2, 7),
                        psi=np.repeat(rng.uniform([0.4, -0.2, 0.0], [0.8, 0.4, 0.2])[None], steps + 1, 0),
                        horizon=steps) for _ in range(n)]
    generate(model, task, episodes[:8])  # warm-up
    models = [model]
    for seed in range(1, PACK):
        torch.manual_seed(seed)
        models.append(STM(model.config, task.layout, *stats).eval().to(_device))
    pack = PackedSTM.from_models(models).to(_device)
    generate_packed(pack, task, episodes[:8])  # warm-up
    few = episodes[:EVAL_EPISODES]
    secs, separate, packed, separate_few, packed_few = [], [], [], [], []
    for _ in range(rounds):  # interleaved
        secs.append(_time_once(lambda: generate(model, task, episodes), 1))  # (generate's own .seconds is wall)
        separate.append(_time_once(lambda: [generate(m, task, episodes) for m in models], 1))
        packed.append(_time_once(lambda: generate_packed(pack, task, episodes), 1))
        separate_few.append(_time_once(lambda: [generate(m, task, few) for m in models], 3))
        packed_few.append(_time_once(lambda: generate_packed(pack, task, few), 3))
    return {"rollouts": n, "steps": steps, "fk_grounding": True, "seconds": round(statistics.median(secs), 3),
            "seconds_all": [round(s, 3) for s in secs], "packed_k": PACK,
            "packed_seconds": round(statistics.median(packed), 3),
            "separate_seconds": round(statistics.median(separate), 3),
            "packed_speedup": round(statistics.median(separate) / statistics.median(packed), 3),
            "eval_episodes": EVAL_EPISODES,
            "packed_speedup_eval_episodes": round(statistics.median(separate_few) / statistics.median(packed_few), 3)}


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description="STM speed: training iterations and rollouts, as ratios")
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument("--rounds", type=int, default=5)
    ap.add_argument("--reps", type=int, default=2, help="iterations per timed round")
    ap.add_argument("--threads", type=int, default=1, help="torch intra-op threads (0: leave torch's default)")
    ap.add_argument("--sizes", nargs="+", default=list(SIZES), choices=list(SIZES))
    ap.add_argument("--no-rollouts", action="store_true")
    ap.add_argument("--no-fk", action="store_true", help="skip the tip kinematics' timing")
    ap.add_argument("--clock", choices=list(CLOCKS), default="cpu",
                    help="cpu: this process's CPU time (default; steady on a shared machine); wall: elapsed time "
                         "(always, on a GPU)")
    ap.add_argument("--weights", type=Path, default=None, metavar="CHECKPOINT",
                    help="also time the training iteration on this training checkpoint's weights, subnormals "
                         "flushed and kept (stm.speed.trained)")
    ap.add_argument("--device", default="cpu", help="auto, cpu (default), cuda or cuda:N: where the training "
                    "iterations, their floors and the rollouts run (the tip kinematics' comparison: the CPU)")
    args = ap.parse_args(argv)
    global _clock, _device
    try:
        _device = resolve_device(args.device)
    except DeviceError as e:
        ap.error(str(e))
    if _device.type == "cuda":  # the host's CPU time leaves out the GPU's
        args.clock = "wall"
    _clock = CLOCKS[args.clock]
    if args.threads:
        torch.set_num_threads(args.threads)
    load_before = os.getloadavg()
    with subnormals_flushed():  # as stm.training.loop trains
        training = [training_bench(s, args.rounds, args.reps) for s in args.sizes]
    result = {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
              "clock": args.clock, "device": str(_device),
              "load_average_before": [round(x, 2) for x in load_before],
              "training": training}
    if args.weights is not None:
        result["trained_weights"] = trained_weights_bench(args.weights, args.rounds, args.reps)
    if not args.no_fk:
        result["fk"] = fk_bench(args.rounds)
    if not args.no_rollouts:
        result["rollouts"] = rollout_bench()
    result["load_average_after"] = [round(x, 2) for x in os.getloadavg()]
    if args.json:
        print(json.dumps(result, indent=1))
    else:
        print(summary(result))
    return result


if __name__ == "__main__":
    main()
