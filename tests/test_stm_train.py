import math

import pytest
import torch
from stm_toytask import ToyReach, single_torch_thread  # noqa: F401  (autouse)

from envs.kinematics import default_kinematics
from stm.config import ModelConfig, TrainConfig
from stm.model import STM, feedback_state, normalization_stats
from stm.packed import PackedSTM
from stm.training.autoconditioning import batch_loss, schedule, segments
from stm.training.autoconditioning import unroll_model as unroll
from stm.training.batches import DemoTensors
from stm.training.checkpoint import FORMAT_VERSION, CheckpointError, load_checkpoint, load_model, save_checkpoint
from stm.training.loop import TrainingDiverged, train

KIN = default_kinematics(torch.float32)
TINY = ModelConfig(hidden_size=12, num_layers=2, mixtures=2)


@pytest.fixture(scope="module")
def toy():
    task = ToyReach(n_demos=6, min_steps=8, max_steps=11, gripper=True)
    return task, task.demos(0)


def test_schedule_pattern():
    assert schedule(12, 2, 3).tolist() == [1, 1, 0, 0, 0, 1, 1, 0, 0, 0, 1, 1]
    assert schedule(4, 5, 0).all()
    # the runs the unroll follows are the schedule's
    for T, u, v in ((12, 2, 3), (13, 2, 3), (4, 5, 0), (7, 1, 4), (3, 5, 5)):
        runs = [bool(x) for n, k in segments(T, u, v) for x in [1] * n + [0] * k]
        assert runs == schedule(T, u, v).tolist()


def _model(task, demos, cfg=TINY):
    data = DemoTensors.build(task, demos)
    valid = torch.arange(data.states.shape[1])[None] <= data.lengths[:, None]
    torch.manual_seed(0)
    return STM(cfg, task.layout, *normalization_stats(data.states, valid)), data


@pytest.mark.parametrize("u,v,phi_mode", [(2, 2, "grounded"), (3, 1, "free"), (1, 4, "grounded")])
def test_autoconditioning_feeds_exactly_the_scheduled_steps(toy, u, v, phi_mode):
    task, demos = toy
    model, data = _model(task, demos)
    batch = data.batch(torch.arange(len(demos)))
    cfg = TrainConfig(u=u, v=v, phi_mode=phi_mode)
    raw, fed = unroll(model, batch, task, cfg, KIN, return_inputs=True)
    z_gt = model.normalize(batch.states[:, :-1])
    T = z_gt.shape[1]
    gt = schedule(T, u, v)
    torch.testing.assert_close(fed[:, gt], z_gt[:, gt])  # ground-truth steps: the demo states
    # self-fed steps: rebuilt here independently from the model's prediction one step earlier
    q = None
    for t in range(T):
        if gt[t]:
            q = batch.q[:, t]
            continue
        pred = model.denormalize(model.predict(raw[:, t - 1]))
        s, q = feedback_state(task, KIN, pred, q, batch.psi[:, t], phi_mode)
        torch.testing.assert_close(fed[:, t], model.normalize(s), atol=1e-5, rtol=1e-5)
        assert not torch.allclose(fed[:, t], z_gt[:, t], atol=1e-3)
    # the head outputs agree with a plain step-by-step run over the fed inputs
    raw_ref, _ = model(fed.detach())
    torch.testing.assert_close(raw, raw_ref, atol=1e-5, rtol=1e-4)


def test_teacher_forcing_equals_plain_forward_and_detach_cuts_gradients(toy):
    task, demos = toy
    model, data = _model(task, demos)
    batch = data.batch(torch.arange(4))
    raw, fed = unroll(model, batch, task, TrainConfig(v=0), KIN, return_inputs=True)
    torch.testing.assert_close(fed, model.normalize(batch.states[:, :-1]))
    # a late step's gradient reaches the head through fed-back states unless they are detached
    grads = {}
    for detach in (False, True):
        model.zero_grad()
        out, fed = unroll(model, batch, task, TrainConfig(u=1, v=5, detach_feedback=detach), KIN,
                          return_inputs=True)
        out[:, 3].sum().backward()  # inputs 1..3 were self-fed
        grads[detach] = model.head.weight.grad.clone()
    model.zero_grad()
    direct, _ = model(fed.detach())  # only the direct path from the head to step 3
    direct[:, 3].sum().backward()
    torch.testing.assert_close(grads[True], model.head.weight.grad)
    assert not torch.allclose(grads[False], grads[True])


def test_resume_reproduces_the_uninterrupted_run(toy, tmp_path):
    task, demos = toy
    cfg = TrainConfig(iters=12, batch_size=4, lr=3e-3, u=2, v=2, feedback="sample", checkpoint_every=5,
                      log_every=1, seed=3)
    full = train(TINY, cfg, task, demos)
    path = tmp_path / "ckpt.pt"
    seen = []
    first = train(TINY, TrainConfig.from_dict({**cfg.to_dict(), "iters": 5}), task, demos, checkpoint_path=path,
                  on_checkpoint=lambda p, it: seen.append(it))
    assert first.iterations == 5 and seen == [5, 5]  # periodic + final checkpoint
    resumed = train(TINY, cfg, task, demos, checkpoint_path=path)
    assert resumed.iterations == 12
    assert resumed.history["train/loss"] == full.history["train/loss"]
    for a, b in zip(resumed.model.state_dict().values(), full.model.state_dict().values(), strict=True):
        assert torch.equal(a, b)
    with pytest.raises(ValueError, match="another model config"):
        train(ModelConfig(hidden_size=7), cfg, task, demos, checkpoint_path=path)


def test_nan_guard_names_iteration_and_keeps_last_good_checkpoint(toy, tmp_path, monkeypatch):
    task, demos = toy
    path = tmp_path / "ckpt.pt"
    cfg = TrainConfig(iters=20, batch_size=3, checkpoint_every=4, log_every=1, u=2, v=1)
    holder = {}

    def sabotage(iteration, metrics):
        if iteration == 6:  # poison the weights: iteration 7 computes a NaN loss
            with torch.no_grad():
                for p in holder["pack"].stacked:
                    p.fill_(math.nan)

    original = PackedSTM.from_models

    def capture(models):
        holder["pack"] = original(models)
        return holder["pack"]

    monkeypatch.setattr(PackedSTM, "from_models", staticmethod(capture))
    with pytest.raises(TrainingDiverged, match="iteration 7") as exc:
        train(TINY, cfg, task, demos, checkpoint_path=path, on_metrics=sabotage)
    assert exc.value.iteration == 7
    ckpt = load_checkpoint(path)
    assert ckpt["iteration"] == 4
    assert all(torch.isfinite(t).all() for t in ckpt["model"].values())


def test_validation_callback_stops_early(toy, tmp_path):
    task, demos = toy
    calls = []
    cfg = TrainConfig(iters=50, batch_size=3, val_every=3, val_episodes=2, u=2, v=1)
    res = train(TINY, cfg, task, demos, checkpoint_path=tmp_path / "c.pt",
                on_validation=lambda it, value: calls.append((it, value)) or it >= 6)
    assert res.stopped_early and res.iterations == 6 and [c[0] for c in calls] == [3, 6]
    assert all(value > 0 and math.isfinite(value) for _, value in calls)
    assert load_checkpoint(tmp_path / "c.pt")["iteration"] == 6
    model = load_model(tmp_path / "c.pt")
    assert model.config == TINY and not model.training


def test_metrics_callback_batches_and_loss_decreases(toy):
    task, demos = toy
    logged = []
    res = train(TINY, TrainConfig(iters=60, batch_size=6, lr=1e-2, log_every=20, u=2, v=2), task, demos,
                on_metrics=lambda it, m: logged.append((it, m)))
    assert [it for it, _ in logged] == [20, 40, 60]
    assert set(logged[0][1]) >= {"train/loss", "train/grad_norm"}
    assert logged[-1][1]["train/loss"] < logged[0][1]["train/loss"]
    assert len(res.history["train/loss"]) == 60


def test_bad_checkpoints_give_clear_errors(toy, tmp_path):
    bad = tmp_path / "bad.pt"
    bad.write_bytes(b"not a checkpoint at all")
    with pytest.raises(CheckpointError, match="cannot read checkpoint"):
        load_model(bad)
    old = save_checkpoint({"format_version": FORMAT_VERSION + 1}, tmp_path / "old.pt")
    with pytest.raises(CheckpointError, match="format version"):
        load_checkpoint(old)
    with pytest.raises(CheckpointError, match="no checkpoint"):
        load_checkpoint(tmp_path / "missing.pt")
    task, demos = toy
    with pytest.raises(CheckpointError):
        train(TINY, TrainConfig(iters=2), task, demos, checkpoint_path=bad)  # never silently overwritten
    assert bad.read_bytes() == b"not a checkpoint at all"


def test_batch_loss_feeds_back_each_mode_on_the_scheduled_steps_only(toy):
    task, demos = toy
    model, data = _model(task, demos)
    batch = data.batch(torch.arange(3))

    def loss(feedback: str, u: int, v: int, seed: int = 0) -> float:
        cfg = TrainConfig(u=u, v=v, feedback=feedback)
        value = batch_loss(model, batch, task, cfg, KIN, torch.Generator().manual_seed(seed))
        assert torch.isfinite(value)
        return value.item()

    modes = ("sample", "component_mean", "mixture_mean")
    teacher = {loss(f, u=4, v=0) for f in modes}
    assert len(teacher) == 1  # no step is fed back: the feedback mode cannot matter
    fed = [loss(f, u=2, v=2) for f in modes]
    assert len(set(fed)) == 3 and teacher.isdisjoint(fed)  # each mode feeds back its own states
    assert loss("sample", 2, 2, seed=0) == fed[0] != loss("sample", 2, 2, seed=1)  # sampling follows the generator


def test_phi_mode_travels_with_the_checkpoint(toy, tmp_path):
    task, demos = toy
    train(TINY, TrainConfig(iters=2, batch_size=2, u=1, v=1, phi_mode="free"), task, demos,
          checkpoint_path=tmp_path / "free.pt")
    assert load_model(tmp_path / "free.pt").phi_mode == "free"


def test_input_noise_only_perturbs_ground_truth_inputs_in_training(toy):
    task, demos = toy
    model, data = _model(task, demos)
    batch = data.batch(torch.arange(3))
    cfg = TrainConfig(u=2, v=2, input_noise=0.1)
    clean = model.normalize(batch.states[:, :-1])
    _, fed = unroll(model, batch, task, cfg, KIN, torch.Generator().manual_seed(0), return_inputs=True)
    gt = schedule(clean.shape[1], 2, 2)
    noise = (fed[:, gt] - clean[:, gt]).std().item()
    assert 0.05 < noise < 0.2
    model.eval()
    _, fed = unroll(model, batch, task, cfg, KIN, torch.Generator().manual_seed(0), return_inputs=True)
    torch.testing.assert_close(fed[:, gt], clean[:, gt])


def test_validation_uses_fresh_episodes_when_the_task_has_a_kinematic_error():
    import numpy as np

    from stm.training.validation import VAL_SEED, Validation

    class ToyWithError(ToyReach):
        def kinematic_error(self, tip, episode):
            return float(np.linalg.norm(tip[-1] - episode.psi[-1]))

    plain, scored = ToyReach(n_demos=4), ToyWithError(n_demos=4)
    demos = plain.demos(0)
    replay = Validation.build(plain, demos, 3)
    assert replay.demos is demos and len(replay.episodes) == 3
    np.testing.assert_array_equal(replay.episodes[0].q0, demos.q[0, 0])
    fresh = Validation.build(scored, demos, 3)
    assert fresh.demos is None
    np.testing.assert_array_equal(fresh.episodes[0].q0, scored.episodes(3, VAL_SEED)[0].q0)
    assert not any(np.allclose(ep.q0, demos.q[i, 0]) for i, ep in enumerate(fresh.episodes))


def test_tf_warmup_teacher_forces_the_first_iterations_then_auto_conditions(toy, tmp_path):
    task, demos = toy
    common = dict(batch_size=4, lr=3e-3, u=2, v=2, seed=5, log_every=0)
    tf = train(TINY, TrainConfig(iters=6, **{**common, "v": 0}), task, demos).history["train/loss"]
    ac = train(TINY, TrainConfig(iters=6, **common), task, demos).history["train/loss"]
    cfg = TrainConfig(iters=6, tf_warmup=3, checkpoint_every=2, **common)
    warm = train(TINY, cfg, task, demos).history["train/loss"]
    assert warm[:3] == tf[:3] and warm[3:] != tf[3:] and warm[:3] != ac[:3]
    # resuming inside the warm-up reproduces the run
    path = tmp_path / "w.pt"
    train(TINY, TrainConfig.from_dict({**cfg.to_dict(), "iters": 2}), task, demos, checkpoint_path=path)
    assert train(TINY, cfg, task, demos, checkpoint_path=path).history["train/loss"] == warm
    with pytest.raises(ValueError, match=r"tf_warmup\s+Input should be greater than or equal to 0"):
        TrainConfig(tf_warmup=-1)


def test_with_hold_appends_the_last_row_and_counts_it():
    import numpy as np

    demos = ToyReach(n_demos=3, min_steps=5, max_steps=9, gripper=True).demos(0)
    held = demos.with_hold(4)
    assert demos.with_hold(0) is demos and held.meta["hold_steps"] == 4
    np.testing.assert_array_equal(held.lengths, demos.lengths + 4)
    for i, n in enumerate(demos.lengths):
        for a, b in ((held.q, demos.q), (held.grip, demos.grip), (held.psi, demos.psi)):
            np.testing.assert_array_equal(a[i, : n + 1], b[i, : n + 1])  # the demo itself unchanged
            np.testing.assert_array_equal(a[i, n + 1: n + 5], np.repeat(b[i, n][None], 4, axis=0))  # then it holds
    with pytest.raises(ValueError, match="hold steps must be >= 0"):
        demos.with_hold(-1)


def test_hold_steps_trains_the_held_demos(toy):
    """train(hold_steps=H) is training on demos.with_hold(H): the same losses; and not the demos alone."""
    task, demos = toy
    cfg = TrainConfig(iters=4, batch_size=3, lr=3e-3, u=2, v=2, log_every=0, checkpoint_every=0)
    held = train(TINY, TrainConfig.from_dict({**cfg.to_dict(), "hold_steps": 3}), task, demos)
    explicit = train(TINY, cfg, task, demos.with_hold(3))
    plain = train(TINY, cfg, task, demos)
    assert held.history["train/loss"] == explicit.history["train/loss"]
    assert held.history["train/loss"] != plain.history["train/loss"]


def test_ctrl_c_mid_step_checkpoints_that_whole_step_and_a_resume_matches(
    toy, tmp_path, monkeypatch, sigint_raises
):
    """A Ctrl-C that lands while iteration 8 computes its loss waits for the step to finish; the training then
    checkpoints iteration 8 (not the periodic 5) and passes the interrupt on; resuming finishes the run exactly as
    an uninterrupted one."""
    import signal
    import threading

    import stm.training.loop

    if threading.current_thread() is not threading.main_thread():
        pytest.skip("signals reach the main thread only")
    task, demos = toy
    cfg = TrainConfig(iters=12, batch_size=4, lr=3e-3, u=2, v=2, feedback="sample", checkpoint_every=5,
                      log_every=1, seed=3)
    full = train(TINY, cfg, task, demos)
    real, calls = stm.training.loop.unroll, []

    def loss_then_ctrl_c(*args, **kwargs):
        calls.append(1)
        out = real(*args, **kwargs)
        if len(calls) == 8:  # before the backward pass and the optimiser step of iteration 8
            signal.raise_signal(signal.SIGINT)
        return out

    monkeypatch.setattr(stm.training.loop, "unroll", loss_then_ctrl_c)
    path, seen = tmp_path / "ckpt.pt", []
    with pytest.raises(KeyboardInterrupt):
        train(TINY, cfg, task, demos, checkpoint_path=path, on_checkpoint=lambda p, it: seen.append(it))
    assert seen == [5, 8] and load_checkpoint(path)["iteration"] == 8
    monkeypatch.undo()
    resumed = train(TINY, cfg, task, demos, checkpoint_path=path)
    assert resumed.history["train/loss"] == full.history["train/loss"]
    for a, b in zip(resumed.model.state_dict().values(), full.model.state_dict().values(), strict=True):
        assert torch.equal(a, b)
