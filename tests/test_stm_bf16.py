"""bfloat16 matrix products (TrainConfig.matmul_dtype): the LSTM stack's and the head's products run in bf16,
forward and backward, and give the float32 loss and gradients within bf16's rounding, for the four variants,
one model and a pack; everything else stays float32."""

import numpy as np
import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from stm.config import ModelConfig, TrainConfig
from stm.fk import default_tip_kinematics
from stm.lstm_step import product_dtype
from stm.model import STM, normalization_stats
from stm.packed import PackedSTM
from stm.speed.floor import record_matmuls
from stm.training.autoconditioning import batch_loss, unroll
from stm.training.batches import DemoTensors
from stm.training.loop import train
from stm.variants import VARIANTS

KIN = default_tip_kinematics(torch.float32)
MODEL = ModelConfig(hidden_size=32, num_layers=3, mixtures=3)
# bf16 keeps 8 bits of mantissa (relative rounding 2^-9 per product): the loss is a mean over many
# steps, so its error averages out; a gradient's error is the products' rounding carried through
LOSS_RTOL = 5e-4  # measured up to 8e-5
GRAD_RTOL = 1e-2  # measured up to 4e-3; |g_bf16 - g_fp32| / |g_fp32| over all parameters of a model
SCHEDULES = {"lstm": {}, "ac-lstm": {"u": 2, "v": 3}, "lstm-mdn": {}, "ac-lstm-mdn": {"u": 3, "v": 2}}


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=8, min_steps=12, max_steps=16, gripper=True)
    data = DemoTensors.build(task, task.demos(0))
    valid = torch.arange(data.states.shape[1])[None] <= data.lengths[:, None]
    return task, data, normalization_stats(data.states, valid)


def _configs(variant: str, dtype: str):
    return VARIANTS[variant].configs(MODEL, TrainConfig(matmul_dtype=dtype, **SCHEDULES[variant]))


def _models(variant: str, task, stats, k: int) -> list[STM]:
    out = []
    for seed in range(k):
        torch.manual_seed(seed)
        out.append(STM(_configs(variant, "float32")[0], task.layout, *stats))
    return out


def _single(variant, task, data, stats, dtype):
    [model] = _models(variant, task, stats, 1)
    batch = data.batch(torch.arange(len(data)))
    loss = batch_loss(model, batch, task, _configs(variant, dtype)[1], KIN)
    grads = torch.autograd.grad(loss, list(model.parameters()))
    return loss.detach()[None], [torch.cat([g.flatten() for g in grads])]


def _packed(variant, task, data, stats, dtype, k=3):
    pack = PackedSTM.from_models(_models(variant, task, stats, k))
    cfg = _configs(variant, dtype)[1]
    batch = data.stacked([data.draw(cfg, torch.Generator().manual_seed(j)) for j in range(k)])
    steps = [int(m.sum(-1).max()) for m in batch.mask]
    view = pack.view()
    raw = unroll(view, batch.states, batch.q, batch.psi, steps, task, cfg, KIN, [None] * k)
    losses = view.losses(raw, view.normalize(batch.states[:, :, 1:]), batch.mask)
    grads = torch.autograd.grad(losses.sum(), list(pack.stacked))
    return losses.detach(), [torch.cat([g[j].flatten() for g in grads]) for j in range(k)]


@pytest.mark.parametrize("how", ["single", "packed"])
@pytest.mark.parametrize("variant", list(VARIANTS))
def test_bf16_products_give_the_fp32_loss_and_gradients(toy, variant, how):
    task, data, stats = toy
    run = _single if how == "single" else _packed
    loss32, grads32 = run(variant, task, data, stats, "float32")
    loss16, grads16 = run(variant, task, data, stats, "bfloat16")
    assert not torch.equal(loss16, loss32)  # the bf16 path ran
    np.testing.assert_allclose(loss16, loss32, rtol=LOSS_RTOL)
    for g16, g32 in zip(grads16, grads32, strict=True):
        assert ((g16 - g32).norm() / g32.norm()).item() < GRAD_RTOL


def test_bf16_training_follows_fp32_training(toy):
    """A few dozen Adam steps (master weights and Adam in fp32) stay on the fp32 run's loss curve."""
    task, _, _ = toy
    demos = task.demos(0)
    model_cfg, cfg = VARIANTS["ac-lstm-mdn"].configs(MODEL, TrainConfig(iters=30, batch_size=4, u=2, v=2,
                                                                        log_every=0, checkpoint_every=0))
    fp32 = train(model_cfg, cfg, task, demos).history["train/loss"]
    bf16 = train(model_cfg, TrainConfig.from_dict({**cfg.to_dict(), "matmul_dtype": "bfloat16"}), task,
                 demos).history["train/loss"]
    assert abs(bf16[-1] - fp32[-1]) < 0.02 * max(1.0, abs(fp32[-1]))
    assert bf16[-1] < bf16[0] - 0.1  # it learns


def test_bf16_runs_the_lstm_and_head_products_in_bf16_and_kinematics_in_fp32(toy):
    """Packed and auto-conditioned (stepped chunks, layer sequences, self-fed steps, head): every product is
    bf16 but those of the tip kinematics, whose constants stay fp32."""
    task, data, stats = toy
    fk_shapes = {tuple(KIN.coef.shape), tuple(KIN.row_sums.shape), tuple(KIN.signs.shape)}
    calls = record_matmuls(lambda: _packed("ac-lstm-mdn", task, data, stats, "bfloat16"))
    dtypes = {}
    for _, args, _ in calls:
        specs = [a for a in args if hasattr(a, "dtype")]
        fk = any(tuple(s.shape[-2:]) in fk_shapes for s in specs)  # the C++ steps batch them as (1, R, C)
        dtypes.setdefault(fk, set()).update(s.dtype for s in specs)
    assert dtypes[False] == {torch.bfloat16}
    assert dtypes[True] == {torch.float32}


def test_product_dtype_names():
    assert product_dtype("float32") is None
    assert product_dtype("bfloat16") is torch.bfloat16
    with pytest.raises(ValueError, match="known: float32, bfloat16"):
        product_dtype("float16")
    with pytest.raises(ValueError, match="matmul_dtype"):
        TrainConfig(matmul_dtype="float16")


def test_the_default_leaves_config_hashes_alone():
    assert "matmul_dtype" not in TrainConfig().hashed_dict()
    assert TrainConfig(matmul_dtype="bfloat16").hashed_dict()["matmul_dtype"] == "bfloat16"
