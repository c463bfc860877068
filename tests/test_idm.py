import warnings

import numpy as np
import pybullet as p
import pytest
import torch

from envs.robot import NEUTRAL_Q
from stm.control.idm import (
    FastIDM,
    IDMConfig,
    IDMController,
    InverseDynamicsMDN,
    load_idm,
    save_idm,
    track_plan,
    train_idm,
)
from stm.control.idm_data import FEATURE_DIM, ExplorationConfig, IDMData, cache_path, collect, load_or_collect
from stm.control.torque_sim import JointDynamics, TorqueWorld

TINY = ExplorationConfig(episodes=2, episode_seconds=0.6, seed=3)


@pytest.fixture(autouse=True)
def one_torch_thread():
    """Tiny networks: torch's thread pool only adds hand-off waits on a shared CPU."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def tiny_data() -> IDMData:
    return collect(TINY, progress=False)


def test_model_shapes_and_fast_path_agree():
    torch.manual_seed(0)
    x = torch.randn(5, FEATURE_DIM)
    for point in ("mixture_mean", "component_mean"):
        model = InverseDynamicsMDN(IDMConfig(hidden=32, point=point)).eval()
        logit_alpha, mu, log_sigma = model.mixture(x)
        assert logit_alpha.shape == (5, 7, 15) and mu.shape == (5, 7, 15, 1) and log_sigma.shape == (5, 7, 15)
        with torch.inference_mode():
            tau = model.torques(x)
        assert tau.shape == (5, 7)
        np.testing.assert_allclose(FastIDM(model)(x.double().numpy()), tau.numpy(), atol=1e-5)


def test_paper_sizes_are_the_defaults():
    model = InverseDynamicsMDN(IDMConfig())
    linears = [m for m in model.trunk if isinstance(m, torch.nn.Linear)]
    assert [lin.out_features for lin in linears] == [256, 256, 256]
    assert model.head.out_features == 7 * 15 * 3


def test_a_saved_idm_loads_with_its_config_and_standardisation(tmp_path, tiny_data):
    """The study logs idm_sim.pt / idm_finetuned.pt: load_idm is how a user gets them back."""
    model, _ = train_idm(tiny_data, IDMConfig(hidden=16, mixtures=2, epochs=1, batch_size=32, point="component_mean"))
    save_idm(model, tmp_path / "idm.pt")
    loaded = load_idm(tmp_path / "idm.pt")
    assert loaded.cfg == model.cfg and not loaded.training
    x = torch.randn(4, FEATURE_DIM)
    with torch.inference_mode():
        torch.testing.assert_close(loaded.torques(x), model.torques(x))
    with pytest.raises(ValueError, match="point"):
        IDMConfig(point="median")


def test_nll_decreases_on_a_tiny_dataset(tiny_data):
    assert tiny_data.states.shape == (2, 61, 14) and tiny_data.actions.shape == (2, 60, 7)
    _, hist = train_idm(tiny_data, IDMConfig(hidden=64, epochs=25, batch_size=32, val_fraction=0.0))
    assert np.isfinite(hist["train_nll"]).all()
    assert hist["train_nll"][-1] < hist["train_nll"][0] - 1.0


def test_data_cache_reuse_and_corrupt_cache_rebuilt(tmp_path, tiny_data):
    first = load_or_collect(TINY, tmp_path, progress=False)
    path = cache_path(TINY, tmp_path)
    assert path.exists()
    np.testing.assert_array_equal(first.states, tiny_data.states)  # collection is deterministic per seed
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # a valid cache loads silently
        again = load_or_collect(TINY, tmp_path)
    np.testing.assert_array_equal(again.actions, first.actions)
    for damage in (b"not a zip file", path.read_bytes()[:200]):
        path.write_bytes(damage)
        with pytest.warns(RuntimeWarning, match="rebuilding") as record:
            rebuilt = load_or_collect(TINY, tmp_path, progress=False)
        assert len(record) == 1, [str(w.message) for w in record]
        np.testing.assert_array_equal(rebuilt.states, first.states)
    other = ExplorationConfig(episodes=2, episode_seconds=0.6, seed=4)
    assert cache_path(other, tmp_path) != path and other.config_hash() != TINY.config_hash()


def test_stale_cache_with_wrong_contents_is_rebuilt(tmp_path):
    path = cache_path(TINY, tmp_path)
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savez(path, states=np.zeros((2, 61, 14)), actions=np.zeros((2, 60, 7)), meta=np.array('{"format": 0}'))
    with pytest.warns(RuntimeWarning, match="stale"):
        data = load_or_collect(TINY, tmp_path, progress=False)
    assert np.abs(data.actions).max() > 0


def test_torque_world_friction_damping_and_perturbation():
    with TorqueWorld() as w:
        assert w.control_period == pytest.approx(0.01)
        hold = w.rigid_body_torques(NEUTRAL_Q, np.zeros(7), np.zeros(7))
        s = w.reset(NEUTRAL_Q)
        for _ in range(30):  # below the wrist's 1 N m friction: no motion
            w.apply(hold + np.r_[np.zeros(6), 0.6])
        assert np.abs(w.state()[:7] - s[:7]).max() < 1e-3
        w.reset(NEUTRAL_Q)
        for _ in range(30):  # above it: speed (tau - friction) / damping = 2 rad/s
            w.apply(hold + np.r_[np.zeros(6), 2.0])
        assert w.state()[13] == pytest.approx(2.0, rel=0.05)
        w.reset(NEUTRAL_Q)
        for _ in range(10):  # no torque at all: the arm falls
            w.apply(np.zeros(7))
        assert np.abs(w.state()[:7] - NEUTRAL_Q).max() > 0.01
    nominal = JointDynamics.nominal()
    real = nominal.perturbed(seed=1)
    assert real == nominal.perturbed(seed=1) and real != nominal.perturbed(seed=2)
    assert all(0.8 <= m <= 1.2 for m in real.mass_scale)
    with TorqueWorld(real) as w, TorqueWorld(nominal) as w0:
        m = p.getDynamicsInfo(w.robot.body, w.robot.arm[1], physicsClientId=w.client)[0]
        m0 = p.getDynamicsInfo(w0.robot.body, w0.robot.arm[1], physicsClientId=w0.client)[0]
        assert m == pytest.approx(m0 * real.mass_scale[1])


@pytest.mark.slow
def test_short_idm_rollout_in_pybullet_stays_stable():
    data = collect(ExplorationConfig(episodes=6, episode_seconds=2.0, seed=5), progress=False)
    model, _ = train_idm(data, IDMConfig(hidden=64, epochs=15, batch_size=64, val_fraction=0.0))
    plan = NEUTRAL_Q + np.linspace(0.0, 1.0, 6)[:, None] * np.array([0.2, 0.1, 0.0, -0.1, 0.0, 0.1, 0.0])
    with TorqueWorld() as w:
        tr = track_plan(w, FastIDM(model), plan, step_seconds=0.1)
    assert tr.q.shape == (51, 7) and tr.tau.shape == (50, 7)
    assert np.isfinite(tr.q).all()
    standing_still = np.abs(tr.q_desired - plan[0]).max()  # the error of an arm that never moves: 0.2 rad
    assert np.abs(tr.q - tr.q_desired).max() < 0.25 * standing_still  # tracks the plan (measured 0.016 rad)
    ctrl = IDMController(FastIDM(model))
    ctrl.reset(np.r_[NEUTRAL_Q, np.zeros(7)])
    assert len(ctrl.states) == 2 and len(ctrl.actions) == 2


@pytest.mark.slow
def test_idm_study_smoke_end_to_end(tmp_path):
    from experiments.control_studies import load_config
    from stm.control.idm_study import idm_study

    res = idm_study(load_config("idm", "smoke", []).study, cache_dir=tmp_path / "cache", out_dir=tmp_path / "out")
    assert res["position/tip_rmse_vs_plan_m"] < 0.02 and res["position/final_error_m"] < 0.005
    for cond in ("sim", "real_sim_idm", "real_finetuned"):  # a 3-epoch IDM: no quality claim, consistency only
        rmse, via, ref = res[f"{cond}/tip_rmse_vs_plan_m"], res[f"{cond}/tip_rmse_vs_position_m"], \
            res["position/tip_rmse_vs_plan_m"]
        assert abs(rmse - via) <= ref + 1e-9  # triangle inequality: both measured at the plan's steps
        rate, final = res[f"{cond}/success_rate"], res[f"{cond}/final_error_m"]
        assert rate in (0.0, 0.25, 0.5, 0.75, 1.0)  # 4 plans
        assert (rate == 1.0 and final < 0.05) or (rate == 0.0 and final >= 0.05) or 0.0 < rate < 1.0
    assert res["position/success_rate"] == 1.0  # the expert's plans reach their goals
    assert res["latency_fast_ms"] > 0 and res["data_samples"] == 4 * 198
    assert all((tmp_path / "out" / n).exists() for n in ("idm_tracking.png", "idm_tracking.pdf", "idm_sim.pt"))
    with pytest.raises(ValueError, match="profile"):
        load_config("idm", "huge", [])
