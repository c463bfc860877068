"""Batched, differentiable forward kinematics and Jacobians of the Sawyer arm.

Built with pytorch-kinematics from our URDF. Joint vectors have shape (..., 7)
(right_j0..right_j6); results keep the leading dimensions. pybullet is the
independent check of these numbers (see tests/test_kinematics.py).
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np
import torch

from envs.robot import ARM_JOINTS, HAND_LINK, LIMITS, NEUTRAL_Q, TIP_LINK, URDF_PATH, URDFError, read_urdf


@dataclass
class Poses:
    """Positions (..., 3) and rotation matrices (..., 3, 3) of the hand and the tool tip."""

    hand_pos: torch.Tensor
    hand_rot: torch.Tensor
    tip_pos: torch.Tensor
    tip_rot: torch.Tensor


class SawyerKinematics:
    """Forward kinematics and Jacobian of `right_gripper_tip` (and `right_hand`)."""

    def __init__(self, urdf_path: str | Path = URDF_PATH, dtype: torch.dtype = torch.float32, device="cpu"):
        import pytorch_kinematics as pk  # here: ~0.45 s of import, not paid by processes without FK

        text = read_urdf(urdf_path)
        try:
            chain = pk.build_serial_chain_from_urdf(text, TIP_LINK)
        except Exception as exc:  # pytorch-kinematics raises assorted errors for bad trees
            raise URDFError(f"cannot build a kinematic chain from {urdf_path}: {exc}") from None
        self.chain = chain.to(dtype=dtype, device=device)
        names = self.chain.get_joint_parameter_names()
        if tuple(names) != ARM_JOINTS:
            raise URDFError(f"kinematic chain joints {names} differ from {ARM_JOINTS}")
        self.urdf_path, self.dtype, self.device = Path(urdf_path), dtype, torch.device(device)
        self._hand_idx = int(self.chain.get_frame_indices(HAND_LINK)[0])
        self._tip_idx = int(self.chain.get_frame_indices(TIP_LINK)[0])
        self.lower = torch.as_tensor(LIMITS.lower, dtype=dtype, device=device)
        self.upper = torch.as_tensor(LIMITS.upper, dtype=dtype, device=device)
        self.neutral = torch.as_tensor(NEUTRAL_Q, dtype=dtype, device=device)

    def _transforms(self, q: torch.Tensor) -> tuple[torch.Tensor, tuple]:
        q = torch.as_tensor(q, dtype=self.dtype, device=self.device)
        if q.shape[-1] != 7:
            raise ValueError(f"expected joint vectors of size 7, got shape {tuple(q.shape)}")
        lead = q.shape[:-1]
        return self.chain.forward_kinematics_tensor(q.reshape(-1, 7)), lead

    def tip_position(self, q: torch.Tensor) -> torch.Tensor:
        """Tool-tip position (..., 3): the hot path of rollouts and training."""
        T, lead = self._transforms(q)
        return T[self._tip_idx, :, :3, 3].reshape(*lead, 3)

    def forward(self, q: torch.Tensor) -> Poses:
        T, lead = self._transforms(q)
        hand, tip = T[self._hand_idx], T[self._tip_idx]
        return Poses(
            hand_pos=hand[:, :3, 3].reshape(*lead, 3),
            hand_rot=hand[:, :3, :3].reshape(*lead, 3, 3),
            tip_pos=tip[:, :3, 3].reshape(*lead, 3),
            tip_rot=tip[:, :3, :3].reshape(*lead, 3, 3),
        )

    __call__ = forward

    def jacobian(self, q: torch.Tensor) -> torch.Tensor:
        """Geometric Jacobian of the tool tip in the base frame, (..., 6, 7): rows vx vy vz wx wy wz."""
        q = torch.as_tensor(q, dtype=self.dtype, device=self.device)
        lead = q.shape[:-1]
        return self.chain.jacobian(q.reshape(-1, 7)).reshape(*lead, 6, 7)

    # joint-limit helpers -------------------------------------------------
    def within_limits(self, q: torch.Tensor, tol: float = 0.0) -> torch.Tensor:
        return ((q >= self.lower - tol) & (q <= self.upper + tol)).all(dim=-1)

    def clamp(self, q: torch.Tensor) -> torch.Tensor:
        return torch.maximum(torch.minimum(q, self.upper), self.lower)


@lru_cache(maxsize=4)
def default_kinematics(dtype: torch.dtype = torch.float32) -> SawyerKinematics:
    """A shared instance for the default URDF (building the chain takes ~50 ms)."""
    return SawyerKinematics(dtype=dtype)


def tip_position_np(q: np.ndarray) -> np.ndarray:
    """Convenience: tool-tip positions for numpy joint vectors (..., 7), in float64."""
    with torch.no_grad():
        return default_kinematics(torch.float64).tip_position(torch.as_tensor(q, dtype=torch.float64)).numpy()
