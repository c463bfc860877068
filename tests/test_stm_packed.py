"""Packed training (stm.training.loop.train_packed) trains each seed as stm.training.loop.train trains it alone
(a pack of one): same loss curve, weights and rollouts, for the four variants; a diverging seed leaves the pack
without disturbing the others; each seed checkpoints and resumes on its own.

Tolerances: a pack of K > 1 runs ground-truth chunks through its batched layer sequence where a pack
of one uses oneDNN's fused LSTM, and stacks K seeds' batches, so single ops differ in the last bit
(float32 rounding, ~1e-7 relative). Adam turns a relative
gradient difference into at most about the same relative difference of an update of size
lr, so after N steps weights differ by ~N * lr * 1e-6 at worst; measured: <= 1e-6 after 8
steps at lr 3e-3. Asserted: losses within 1e-5 (relative and absolute), weights within
2e-5 absolute, rollout joint angles within 1e-4 rad after 11 closed-loop steps. Different
seeds differ by > 1e-3, so the checks can fail."""

import math

import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.packed import PackedSTM
from stm.rollout import generate
from stm.training.checkpoint import load_checkpoint
from stm.training.loop import check_packable, train, train_packed
from stm.variants import VARIANTS

TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)
BASE = TrainConfig(iters=8, batch_size=4, lr=3e-3, u=2, v=2, log_every=0, checkpoint_every=0)
SEEDS = (0, 1, 2)
LOSS_TOL, WEIGHT_TOL, ROLLOUT_TOL = 1e-5, 2e-5, 1e-4


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    return task, task.demos(0)


def _configs(variant: str, **train_overrides):
    model, base = VARIANTS[variant].configs(TINY, TrainConfig.from_dict({**BASE.to_dict(), **train_overrides}))
    return model, [TrainConfig.from_dict({**base.to_dict(), "seed": s}) for s in SEEDS]


def _max_weight_diff(a, b) -> float:
    sa, sb = a.state_dict(), b.state_dict()
    assert sa.keys() == sb.keys()
    return max((sa[k] - sb[k]).abs().max().item() for k in sa)


def _assert_same_run(single, packed):
    np.testing.assert_allclose(packed.history["train/loss"], single.history["train/loss"], rtol=LOSS_TOL,
                               atol=LOSS_TOL)
    np.testing.assert_allclose(packed.history["train/grad_norm"], single.history["train/grad_norm"], rtol=1e-4)
    assert packed.iterations == single.iterations
    assert _max_weight_diff(packed.model, single.model) < WEIGHT_TOL


@pytest.mark.parametrize("variant,extra", [
    ("lstm", {}), ("ac-lstm", {"tf_warmup": 2}), ("lstm-mdn", {}), ("ac-lstm-mdn", {"tf_warmup": 2}),
    ("ac-lstm-mdn", {"feedback": "sample", "input_noise": 0.1}),  # each seed's own random stream
    ("ac-lstm-mdn", {"u": 3, "v": 2, "grad_clip": 0.05}),  # layer-sequence chunks; clipping active
    ("ac-lstm", {"hold_steps": 3}),  # the pack trains the held demos too
    ("ac-lstm-mdn", {"window": 5, "burn_in": 3}),  # each seed's own windows, warmed up by their burn-in
    ("lstm", {"window": 4, "burn_in": 2}),  # teacher forcing from a burnt-in state
], ids=["lstm", "ac-lstm", "lstm-mdn", "ac-lstm-mdn", "ac-lstm-mdn-sample-noise", "ac-lstm-mdn-u3-clipped",
        "ac-lstm-hold", "ac-lstm-mdn-windows", "lstm-windows"])
def test_packed_training_equals_separate_training(toy, variant, extra):
    task, demos = toy
    model_cfg, cfgs = _configs(variant, **extra)
    singles = [train(model_cfg, c, task, demos) for c in cfgs]
    packed = train_packed(model_cfg, cfgs, task, demos)
    for s, p in zip(singles, packed, strict=True):
        assert p.failure is None
        _assert_same_run(s, p)
    assert _max_weight_diff(packed[0].model, packed[1].model) > 1e-3  # seeds differ: the checks can fail
    # rollouts of the K models batched equal each model's own rollouts
    episodes = task.episodes(5, 7)
    mode = "sample" if extra.get("feedback") == "sample" else "component_mean"
    batched = generate([p.model for p in packed], task, episodes, feedback=mode, seed=3)
    for s, ro in zip(singles, batched, strict=True):
        alone = generate(s.model, task, episodes, feedback=mode, seed=3)
        np.testing.assert_allclose(ro.q, alone.q, atol=ROLLOUT_TOL, rtol=0)
        np.testing.assert_array_equal(ro.grip, alone.grip)


def test_seeds_at_different_schedule_positions(toy):
    """Per-seed tf_warmup, (u, v), iters, lr and clipping: seeds in different schedule groups,
    finishing at different iterations, train as alone."""
    task, demos = toy
    model_cfg, cfgs = _configs("ac-lstm-mdn")
    cfgs = [TrainConfig.from_dict({**c.to_dict(), **o}) for c, o in
            zip(cfgs, [{"tf_warmup": 0, "lr": 1e-2}, {"tf_warmup": 5, "grad_clip": 0.05}, {"u": 1, "v": 3, "iters": 5}],
                strict=True)]
    packed = train_packed(model_cfg, cfgs, task, demos)
    for c, p in zip(cfgs, packed, strict=True):
        _assert_same_run(train(model_cfg, c, task, demos), p)


def test_a_diverging_seed_leaves_the_pack_and_the_others_go_on(toy, tmp_path, monkeypatch):
    task, demos = toy
    model_cfg, cfgs = _configs("ac-lstm-mdn", checkpoint_every=2)
    holder = {}
    original = PackedSTM.from_models

    def capture(models):
        holder["pack"] = original(models)
        return holder["pack"]

    monkeypatch.setattr(PackedSTM, "from_models", staticmethod(capture))

    def sabotage(k, iteration, metrics):
        if k == 1 and iteration == 5:  # poison seed 1's weights: its iteration 6 computes a NaN loss
            with torch.no_grad():
                for p in holder["pack"].stacked:
                    p[1].fill_(math.nan)

    cfgs = [TrainConfig.from_dict({**c.to_dict(), "log_every": 1}) for c in cfgs]
    paths = [tmp_path / f"s{s}.pt" for s in SEEDS]
    packed = train_packed(model_cfg, cfgs, task, demos, checkpoint_paths=paths, on_metrics=sabotage)
    bad = packed[1]
    assert bad.failure is not None and bad.failure.iteration == 6 and "non-finite loss" in str(bad.failure)
    assert bad.iterations == 5 and len(bad.history["train/loss"]) == 5
    ckpt = load_checkpoint(paths[1])  # the last good one
    assert ckpt["iteration"] == 4 and all(torch.isfinite(t).all() for t in ckpt["model"].values())
    for k in (0, 2):  # the others as if trained alone
        assert packed[k].failure is None
        _assert_same_run(train(model_cfg, cfgs[k], task, demos), packed[k])
        assert load_checkpoint(paths[k])["iteration"] == 8


def test_each_seed_checkpoints_and_resumes_on_its_own(toy, tmp_path):
    task, demos = toy
    model_cfg, cfgs = _configs("ac-lstm-mdn", checkpoint_every=3, feedback="sample")
    paths = [tmp_path / f"s{s}.pt" for s in SEEDS]
    full = train_packed(model_cfg, cfgs, task, demos)
    # seed 0 stopped after 3 iterations by a packed job, seed 1 after 5 by a single-model job, seed 2 never ran
    train_packed(model_cfg, [TrainConfig.from_dict({**cfgs[0].to_dict(), "iters": 3})], task, demos,
                 checkpoint_paths=paths[:1])
    train(model_cfg, TrainConfig.from_dict({**cfgs[1].to_dict(), "iters": 5}), task, demos, checkpoint_path=paths[1])
    seen = []
    resumed = train_packed(model_cfg, cfgs, task, demos, checkpoint_paths=paths,
                           on_checkpoint=lambda k, path, it: seen.append((k, it)))
    assert sorted(seen) == [(0, 6), (0, 8), (1, 6), (1, 8), (2, 3), (2, 6), (2, 8)]
    for f, r in zip(full, resumed, strict=True):
        _assert_same_run(f, r)
    # a packed checkpoint is an ordinary one: the single trainer resumes it
    alone = train(model_cfg, TrainConfig.from_dict({**cfgs[2].to_dict(), "iters": 10}), task, demos,
                  checkpoint_path=paths[2])
    ref = train(model_cfg, TrainConfig.from_dict({**cfgs[2].to_dict(), "iters": 10}), task, demos)
    _assert_same_run(ref, alone)


def test_validation_stops_one_seed_early(toy):
    task, demos = toy
    model_cfg, cfgs = _configs("ac-lstm-mdn", val_every=2, val_episodes=2)
    calls = []
    packed = train_packed(model_cfg, cfgs, task, demos,
                          on_validation=lambda k, it, value: calls.append((k, it)) or (k == 0 and it >= 4))
    assert [p.iterations for p in packed] == [4, 8, 8] and packed[0].stopped_early
    assert sorted(calls) == sorted([(0, 2), (0, 4)] + [(k, it) for k in (1, 2) for it in (2, 4, 6, 8)])
    assert len(packed[1].history["val/metric"]) == 4


def test_unpackable_configs_are_refused():
    with pytest.raises(ValueError, match="share one model config"):
        check_packable([TINY, ModelConfig(hidden_size=7)], [BASE, BASE])
    with pytest.raises(ValueError, match="differ in feedback"):
        check_packable([TINY, TINY], [BASE, TrainConfig.from_dict({**BASE.to_dict(), "feedback": "sample"})])
    check_packable([TINY, TINY], [BASE, TrainConfig.from_dict({**BASE.to_dict(), "seed": 4, "lr": 1e-2})])


def test_bench_reports_packed_speedups(monkeypatch, capsys):
    """`python -m stm.speed.bench --json` gives each training entry packed_k and the packed speedups,
    (K x one model's ms/iter) / (the pack's ms/iter), here at a tiny size (the numbers are not checked)."""
    from stm.speed import bench

    monkeypatch.setitem(bench.SIZES, "reacher", dict(hidden=8, mixtures=2, batch=4, steps=6, gripper=False))
    out = bench.main(["--json", "--sizes", "reacher", "--rounds", "1", "--reps", "1", "--no-rollouts"])
    entry = out["training"][0]
    assert out["device"] == "cpu"
    ms = entry["ms_per_iter"]
    assert entry["size"] == "reacher" and entry["packed_k"] == 3
    for k in ("tf", "ac_u2v2", "ac_u5v5"):
        assert entry[f"packed_speedup_{k}"] == pytest.approx(3 * ms[k] / ms[f"packed_{k}"], rel=0.02)
    assert entry["packed_speedup_ac"] == min(entry["packed_speedup_ac_u2v2"], entry["packed_speedup_ac_u5v5"])
    share = entry["matmul_share_ac_u5v5"]
    assert 0 < share < 1 and entry["packed_speedup_ceiling"] == pytest.approx(1 / (share + (1 - share) / 3), rel=0.01)
    assert entry["window_speedup_packed_ac_u5v5"] == pytest.approx(ms["packed_ac_u5v5"] / ms["packed_ac_u5v5_window"],
                                                                   rel=0.02)
    # the floor: the FLOPs counted from the shapes at the peak GEMM rate measured in the same run
    peak = out["peak_gflops"]
    assert peak["fp32"] > 0 and peak["bf16"] > 0 and peak["size"] == 2048
    for k in ("tf", "ac_u5v5", "packed_tf", "packed_ac_u5v5", "ac_u5v5_cpp", "packed_ac_u5v5_cpp"):
        per_model = ms[k] / (3 if k.startswith("packed") else 1)
        assert entry["ms_per_model_iter"][k] == pytest.approx(per_model, rel=0.02)
        schedule = "tf" if "tf" in k else "ac_u5v5"
        gflop = entry["gflop_per_model_iter"][schedule]["total"]
        floor = {dt: entry["floor_ms_per_model_iter"][dt][schedule] for dt in ("fp32", "bf16")}
        assert floor["fp32"] == pytest.approx(gflop / peak["fp32"] * 1e3, rel=0.01)
        assert floor["bf16"] == pytest.approx(gflop / peak["bf16"] * 1e3, rel=0.01)
        assert entry["floor_ratio"][k] == pytest.approx(per_model / (gflop / peak["fp32"] * 1e3), rel=0.05)
        assert entry["bf16_floor_ratio"][k] == pytest.approx(entry["bf16_ms_per_model_iter"][k]
                                                             / (gflop / peak["bf16"] * 1e3), rel=0.05)
        assert entry["matmuls_per_iter"][k] > 0 and entry["products_replayed_gflops"][k] > 0
        assert entry["products_ratio"][k] == pytest.approx(
            per_model / entry["products_replayed_ms_per_model_iter"][k], rel=0.05)
        assert entry["bf16_over_fp32"][k] == pytest.approx(ms[f"bf16_{k}"] / ms[k], rel=0.02)
    parts = entry["gflop_per_model_iter"]["ac_u5v5"]
    assert parts["feedback"] > 0 == entry["gflop_per_model_iter"]["tf"]["feedback"]
    assert parts["total"] == pytest.approx(parts["lstm"] + parts["head"] + parts["feedback"], rel=1e-3)
    assert entry["aten_calls_per_iter"]["ac_u5v5"] > entry["aten_calls_per_iter"]["tf"] > 0
    fk = out["fk"]
    assert set(fk["us_per_call"]) == set(fk["aten_calls"]) == {"train", "train_packed", "rollouts"}
    assert all(c["closed_form"] < c["pytorch_kinematics"] for c in fk["aten_calls"].values())
    assert '"packed_speedup_ac"' in capsys.readouterr().out


def test_matmul_share_tells_products_from_elementwise_ops():
    from stm.speed.bench import matmul_share, packing_ceiling

    a, b = torch.randn(256, 256), torch.randn(256, 256)
    assert matmul_share(lambda: [a @ b for _ in range(5)]) > 0.95
    assert matmul_share(lambda: [torch.sigmoid(a) * b for _ in range(5)]) == 0.0
    assert packing_ceiling(0.0, 3) == pytest.approx(3.0) and packing_ceiling(1.0, 3) == pytest.approx(1.0)
    assert packing_ceiling(0.5, 3) == pytest.approx(1.5)


def test_ctrl_c_mid_step_checkpoints_every_seed_there_and_a_resume_matches(
    toy, tmp_path, monkeypatch, sigint_raises
):
    """A Ctrl-C during iteration 5's unroll: the pack finishes that step, checkpoints each seed at 5 (the periodic
    ones are at 3, 6, ...) and passes the interrupt on; resuming gives the uninterrupted run."""
    import signal
    import threading

    import stm.training.loop

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
    task, demos = toy
    model_cfg, cfgs = _configs("ac-lstm-mdn", checkpoint_every=3, feedback="sample")
    paths = [tmp_path / f"s{s}.pt" for s in SEEDS]
    full = train_packed(model_cfg, cfgs, task, demos)
    real, calls = stm.training.loop.unroll, []

    def unroll_then_ctrl_c(*args, **kwargs):
        calls.append(1)
        out = real(*args, **kwargs)
        if len(calls) == 5:  # every seed at one schedule step: one unroll per iteration
            signal.raise_signal(signal.SIGINT)
        return out

    monkeypatch.setattr(stm.training.loop, "unroll", unroll_then_ctrl_c)
    seen = []
    with pytest.raises(KeyboardInterrupt):
        train_packed(model_cfg, cfgs, task, demos, checkpoint_paths=paths,
                     on_checkpoint=lambda k, path, it: seen.append((k, it)))
    assert sorted(seen) == sorted((k, it) for k in range(len(SEEDS)) for it in (3, 5))
    monkeypatch.undo()
    resumed = train_packed(model_cfg, cfgs, task, demos, checkpoint_paths=paths)
    for f, r in zip(full, resumed, strict=True):
        _assert_same_run(f, r)
