"""pytorch-kinematics FK against pybullet, the facts sheet's reference poses, the Jacobian
against finite differences, and clear errors for bad robot descriptions."""

from __future__ import annotations

import numpy as np
import pybullet as p
import pytest
import torch

from envs.kinematics import SawyerKinematics, default_kinematics
from envs.robot import LIMITS, NEUTRAL_Q, URDFError, load_in_pybullet

# (q, right_hand position, right_gripper_tip position): reference poses of the Sawyer kinematic facts the URDF
# (envs/assets/sawyer/sawyer.urdf) was written from
REFERENCE = [
    (np.zeros(7), (1.0155, 0.1603, 0.3170), (1.15112, 0.1603, 0.31700)),
    (NEUTRAL_Q, (0.449598, 0.1603, 0.215754), (0.449705, 0.1603, 0.080134)),
    (np.array([0.8355, -2.1684, -2.7933, -2.9433, 1.8646, 2.4568, 1.0050]),
     (-0.255726, 0.133847, 0.308760), (-0.232048, 0.022052, 0.381794)),
]


@pytest.fixture(scope="module")
def kin():
    return default_kinematics(torch.float64)


@pytest.fixture(scope="module")
def bullet():
    client = p.connect(p.DIRECT)
    robot = load_in_pybullet(client)
    yield robot
    p.disconnect(client)


def _bullet_poses(robot, q):
    robot.reset(q)
    hand = robot.link_pose(robot.hand)
    tip = robot.link_pose(robot.tip)
    return hand, tip


def _angle_between(Ra: np.ndarray, Rb: np.ndarray) -> float:
    c = (np.trace(Ra.T @ Rb) - 1.0) / 2.0
    # arccos is ill-conditioned near 0: use the skew part for small angles
    skew = Ra.T @ Rb - Rb.T @ Ra
    s = np.linalg.norm([skew[2, 1], skew[0, 2], skew[1, 0]]) / 2.0
    return float(np.arctan2(s, c))


def test_fk_matches_pybullet_at_200_random_configurations(kin, bullet):
    q = LIMITS.sample(np.random.default_rng(0), 200)
    poses = kin.forward(torch.as_tensor(q))
    worst_pos, worst_rot = 0.0, 0.0
    for i in range(200):
        (hp, hr), (tp, tr) = _bullet_poses(bullet, q[i])
        worst_pos = max(worst_pos, np.abs(poses.hand_pos[i].numpy() - hp).max(),
                        np.abs(poses.tip_pos[i].numpy() - tp).max())
        worst_rot = max(worst_rot, _angle_between(poses.hand_rot[i].numpy(), hr),
                        _angle_between(poses.tip_rot[i].numpy(), tr))
    assert worst_pos <= 1e-5, worst_pos
    assert worst_rot <= 1e-5, worst_rot


def test_angle_helper_sees_small_rotations():
    t = 3e-5
    R = np.array([[np.cos(t), -np.sin(t), 0], [np.sin(t), np.cos(t), 0], [0, 0, 1]])
    assert _angle_between(np.eye(3), R) == pytest.approx(t, rel=1e-6)


@pytest.mark.parametrize("q, hand, tip", REFERENCE)
def test_reference_poses_of_the_facts_sheet(kin, bullet, q, hand, tip):
    poses = kin.forward(torch.as_tensor(q))
    assert np.abs(poses.hand_pos.numpy() - hand).max() <= 1e-4
    assert np.abs(poses.tip_pos.numpy() - tip).max() <= 1e-4
    (hp, _), (tp, _) = _bullet_poses(bullet, q)
    assert np.abs(hp - hand).max() <= 1e-4 and np.abs(tp - tip).max() <= 1e-4


def test_batched_shapes_and_float32_agree(kin):
    q = torch.as_tensor(LIMITS.sample(np.random.default_rng(1), 20)).reshape(4, 5, 7)
    tip64 = kin.tip_position(q)
    assert tip64.shape == (4, 5, 3) and kin.jacobian(q).shape == (4, 5, 6, 7)
    tip32 = default_kinematics(torch.float32).tip_position(q.float())
    assert torch.allclose(tip32.double(), tip64, atol=1e-5)
    with pytest.raises(ValueError, match="size 7"):
        kin.tip_position(torch.zeros(3, 6))


def test_jacobian_matches_finite_differences(kin):
    q = torch.as_tensor(LIMITS.sample(np.random.default_rng(2), 10, margin=0.01))
    J = kin.jacobian(q).numpy()
    h = 1e-6
    for i in range(7):
        dq = torch.zeros(7, dtype=torch.float64)
        dq[i] = h
        plus, minus = kin.forward(q + dq), kin.forward(q - dq)
        dpos = (plus.tip_pos - minus.tip_pos).numpy() / (2 * h)
        dR = (plus.tip_rot - minus.tip_rot).numpy() / (2 * h)
        W = dR @ kin.forward(q).tip_rot.numpy().transpose(0, 2, 1)  # [omega]x = dR/dq R^T
        omega = np.stack([W[:, 2, 1], W[:, 0, 2], W[:, 1, 0]], axis=-1)
        assert np.abs(J[:, :3, i] - dpos).max() < 1e-6
        assert np.abs(J[:, 3:, i] - omega).max() < 1e-6


def test_missing_urdf_is_a_clear_error(tmp_path):
    with pytest.raises(URDFError, match="not found") as exc:
        SawyerKinematics(tmp_path / "nope.urdf")
    assert "\n" not in str(exc.value)
    client = p.connect(p.DIRECT)
    try:
        with pytest.raises(URDFError, match="not found"):
            load_in_pybullet(client, tmp_path / "nope.urdf")
    finally:
        p.disconnect(client)


@pytest.mark.parametrize("text, reason", [
    ("<robot name='x'><link name='a'>", "not valid XML"),
    ("<notarobot/>", "expected <robot>"),
    ("<robot name='x'><link name='right_arm_base_link'/></robot>", "lacks"),
])
def test_malformed_urdf_is_a_clear_error(tmp_path, text, reason):
    path = tmp_path / "bad.urdf"
    path.write_text(text)
    with pytest.raises(URDFError, match=reason) as exc:
        SawyerKinematics(path)
    assert "\n" not in str(exc.value).strip()
