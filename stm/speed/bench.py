"""Speed of the STM: training iterations and rollout throughput, side by side.

    python -m stm.speed.bench [--json] [--rounds 5] [--threads 1] [--sizes reacher pick-place] [--device cpu]

One training iteration = forward, loss, backward, Adam step, as stm.training.loop runs it (one model is a pack
of one), on a batch at the paper's sizes: pick-place (3x128 LSTM, 20 Gaussians, batch 32, 170 steps) and
reacher (3x64, 3 Gaussians, batch 32, 70 steps), with the task's state size.
Timed in the same run, interleaved round by round (the machine is shared, so medians of interleaved rounds
give fair ratios): teacher forcing (tf), auto-conditioning with u = v = 2 and u = v = 5, on the Python steps
(step_kernel "python": the reference and fallback), tf and u = v = 5 also on the C++ steps (*_cpp: the C++ steps,
stm.self_fed, and the fused NLL, stm.mdn_fused; the default's route where the extension builds), and a plain reference
(nn.LSTM + linear MDN head + mixture NLL + Adam with clipping, a dozen lines); and the same three schedules
for a pack of K = 3 models trained together (stm.packed): packed_speedup_* = (K x one model's ms/iter) / (the
pack's ms/iter), packed_speedup_ac the lower of the two auto-conditioned schedules';
window_speedup_packed_ac_u5v5 is a packed u = v = 5 iteration on the whole demos over one on windows of 40
steps after a 20-step burn-in (stm.training.windows); matmul_share_ac_u5v5 is the share of one model's a.c.
iteration spent in matrix products (torch.profiler; a lower bound) and packed_speedup_ceiling the most a pack
of K could then gain (Amdahl: products cost K-fold, the rest once); bf16_over_fp32: the tf and a.c. u = v = 5
iterations, single and packed, with bf16 matrix products (TrainConfig.matmul_dtype) over float32, timed in the same
rounds (the *_cpp ones: the C++ steps' bf16 products over their float32 ones); bf16_floor_ratio: ms per
model-iteration with bf16 products / its bf16 floor. The floor (stm.speed.floor): the FLOPs of one model's iteration
counted from the shapes (gflop_per_model_iter: the LSTM, the head, the feedback head's rows) at the core's peak GEMM
rate, measured in the same run on one large warm product in fp32 and bf16 (peak_gflops: 2048^3 on a CPU, the best
of a few); floor_ratio = ms per model-iteration / (FLOPs / fp32 peak). The products an fp32 iteration calls,
recorded and replayed alone on warm operands, timed in the same rounds: products_replayed_ms_per_model_iter, the
rate they reach (products_replayed_gflops) and products_ratio = ms per iteration / the replay's (what the rest of
the iteration costs on top of its own products). The training iterations run with subnormal
floats flushed to zero, as stm.training.loop trains; --weights CHECKPOINT also times a pack of a trained
checkpoint's copies with them flushed and kept (stm.speed.trained: on a peaked mixture head the difference is
large). The tip kinematics of the fed-back state (stm.fk) against
pytorch-kinematics, per call and in ATen calls. Then 1,000 reacher rollouts of 70 steps with FK grounding, and
3 models' rollouts batched (stm.rollout.generate of a pack) against one after the other, for 1,000 and for 34
episodes (an evaluation cell's).

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
from stm.packed import PackedSTM
from stm.rollout import generate
from stm.speed.bench_inputs import BenchTask, PlainMDN, bench_demos
from stm.speed.floor import PEAK_SIZE, iteration_flops, peak_gflops, product_flops, record_matmuls, replayer
from stm.speed.summary import summary
from stm.speed.trained import trained_weights_bench
from stm.training.batches import DemoTensors
from stm.training.loop import pack_iteration
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


def _iterations(task, demos, model_cfg: ModelConfig, k: int = PACK):
    """A factory: TrainConfig -> one training iteration of a pack of k models (seeds 0..k-1; one model is a pack of
    one) on the demos, as stm.training.loop runs it (stm.training.loop.pack_iteration)."""
    def make(cfg: TrainConfig):
        return pack_iteration(model_cfg, [dataclasses.replace(cfg, seed=seed) for seed in range(k)], task, demos,
                              device=_device)
    return make


# timed against their floors, their own products replayed beside them
FLOOR_CASES = ("tf", "tf_cpp", "ac_u5v5", "ac_u5v5_cpp", "packed_tf", "packed_tf_cpp", "packed_ac_u5v5",
               "packed_ac_u5v5_cpp")
BF16_CASES = FLOOR_CASES
FLOOR_SCHEDULES = ("tf", "ac_u5v5")
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


def _digits(x: float, n: int = 4) -> float:
    """x to n significant digits (a tiny test size's floor is a fraction of a millisecond)."""
    return float(f"{x:.{n}g}")


def _schedule(case: str) -> str:
    """The schedule a timed case runs ("packed_ac_u5v5_cpp" -> "ac_u5v5")."""
    return case.removeprefix("packed_").removesuffix("_cpp")


def training_bench(size: str, rounds: int, reps: int, peak: dict[str, float]) -> dict:
    """One size's training iterations, timed side by side; `peak`: the core's GEMM GFLOP/s per product dtype
    (fp32, bf16), measured in the same run, for the floors."""
    spec = SIZES[size]
    task = BenchTask(size, spec["gripper"])
    demos = bench_demos(spec["batch"], spec["steps"], spec["gripper"])
    data = DemoTensors.build(task, demos)
    stats = normalization_stats(data.states, torch.ones(data.states.shape[:2], dtype=torch.bool), task.layout)
    torch.manual_seed(0)
    model = STM(ModelConfig(hidden_size=spec["hidden"], num_layers=3, mixtures=spec["mixtures"]), task.layout, *stats)
    plain = PlainMDN(task.layout.dim, spec["hidden"], 3, spec["mixtures"]).to(_device)
    plain_opt = torch.optim.Adam(plain.parameters(), lr=1e-4)
    x, y = (model.normalize(s).to(_device) for s in (data.states[:, :-1], data.states[:, 1:]))
    cpp_ext.self_fed_extension()  # built (or loaded) before the timing

    def plain_step():
        loss = plain.loss(x, y)
        plain_opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(plain.parameters(), 1.0)  # like for like: the STM step clips too
        plain_opt.step()

    # *_cpp: step_kernel "cpp", the C++ self-fed segment (stm.self_fed) and the fused NLL (stm.mdn_fused)
    base = TrainConfig(batch_size=spec["batch"], step_kernel="python")
    schedules = {"tf": dataclasses.replace(base, v=0), "tf_cpp": dataclasses.replace(base, v=0, step_kernel="cpp"),
                 "ac_u2v2": dataclasses.replace(base, u=2, v=2), "ac_u5v5": dataclasses.replace(base, u=5, v=5),
                 "ac_u5v5_cpp": dataclasses.replace(base, u=5, v=5, step_kernel="cpp")}
    single, packed = _iterations(task, demos, model.config, k=1), _iterations(task, demos, model.config)
    window, burn_in = WINDOW
    cases = {"plain": plain_step, **{k: single(c) for k, c in schedules.items()},
             **{f"packed_{k}": packed(c) for k, c in schedules.items()},
             "packed_ac_u5v5_window": packed(dataclasses.replace(schedules["ac_u5v5"], window=window,
                                                                 burn_in=burn_in)),
             **{f"bf16_{k}": (packed if "packed" in k else single)(dataclasses.replace(
                 schedules[k.removeprefix("packed_")], matmul_dtype="bfloat16")) for k in BF16_CASES}}
    for fn in cases.values():  # warm-up
        fn()
    matmuls = {k: record_matmuls(cases[k]) for k in FLOOR_CASES}
    for k, calls in matmuls.items():  # the products replayed alone, warm, timed in the same rounds
        cases[f"products_{k}"] = replayer(calls, _device)
    med = interleaved_medians(cases, rounds, reps)
    per_model = {k: med[k] / (PACK if "packed" in k else 1) for k in med}  # replays too
    share = matmul_share(cases["ac_u5v5"])
    speedup = {k: round(PACK * med[k] / med[f"packed_{k}"], 3) for k in ("tf", "ac_u2v2", "ac_u5v5")}
    # the floor: each schedule's FLOPs per model-iteration at the core's peak rate, per product dtype
    flops = {s: iteration_flops(model.config, task.layout, schedules[s], spec["batch"], spec["steps"])
             for s in FLOOR_SCHEDULES}
    floor = {dt: {s: flops[s]["total"] / (peak[dt] * 1e9) for s in FLOOR_SCHEDULES} for dt in peak}
    return {
        "size": size, "state_dim": task.layout.dim, **{k: spec[k] for k in ("hidden", "mixtures", "batch", "steps")},
        "ms_per_iter": {k: _digits(v * 1e3) for k, v in med.items() if not k.startswith("products")},
        "ms_per_model_iter": {k: _digits(per_model[k] * 1e3) for k in FLOOR_CASES},
        "gflop_per_model_iter": {s: {part: _digits(n / 1e9) for part, n in f.items()} for s, f in flops.items()},
        "floor_ms_per_model_iter": {dt: {s: _digits(v * 1e3) for s, v in f.items()} for dt, f in floor.items()},
        # ms per model-iteration / (its FLOPs / the fp32 peak): 1 is every product at the core's best, nothing else
        "floor_ratio": {k: round(per_model[k] / floor["fp32"][_schedule(k)], 3) for k in FLOOR_CASES},
        # the iteration's own products replayed alone on warm operands (stm.speed.floor.replayer), per
        # model-iteration; the rate they reach; the iteration over them
        "products_replayed_ms_per_model_iter": {k: _digits(per_model[f"products_{k}"] * 1e3) for k in FLOOR_CASES},
        "products_replayed_gflops": {k: round(product_flops(c) / med[f"products_{k}"] / 1e9, 1)
                                     for k, c in matmuls.items()},
        "products_ratio": {k: round(med[k] / med[f"products_{k}"], 3) for k in FLOOR_CASES},
        "matmuls_per_iter": {k: len(v) for k, v in matmuls.items()},
        # TrainConfig.matmul_dtype "bfloat16": the same iteration's ms over float32's, timed in the same rounds
        "bf16_over_fp32": {k: round(med[f"bf16_{k}"] / med[k], 3) for k in BF16_CASES},
        # with bf16 products, per model-iteration and over their floor (the FLOPs at the bf16 peak)
        "bf16_ms_per_model_iter": {k: _digits(per_model[f"bf16_{k}"] * 1e3) for k in BF16_CASES},
        "bf16_floor_ratio": {k: round(per_model[f"bf16_{k}"] / floor["bf16"][_schedule(k)], 3) for k in BF16_CASES},
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
    generate(pack, task, episodes[:8])  # warm-up
    few = episodes[:EVAL_EPISODES]
    secs, separate, packed, separate_few, packed_few = [], [], [], [], []
    for _ in range(rounds):  # interleaved
        secs.append(_time_once(lambda: generate(model, task, episodes), 1))  # (generate's own .seconds is wall)
        separate.append(_time_once(lambda: [generate(m, task, episodes) for m in models], 1))
        packed.append(_time_once(lambda: generate(pack, task, episodes), 1))
        separate_few.append(_time_once(lambda: [generate(m, task, few) for m in models], 3))
        packed_few.append(_time_once(lambda: generate(pack, task, few), 3))
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
    peak = {name: peak_gflops(dt, _clock, _device) for name, dt in (("fp32", torch.float32), ("bf16", torch.bfloat16))}
    with subnormals_flushed():  # as stm.training.loop trains
        training = [training_bench(s, args.rounds, args.reps, peak) for s in args.sizes]
    result = {"torch": torch.__version__, "threads": torch.get_num_threads(), "cpus": os.cpu_count(),
              "clock": args.clock, "device": str(_device),
              "load_average_before": [round(x, 2) for x in load_before],
              # the core's rate on one large warm product (GFLOP per second of the clock): the floors' rate
              "peak_gflops": {**{k: round(v, 1) for k, v in peak.items()},
                              "size": PEAK_SIZE.get(_device.type, PEAK_SIZE["cpu"])},
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
