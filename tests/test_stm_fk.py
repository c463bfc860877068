import pytest
import torch

from envs.kinematics import SawyerKinematics
from envs.robot import LIMITS
from stm.fk import TipKinematics


def _random_q(n: int, dtype, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    lo, hi = torch.as_tensor(LIMITS.lower, dtype=dtype), torch.as_tensor(LIMITS.upper, dtype=dtype)
    return lo + (hi - lo) * torch.rand(n, 7, generator=g, dtype=dtype)


@pytest.fixture(scope="module")
def kin64():
    return SawyerKinematics(dtype=torch.float64)


def test_tip_position_and_gradient_match_pytorch_kinematics(kin64):
    fk = TipKinematics(kin64)
    q = _random_q(64, torch.float64).reshape(4, 16, 7).requires_grad_()
    w = torch.randn(4, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref = kin64.tip_position(q)
    (ref * w).sum().backward()
    g_ref, q.grad = q.grad.clone(), None
    ours = fk.tip_position(q)
    (ours * w).sum().backward()
    assert ours.shape == (4, 16, 3)
    torch.testing.assert_close(ours, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(q.grad, g_ref, atol=1e-10, rtol=0)


def test_float32_within_a_micrometre_of_pytorch_kinematics_in_float64(kin64):
    """The training and rollout dtype: the closed form's rounding stays below 1e-6 m over the joint limits."""
    fk = TipKinematics(SawyerKinematics(dtype=torch.float32))
    q = _random_q(20000, torch.float64, seed=2)
    with torch.no_grad():
        ref = kin64.tip_position(q)
        err = (fk.tip_position(q.float()).double() - ref).abs().max().item()
    assert err < 1e-6
    q32 = q[:256].float().requires_grad_()
    fk.tip_position(q32).sum().backward()
    jac = kin64.jacobian(q[:256])[:, :3]  # d tip / d q, (256, 3, 7)
    torch.testing.assert_close(q32.grad.double(), jac.sum(1), atol=1e-5, rtol=0)


def test_gradcheck_and_no_graph_without_grad(kin64):
    fk = TipKinematics(kin64)
    q = _random_q(6, torch.float64).reshape(2, 3, 7).requires_grad_()
    assert torch.autograd.gradcheck(fk.tip_position, (q,))
    with torch.no_grad():
        out = fk.tip_position(q)
    assert not out.requires_grad
    torch.testing.assert_close(out, fk.tip_position(q).detach(), atol=1e-14, rtol=0)


def test_shapes_single_configuration_and_empty_batch(kin64):
    fk = TipKinematics(kin64)
    q = _random_q(1, torch.float64)[0]
    torch.testing.assert_close(fk.tip_position(q), kin64.tip_position(q), atol=1e-12, rtol=0)
    assert fk.tip_position(torch.zeros(0, 7, dtype=torch.float64)).shape == (0, 3)
    assert fk.tip_position(torch.zeros(2, 0, 7, dtype=torch.float64, requires_grad=True)).shape == (2, 0, 3)
