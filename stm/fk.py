"""Tool-tip forward kinematics for the training and rollout loops: few ops, cheap backward.

The STM feeds back phi = f(tip(q)) at every self-fed step, so the tip position's
forward and backward run once per step in Python-sized batches, where per-op
overhead dominates. envs.kinematics.SawyerKinematics (pytorch-kinematics) computes
every frame's full pose and, backward, spreads the gradient over all of them.
Here: the serial chain T_tip(q) = A_0 Rz(q_0) A_1 Rz(q_1) ... A_6 Rz(q_6) A_tip,
with the fixed A_i read off pytorch-kinematics' frames at q = 0 (and checked
against it at random configurations on construction), 2 batched ops per joint,
no autograd graph; the backward is the positional Jacobian
J_j = z_j x (p_tip - o_j), one einsum.
"""

from __future__ import annotations

import torch

from envs.kinematics import SawyerKinematics, default_kinematics
from envs.robot import TIP_LINK


class _TipPosition(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q: torch.Tensor, fk: TipKinematics) -> torch.Tensor:
        B = q.shape[0]
        c, s = torch.cos(q), torch.sin(q)
        zero, one = torch.zeros_like(c), torch.ones_like(c)
        rz = torch.stack([c, -s, zero, s, c, zero, zero, zero, one], dim=-1).view(B, 7, 3, 3)
        m = fk.rot @ rz  # (B, 7, 3, 3): A_i's rotation then the joint's rotation
        R = fk.rot0.expand(B, 3, 3)  # identity
        p = q.new_zeros(B, 3, 1)
        need_jac = ctx.needs_input_grad[0]
        origins, axes = [], []
        for i in range(7):
            p = torch.baddbmm(p, R, fk.trans[i].expand(B, 3, 1))  # joint i's origin
            R = R @ m[:, i]
            if need_jac:
                origins.append(p)
                axes.append(R[:, :, 2])  # Rz keeps the z axis: joint i's axis in the base frame
        tip = torch.baddbmm(p, R, fk.tip_offset.expand(B, 3, 1)).squeeze(-1)
        if need_jac:
            o = torch.stack(origins).squeeze(-1)  # (7, B, 3)
            ctx.save_for_backward(torch.linalg.cross(torch.stack(axes), tip.unsqueeze(0) - o, dim=-1))
        return tip

    @staticmethod
    def backward(ctx, grad_tip: torch.Tensor):
        (jac,) = ctx.saved_tensors  # (7, B, 3): d tip / d q_j
        return torch.einsum("jbc,bc->bj", jac, grad_tip), None


class TipKinematics:
    """What the STM loops need from the kinematics: tip_position (..., 7) -> (..., 3), lower, upper."""

    def __init__(self, kin: SawyerKinematics | None = None):
        kin = kin if kin is not None else default_kinematics(torch.float32)
        self.kin, self.dtype = kin, kin.dtype
        self.lower, self.upper = kin.lower, kin.upper
        chain = kin.chain
        if not torch.all(chain.axes == torch.tensor([0.0, 0.0, 1.0], dtype=chain.axes.dtype)):
            raise ValueError("TipKinematics expects every arm joint to rotate about its own z axis")
        frames = {chain.find_frame(n).joint.name: n for n in chain.get_frame_names(exclude_fixed=True)}
        idx = chain.get_frame_indices(*[frames[j] for j in chain.get_joint_parameter_names()], TIP_LINK)
        with torch.no_grad():
            T0 = chain.forward_kinematics_tensor(torch.zeros(1, 7, dtype=kin.dtype))[idx, 0].double()
        rel = [T0[0]] + [torch.linalg.inv(T0[i - 1]) @ T0[i] for i in range(1, 8)]
        self.rot = torch.stack([r[:3, :3] for r in rel[:7]]).to(kin.dtype)  # (7, 3, 3)
        self.trans = torch.stack([r[:3, 3:] for r in rel[:7]]).to(kin.dtype)  # (7, 3, 1)
        self.tip_offset = rel[7][:3, 3:].to(kin.dtype)
        self.rot0 = torch.eye(3, dtype=kin.dtype)
        self._check()

    def _check(self) -> None:
        q = self.kin.neutral + torch.linspace(-1.0, 1.0, 7 * 16, dtype=self.dtype).reshape(16, 7).roll(3, 0)
        with torch.no_grad():
            err = (self.tip_position(q) - self.kin.tip_position(q)).abs().max().item()
        if err > (1e-5 if self.dtype == torch.float32 else 1e-10):
            raise ValueError(f"TipKinematics differs from pytorch-kinematics by {err:.2e} m; unsupported chain")

    def tip_position(self, q: torch.Tensor) -> torch.Tensor:
        q = torch.as_tensor(q, dtype=self.dtype)
        lead = q.shape[:-1]
        return _TipPosition.apply(q.reshape(-1, 7), self).reshape(*lead, 3)

    def clamp(self, q: torch.Tensor) -> torch.Tensor:
        return torch.clamp(q, self.lower, self.upper)


_DEFAULT: dict[torch.dtype, TipKinematics] = {}


def default_tip_kinematics(dtype: torch.dtype = torch.float32) -> TipKinematics:
    """A shared instance over envs.kinematics.default_kinematics(dtype)."""
    if dtype not in _DEFAULT:
        _DEFAULT[dtype] = TipKinematics(default_kinematics(dtype))
    return _DEFAULT[dtype]
