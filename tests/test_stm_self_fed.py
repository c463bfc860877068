"""The C++ kernels of TrainConfig.step_kernel = "cpp", the self-fed segment (stm.self_fed) and the fused mixture NLL
of the loss (stm.mdn_fused), against the Python steps and stm.mdn's NLL they replace (the reference, itself held to a
plain step-by-step unroll in tests/test_stm_speed_equivalence.py).

Tolerances: the self-fed steps compute what the Python steps' ATen calls compute, in the same order; the ground-truth
chunks run as a layer sequence where a single model's Python path calls oneDNN's fused layer, and the backward
sums a few gradient contributions in another order (the feedback head's weight gradient: one product per segment
instead of one per step), so results differ by float32 rounding: measured, losses within 1e-7 relative and
gradients within 4e-7 of each parameter's largest (on a Xeon; 1.01e-6 on an AMD EPYC, in the teacher-forced
pack with the fused NLL); asserted 1e-6 for losses and 2e-6, the fused NLL's own rounding, for gradients. The
fused NLL rounds differently from
stm.mdn's dozen ATen calls (tests/test_stm_mdn_fused.py: per element within 6e-7, gradients within 2e-6 of
the largest): the same loss and gradient tolerances hold with it, teacher-forced (no self-fed steps: the NLL is the
only difference; the deterministic head has none, asserted bitwise equal) and auto-conditioned. After N Adam steps
at lr the weights differ by up to ~N * lr * (a gradient's rounding over its own size): Adam divides each element's
gradient by its own running scale, so an element whose gradient is small next to its tensor's largest moves its
rounding up. Measured after 8 steps at lr 3e-3: 7.6e-7 with the segment alone, 1.7e-6 with the fused NLL as well
(one element of a recurrent weight of the auto-conditioned MDN); asserted 3e-6.
With bf16 products (TrainConfig.matmul_dtype) the C++ route is held to the Python bf16 path: both round the
products' operands to bf16, but not alike (the C++ products keep float32 outputs and biases where ATen's bf16
products round them, and one model's ground-truth chunks run bf16 products where the Python path's fused layer runs
float32), so the two differ by bf16's rounding, as much as either differs from float32: measured, losses within
7e-5 relative and each parameter's gradient within 4.3e-3 of its norm (per model); asserted 5e-4 (as
tests/test_stm_bf16.py) and 2e-2. That the bf16 products ran: the gradients differ from the C++ float32 path's by
more than 2e-4 of their norm (measured at least 1.7e-3; the float32 paths agree within 1e-6).
Skipped where the extension cannot be built (stm.cpp_ext warns and the Python path runs), unless ACRMDN_REQUIRE_CPP
is set (the nox tests session, CI): there they fail."""

import dataclasses

import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm import cpp_ext, mdn_fused, self_fed
from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.model import STM, normalization_stats
from stm.packed import PackedSTM
from stm.training import autoconditioning
from stm.training.autoconditioning import unroll
from stm.training.batches import DemoTensors
from stm.training.loop import train, train_packed
from stm.variants import VARIANTS

KIN = default_tip_kinematics(torch.float32)
LOSS_RTOL, GRAD_TOL, WEIGHT_TOL = 1e-6, 2e-6, 3e-6
BF16_LOSS_RTOL, BF16_GRAD_RTOL, BF16_SHOWS = 5e-4, 2e-2, 2e-4

needs_extension = pytest.mark.skipif(not cpp_ext.required() and cpp_ext.self_fed_extension() is None,
                                     reason="the C++ extension cannot be built here")


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=9, max_steps=13, gripper=True)
    return task, DemoTensors.build(task, task.demos(0))


def _pack(task, data, model_cfg: ModelConfig, phi_mode: str, k: int) -> PackedSTM:
    valid = torch.arange(data.states.shape[1])[None] <= data.lengths[:, None]
    stats = normalization_stats(data.states, valid)
    models = []
    for seed in range(k):
        torch.manual_seed(seed)
        models.append(STM(model_cfg, task.layout, *stats, phi_mode=phi_mode))
    return PackedSTM.from_models(models)


def _loss_and_grads(pack: PackedSTM, batch, task, cfg: TrainConfig):
    K = pack.K
    states, q, psi, mask = (t.expand(K, *t.shape) for t in (batch.states, batch.q, batch.psi, batch.mask))
    burn = None if batch.burn is None else tuple(t.expand(K, *t.shape) for t in batch.burn)
    view = pack.view()
    gens = [torch.Generator().manual_seed(3 + k) for k in range(K)]
    raw = unroll(view, states, q, psi, [mask.shape[-1]] * K, task, cfg, KIN, gens, burn)
    losses = view.losses(raw, view.normalize(states[:, :, 1:]), mask, cfg.step_kernel)
    return losses.detach(), torch.autograd.grad(losses.sum(), list(pack.stacked))


CASES = {  # (model config overrides, train config, models per pack)
    "component_mean_u2v2": ({}, TrainConfig(u=2, v=2), 1),  # stepped ground-truth chunks
    "component_mean_u3v2": ({}, TrainConfig(u=3, v=2), 1),  # fused ground-truth chunks
    "u1v4_packed": ({}, TrainConfig(u=1, v=4), 3),  # a pack: batched layer sequences between segments
    "free_phi": ({}, TrainConfig(u=2, v=3, phi_mode="free"), 1),
    "detached": ({}, TrainConfig(u=2, v=2, detach_feedback=True), 2),
    "input_noise": ({}, TrainConfig(u=2, v=2, input_noise=0.1), 1),
    "deterministic_head": ({"head": "deterministic"}, TrainConfig(u=2, v=3), 2),
    "no_gripper_layers_2": ({"num_layers": 2}, TrainConfig(u=3, v=3), 1),
    "mixture_mean_falls_back": ({}, TrainConfig(u=1, v=3, feedback="mixture_mean"), 1),
    "sample_falls_back": ({}, TrainConfig(u=2, v=3, feedback="sample", temperature=0.5), 1),
    "teacher_forced": ({}, TrainConfig(v=0), 1),  # no self-fed steps: the fused NLL alone
    "teacher_forced_packed": ({}, TrainConfig(v=0), 3),
}


@needs_extension
@pytest.mark.parametrize("case", list(CASES))
def test_cpp_segment_matches_python_steps(toy, case, monkeypatch):
    task, data = toy
    made = []
    monkeypatch.setattr(autoconditioning, "cpp_steps", lambda *a, **kw: made.append(self_fed.cpp_steps(*a, **kw))
                        or made[-1])
    overrides, cfg, k = CASES[case]
    if case == "no_gripper_layers_2":
        task = ToyReach(n_demos=6, min_steps=9, max_steps=13, gripper=False)
        data = DemoTensors.build(task, task.demos(0))
    pack = _pack(task, data, ModelConfig(**{"hidden_size": 16, "num_layers": 3, "mixtures": 3, **overrides}),
                 cfg.phi_mode, k)
    batch = data.batch(torch.arange(len(data.lengths)))
    ref_loss, ref_grads = _loss_and_grads(pack, batch, task, dataclasses.replace(cfg, step_kernel="python"))
    loss, grads = _loss_and_grads(pack, batch, task, dataclasses.replace(cfg, step_kernel="cpp"))
    if cfg.v == 0:
        assert made == []  # teacher forcing: no self-fed steps to run
    else:  # the C++ steps ran where they apply, with float32 products
        assert made[0] is None and (made[1] is None) == case.endswith("falls_back")
        assert made[1] is None or made[1].low_fb == []
    torch.testing.assert_close(loss, ref_loss, rtol=LOSS_RTOL, atol=0)
    for name, g, g_ref in zip(pack.names, grads, ref_grads, strict=True):
        scale = g_ref.abs().max().clamp_min(1e-3)
        torch.testing.assert_close(g / scale, g_ref / scale, rtol=0, atol=GRAD_TOL, msg=lambda m, n=name: f"{n}: {m}")


@needs_extension
def test_cpp_segment_runs_where_it_applies(toy):
    task, _ = toy
    view = _pack(task, toy[1], ModelConfig(hidden_size=8, mixtures=2), "grounded", 1).view()
    assert self_fed.supported(view, TrainConfig(step_kernel="cpp"))
    assert self_fed.supported(view, TrainConfig())  # auto, the default: where the extension builds
    assert not self_fed.supported(view, TrainConfig(step_kernel="python"))
    assert not self_fed.supported(_pack(task, toy[1], ModelConfig(hidden_size=8, mixtures=2), "grounded", 1)
                                  .to("meta").view(), TrainConfig())  # off the CPU: the Python steps
    assert not self_fed.supported(view, TrainConfig(step_kernel="cpp", v=0))  # teacher forcing: no self-fed steps
    assert not self_fed.supported(view, TrainConfig(step_kernel="cpp", feedback="mixture_mean"))
    assert not self_fed.supported(view, TrainConfig(step_kernel="cpp"), return_inputs=True)
    assert self_fed.supported(view, TrainConfig(step_kernel="cpp", matmul_dtype="bfloat16"))


BF16_CASES = {  # (model config overrides, train config, models per pack)
    "mdn": ({}, TrainConfig(u=2, v=3), 1),
    "mdn_packed": ({}, TrainConfig(u=3, v=2), 3),
    "deterministic_head": ({"head": "deterministic"}, TrainConfig(u=2, v=3), 1),
    "deterministic_head_packed": ({"head": "deterministic"}, TrainConfig(u=3, v=2), 3),
}


def _relative(g: torch.Tensor, g_ref: torch.Tensor) -> float:
    return ((g - g_ref).norm() / g_ref.norm()).item()


@needs_extension
@pytest.mark.parametrize("case", list(BF16_CASES))
def test_cpp_bf16_products_match_the_python_bf16_path(toy, case, monkeypatch):
    task, data = toy
    made = []
    monkeypatch.setattr(autoconditioning, "cpp_steps", lambda *a, **kw: made.append(self_fed.cpp_steps(*a, **kw))
                        or made[-1])
    overrides, cfg, k = BF16_CASES[case]
    pack = _pack(task, data, ModelConfig(**{"hidden_size": 16, "num_layers": 3, "mixtures": 3, **overrides}),
                 cfg.phi_mode, k)
    batch = data.batch(torch.arange(len(data.lengths)))
    bf16 = dataclasses.replace(cfg, matmul_dtype="bfloat16")
    ref_loss, ref_grads = _loss_and_grads(pack, batch, task, dataclasses.replace(bf16, step_kernel="python"))
    loss, grads = _loss_and_grads(pack, batch, task, dataclasses.replace(bf16, step_kernel="cpp"))
    assert made[0] is None and made[1] is not None  # the C++ steps ran
    assert [w.dtype for w in made[1].low_fb] == [torch.bfloat16] * 4  # the head's rows and 3 layers, cast once
    _, fp32_grads = _loss_and_grads(pack, batch, task, dataclasses.replace(cfg, step_kernel="cpp"))
    torch.testing.assert_close(loss, ref_loss, rtol=BF16_LOSS_RTOL, atol=0)
    for name, g, g_ref in zip(pack.names, grads, ref_grads, strict=True):
        for j in range(k):
            assert _relative(g[j], g_ref[j]) < BF16_GRAD_RTOL, f"{name} of model {j}"
    for j in range(k):  # the bf16 products ran: their rounding shows
        flat = [torch.cat([g[j].flatten() for g in gs]) for gs in (grads, fp32_grads)]
        assert _relative(*flat) > BF16_SHOWS


class _AutogradSums(self_fed._GradSums):
    """Each node hands autograd its own weight gradients, which autograd sums (the sums in place undone)."""

    def hand(self, first, dw, db):
        return self_fed._interleave(dw, db)


SUM_CASES = {  # (train config, models per pack)
    "u2v2": (TrainConfig(u=2, v=2), 1),
    "u1v4_packed": (TrainConfig(u=1, v=4), 3),
    "bf16_packed": (TrainConfig(u=3, v=2, matmul_dtype="bfloat16"), 2),
    "detached": (TrainConfig(u=2, v=3, detach_feedback=True), 1),
}


@needs_extension
@pytest.mark.parametrize("case", list(SUM_CASES))
def test_weight_gradients_summed_in_place_match_autograds_sum(toy, case, monkeypatch):
    """The LSTM weight gradients of the C++ nodes, summed in place and handed to autograd by the unroll's first node
    (stm.self_fed._GradSums), are those autograd sums from each node's own: within float32 rounding (the products'
    sums in another order; bf16 products too: they add in float32), and only the first node hands them."""
    task, data = toy
    cfg, k = SUM_CASES[case]
    cfg = dataclasses.replace(cfg, step_kernel="cpp")
    pack = _pack(task, data, ModelConfig(hidden_size=16, num_layers=3, mixtures=3), cfg.phi_mode, k)
    batch = data.batch(torch.arange(len(data.lengths)))
    handed = []
    hand = self_fed._GradSums.hand
    monkeypatch.setattr(self_fed._GradSums, "hand", lambda self, first, dw, db: handed.append(first)
                        or hand(self, first, dw, db))
    loss, grads = _loss_and_grads(pack, batch, task, cfg)
    assert len(handed) > 2 and handed[-1] and not any(handed[:-1])  # the first node's backward ran last
    monkeypatch.setattr(self_fed, "_GradSums", _AutogradSums)
    ref_loss, ref_grads = _loss_and_grads(pack, batch, task, cfg)
    assert torch.equal(loss, ref_loss)
    for name, g, g_ref in zip(pack.names, grads, ref_grads, strict=True):
        scale = g_ref.abs().max().clamp_min(1e-3)
        torch.testing.assert_close(g / scale, g_ref / scale, rtol=0, atol=GRAD_TOL, msg=lambda m, n=name: f"{n}: {m}")


def test_a_phi_not_linear_in_the_tip_falls_back(toy):
    task, data = toy
    psi = data.batch(torch.arange(2)).psi.unsqueeze(0)
    assert torch.equal(self_fed._phi_offset(task, psi, torch.float32), -psi)

    class Squared(ToyReach):
        def phi(self, tip_pos, psi):
            return tip_pos * tip_pos - psi

    assert self_fed._phi_offset(Squared(), psi, torch.float32) is None


def test_without_the_extension_auto_runs_the_python_steps_and_cpp_refuses(toy, monkeypatch):
    task, data = toy
    for module in (cpp_ext, self_fed, mdn_fused):
        monkeypatch.setattr(module, "self_fed_extension", lambda: None)
    pack = _pack(task, data, ModelConfig(hidden_size=8, mixtures=2), "grounded", 1)
    batch = data.batch(torch.arange(3))
    for cfg in (TrainConfig(u=2, v=2, step_kernel="python"), TrainConfig(v=0, step_kernel="python")):
        ref = _loss_and_grads(pack, batch, task, cfg)
        got = _loss_and_grads(pack, batch, task, dataclasses.replace(cfg, step_kernel="auto"))
        assert torch.equal(got[0], ref[0]) and all(torch.equal(a, b) for a, b in zip(got[1], ref[1], strict=True))
        with pytest.raises(RuntimeError, match="step_kernel=cpp, but the C\\+\\+ extension cannot be built"):
            _loss_and_grads(pack, batch, task, dataclasses.replace(cfg, step_kernel="cpp"))
    assert cpp_ext.step_kernel("auto") == "python"


def test_the_kernel_that_runs():
    """auto is cpp where the extension builds; python as asked; off the CPU the Python steps run."""
    built = cpp_ext.self_fed_extension() is not None
    assert cpp_ext.step_kernel("auto") == ("cpp" if built else "python")
    assert cpp_ext.step_kernel("python") == "python"
    assert cpp_ext.step_kernel("auto", "cuda") == cpp_ext.step_kernel("cpp", "cuda") == "python"


def test_the_extension_builds_where_it_is_required(monkeypatch):
    """ACRMDN_REQUIRE_CPP (set by the nox tests session, so CI) turns a failed build into a failure instead of the
    C++ tests' skips; where it is set, the extension must load here."""
    if cpp_ext.required():
        assert cpp_ext.self_fed_extension() is not None
    monkeypatch.setenv(cpp_ext.REQUIRE, "0")
    assert not cpp_ext.required()
    monkeypatch.setenv(cpp_ext.REQUIRE, "1")
    assert cpp_ext.required()


TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)
BASE = TrainConfig(iters=8, batch_size=4, lr=3e-3, u=2, v=2, log_every=0, checkpoint_every=0, step_kernel="python")


@needs_extension
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_training_with_the_cpp_kernel_matches(toy, variant):
    """The four variants trained 8 Adam steps with either kernel: same losses and weights within the tolerances
    (the deterministic teacher-forced one bitwise: neither self-fed steps nor an NLL); a pack of two as well."""
    task, _ = toy
    demos = task.demos(0)
    model_cfg, cfg = VARIANTS[variant].configs(TINY, BASE)
    ref = train(model_cfg, cfg, task, demos)  # BASE: the Python steps
    got = train(model_cfg, dataclasses.replace(cfg, step_kernel="cpp"), task, demos)
    exact = cfg.v == 0 and model_cfg.head != "mdn"
    torch.testing.assert_close(torch.tensor(got.history["train/loss"]), torch.tensor(ref.history["train/loss"]),
                               rtol=0 if exact else 1e-6, atol=0)
    for key, w in ref.model.state_dict().items():
        torch.testing.assert_close(got.model.state_dict()[key], w, rtol=0, atol=0 if exact else WEIGHT_TOL)
    if not exact:  # a pack of two
        cfgs = [dataclasses.replace(cfg, seed=s) for s in (0, 1)]
        packed = train_packed(model_cfg, [dataclasses.replace(c, step_kernel="cpp") for c in cfgs], task, demos)
        ref_packed = train_packed(model_cfg, cfgs, task, demos)
        for p, r in zip(packed, ref_packed, strict=True):
            for key, w in r.model.state_dict().items():
                torch.testing.assert_close(p.model.state_dict()[key], w, rtol=0, atol=WEIGHT_TOL)


def test_a_failed_build_warns_once_and_the_python_steps_run(toy, monkeypatch):
    import warnings

    from torch.utils import cpp_extension

    from stm import cpp_ext

    def fail(*args, **kwargs):
        raise RuntimeError("no compiler here")

    monkeypatch.setattr(cpp_extension, "load", fail)
    cpp_ext.self_fed_extension.cache_clear()
    try:
        monkeypatch.setenv(cpp_ext.REQUIRE, "1")  # required (CI): the failure raises
        with pytest.raises(RuntimeError, match="ACRMDN_REQUIRE_CPP is set.*no compiler here"):
            cpp_ext.self_fed_extension()
        monkeypatch.delenv(cpp_ext.REQUIRE)
        with pytest.warns(RuntimeWarning, match="no compiler here"):
            assert cpp_ext.self_fed_extension() is None
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            assert cpp_ext.self_fed_extension() is None  # once
        task, data = toy
        pack = _pack(task, data, ModelConfig(hidden_size=8, mixtures=2), "grounded", 1)
        monkeypatch.setattr(self_fed, "self_fed_extension", cpp_ext.self_fed_extension)
        assert self_fed.cpp_steps(pack.view(), TrainConfig(), task, KIN, None,
                                  data.batch(torch.arange(2)).psi.unsqueeze(0)) is None  # auto: the Python steps
    finally:
        cpp_ext.self_fed_extension.cache_clear()
