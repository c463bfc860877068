"""envs.ik (damped-least-squares IK: solve_ik, solve_path) checked against pybullet's forward
kinematics, and stm.control.idm's save_idm/load_idm round trip."""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest
import torch

from envs.ik import solve_ik, solve_path
from envs.kinematics import default_kinematics
from envs.robot import LIMITS, NEUTRAL_Q, load_in_pybullet


@pytest.fixture(scope="module")
def bullet():
    """pybullet's own forward kinematics: the oracle, independent of pytorch-kinematics."""
    client = p.connect(p.DIRECT)
    robot = load_in_pybullet(client)
    yield robot
    p.disconnect(client)


def _tip(robot, q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    robot.reset(q)
    pos, rot = robot.link_pose(robot.tip)
    return np.asarray(pos), np.asarray(rot)


def _targets(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Reachable targets: the tips of random configurations near the neutral pose, and those configurations."""
    q = LIMITS.clip(NEUTRAL_Q + np.random.default_rng(seed).uniform(-0.4, 0.4, size=(n, 7)))
    kin = default_kinematics(torch.float64)
    return kin.tip_position(torch.as_tensor(q)).numpy(), q


def test_solve_ik_reaches_reachable_targets_with_the_tool_down(bullet):
    targets, _ = _targets(8)
    res = solve_ik(torch.as_tensor(targets), torch.as_tensor(NEUTRAL_Q)[None], iters=200)
    assert res.q.shape == (8, 7) and res.converged.all(), (res.pos_err, res.rot_err)
    for i in range(8):
        pos, rot = _tip(bullet, res.q[i].numpy())
        assert np.linalg.norm(pos - targets[i]) < 2e-4  # tol_pos 1e-4, measured by pybullet
        assert np.degrees(np.arccos(np.clip(-rot[2, 2], -1, 1))) < 0.2  # tool axis points down
    assert LIMITS.contains(res.q.numpy(), tol=1e-9).all()


def test_solve_ik_matches_a_full_target_frame_and_position_only_leaves_orientation_free(bullet):
    targets, q_true = _targets(4, seed=1)
    frames = np.stack([_tip(bullet, q)[1] for q in q_true])
    full = solve_ik(torch.as_tensor(targets), torch.as_tensor(NEUTRAL_Q)[None], target_rot=torch.as_tensor(frames),
                    iters=300)
    assert full.converged.all(), (full.pos_err, full.rot_err)
    for i in range(4):
        pos, rot = _tip(bullet, full.q[i].numpy())
        assert np.linalg.norm(pos - targets[i]) < 2e-4
        assert np.abs(rot - frames[i]).max() < 2e-3  # the whole frame, not only the tool axis
    free = solve_ik(torch.as_tensor(targets), torch.as_tensor(NEUTRAL_Q)[None], tool_axis=None, iters=300)
    assert free.converged.all() and torch.equal(free.rot_err, torch.zeros(4, dtype=free.rot_err.dtype))


def test_solve_ik_on_an_unreachable_target_stays_in_the_limits_and_says_so():
    far = torch.tensor([[3.0, 0.0, 0.5]])  # 3 m away: the arm is about 1.2 m long
    res = solve_ik(far, torch.as_tensor(NEUTRAL_Q)[None], iters=150)
    assert not res.converged.any() and res.pos_err.item() > 1.5
    assert LIMITS.contains(res.q.numpy(), tol=1e-9).all()


def test_solve_path_follows_a_line_waypoint_by_waypoint(bullet):
    kin = default_kinematics(torch.float64)
    q0 = torch.as_tensor(NEUTRAL_Q)[None].repeat(2, 1)
    start = kin.tip_position(q0).numpy()
    end = start + np.array([[0.10, 0.05, -0.05], [-0.05, 0.10, 0.05]])
    path = start[:, None] + np.linspace(0, 1, 12)[None, :, None] * (end - start)[:, None]
    res = solve_path(torch.as_tensor(path), q0)
    assert res.q.shape == (2, 12, 7) and res.converged.all()
    errs = np.array([[np.linalg.norm(_tip(bullet, res.q[b, t].numpy())[0] - path[b, t]) for t in range(12)]
                     for b in range(2)])
    assert errs.max() < 2e-4
    np.testing.assert_allclose(res.pos_err.numpy(), errs.max(axis=1), atol=1e-6)  # the worst waypoint, per path
    steps = np.abs(np.diff(res.q.numpy(), axis=1)).max()
    assert steps < 0.1  # warm starts keep the joint path continuous: ~1.5 cm per waypoint, no jumps
    # an unreachable waypoint makes the whole path unconverged
    bad = path.copy()
    bad[1, 6] = [3.0, 0.0, 0.5]
    assert solve_path(torch.as_tensor(bad), q0, iters=60).converged.tolist() == [True, False]


def test_save_and_load_idm_round_trip(tmp_path):
    from stm.control.idm import IDMConfig, InverseDynamicsMDN, load_idm, save_idm
    from stm.control.idm_data import FEATURE_DIM

    rng = np.random.default_rng(0)
    torch.manual_seed(0)
    cfg = IDMConfig(hidden=16, layers=2, mixtures=3, point="component_mean")
    model = InverseDynamicsMDN(cfg, x_mean=rng.normal(size=FEATURE_DIM), x_std=rng.uniform(0.5, 2, FEATURE_DIM),
                               y_mean=rng.normal(size=7), y_std=rng.uniform(0.5, 2, 7))
    save_idm(model, tmp_path / "idm.pt")
    loaded = load_idm(tmp_path / "idm.pt")
    assert loaded.cfg == cfg and not loaded.training
    for name, tensor in model.state_dict().items():  # weights and the standardisation buffers
        assert torch.equal(loaded.state_dict()[name], tensor), name
    x = torch.as_tensor(rng.normal(size=(5, FEATURE_DIM)), dtype=torch.float32)
    with torch.no_grad():
        assert torch.equal(loaded.torques(x), model.eval().torques(x))
    assert not torch.equal(InverseDynamicsMDN(cfg).state_dict()["y_std"], loaded.state_dict()["y_std"])


class _Code:
    def __reduce__(self):
        return (print, ("pickled code ran",))


def test_load_idm_refuses_pickled_code(tmp_path):
    from stm.control.idm import load_idm

    torch.save({"config": {}, "state_dict": _Code()}, tmp_path / "evil.pt")
    with pytest.raises(Exception, match="[Ww]eights only load failed|Unsupported"):
        load_idm(tmp_path / "evil.pt")
