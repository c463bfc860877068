import torch

from envs.kinematics import SawyerKinematics
from envs.robot import LIMITS
from stm.fk import TipKinematics


def _random_q(n: int, dtype) -> torch.Tensor:
    g = torch.Generator().manual_seed(0)
    lo, hi = torch.as_tensor(LIMITS.lower, dtype=dtype), torch.as_tensor(LIMITS.upper, dtype=dtype)
    return lo + (hi - lo) * torch.rand(n, 7, generator=g, dtype=dtype)


def test_tip_position_and_gradient_match_pytorch_kinematics():
    kin = SawyerKinematics(dtype=torch.float64)
    fk = TipKinematics(kin)
    q = _random_q(64, torch.float64).reshape(4, 16, 7).requires_grad_()
    w = torch.randn(4, 16, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    ref = kin.tip_position(q)
    (ref * w).sum().backward()
    g_ref, q.grad = q.grad.clone(), None
    ours = fk.tip_position(q)
    (ours * w).sum().backward()
    assert ours.shape == (4, 16, 3)
    torch.testing.assert_close(ours, ref, atol=1e-12, rtol=0)
    torch.testing.assert_close(q.grad, g_ref, atol=1e-10, rtol=0)


def test_gradcheck_and_no_graph_without_grad():
    fk = TipKinematics(SawyerKinematics(dtype=torch.float64))
    q = _random_q(3, torch.float64).requires_grad_()
    assert torch.autograd.gradcheck(fk.tip_position, (q,))
    with torch.no_grad():
        assert not fk.tip_position(q).requires_grad
