"""Batched damped-least-squares inverse kinematics of the tool tip.

The IK experts of every task build their demonstrations from it: a Cartesian
path of the tip is solved waypoint by waypoint, each solve warm-started from
the previous one, which keeps the joint path continuous.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from envs.kinematics import SawyerKinematics, default_kinematics

DOWN = (0.0, 0.0, -1.0)  # the tool axis when the gripper points at the table


@dataclass
class IKResult:
    q: torch.Tensor  # (B, 7)
    pos_err: torch.Tensor  # (B,) m
    rot_err: torch.Tensor  # (B,) rad (0 when orientation is free)
    converged: torch.Tensor  # (B,) bool


def _orientation_error(rot: torch.Tensor, target_rot: torch.Tensor | None, axis: torch.Tensor | None) -> torch.Tensor:
    """Angular error vector (B, 3) that rotates the current frame towards the target."""
    if target_rot is not None:
        # 0.5 * sum_i r_i x rd_i: exact direction, magnitude sin(angle) for small errors
        return 0.5 * torch.cross(rot, target_rot, dim=-2).sum(dim=-1)
    if axis is not None:
        return torch.cross(rot[..., :, 2], axis.expand_as(rot[..., :, 2]), dim=-1)
    return torch.zeros(rot.shape[:-2] + (3,), dtype=rot.dtype)


def solve_ik(
    target_pos: torch.Tensor,
    q_init: torch.Tensor,
    *,
    tool_axis: tuple[float, float, float] | None = DOWN,
    target_rot: torch.Tensor | None = None,
    kin: SawyerKinematics | None = None,
    iters: int = 100,
    damping: float = 0.03,
    rot_weight: float = 0.5,
    tol_pos: float = 1e-4,
    tol_rot: float = 1e-3,
) -> IKResult:
    """Solve for joint positions (B, 7) that put the tool tip at target_pos (B, 3).

    Orientation: `target_rot` (B, 3, 3) constrains the full frame; otherwise
    `tool_axis` constrains only the tool's z axis (None: position only).
    Joint limits are enforced by clamping after every step.
    """
    kin = kin or default_kinematics(torch.float64)
    dtype = kin.dtype
    target_pos = torch.as_tensor(target_pos, dtype=dtype).reshape(-1, 3)
    q = torch.as_tensor(q_init, dtype=dtype).reshape(-1, 7).clone()
    q = q.expand(target_pos.shape[0], 7).clone() if q.shape[0] == 1 else q
    axis = None if tool_axis is None or target_rot is not None else torch.tensor(tool_axis, dtype=dtype)
    if target_rot is not None:
        target_rot = torch.as_tensor(target_rot, dtype=dtype).reshape(-1, 3, 3)
    constrain_rot = target_rot is not None or axis is not None
    eye = torch.eye(6 if constrain_rot else 3, dtype=dtype)
    for _ in range(iters):
        J, T = kin.chain.jacobian(q, ret_eef_pose=True)
        e_pos = target_pos - T[:, :3, 3]
        e_rot = _orientation_error(T[:, :3, :3], target_rot, axis)
        pos_err, rot_err = e_pos.norm(dim=-1), e_rot.norm(dim=-1)
        converged = (pos_err < tol_pos) & (rot_err < tol_rot)
        if bool(converged.all()):
            break
        if constrain_rot:
            e = torch.cat([e_pos, rot_weight * e_rot], dim=-1)
            Jw = torch.cat([J[:, :3], rot_weight * J[:, 3:]], dim=1)
        else:
            e, Jw = e_pos, J[:, :3]
        JJt = Jw @ Jw.transpose(1, 2) + (damping**2) * eye
        dq = (Jw.transpose(1, 2) @ torch.linalg.solve(JJt, e.unsqueeze(-1))).squeeze(-1)
        dq = torch.where(converged.unsqueeze(-1), torch.zeros_like(dq), dq)
        q = kin.clamp(q + dq)
    J, T = kin.chain.jacobian(q, ret_eef_pose=True)
    pos_err = (target_pos - T[:, :3, 3]).norm(dim=-1)
    rot_err = _orientation_error(T[:, :3, :3], target_rot, axis).norm(dim=-1)
    return IKResult(q=q, pos_err=pos_err, rot_err=rot_err, converged=(pos_err < tol_pos) & (rot_err < tol_rot))


def solve_path(path: torch.Tensor, q_start: torch.Tensor, **kwargs) -> IKResult:
    """Solve a tip path (B, T, 3) waypoint by waypoint from q_start (B, 7).

    Returns q of shape (B, T, 7); pos_err/rot_err are the worst over the path and
    converged is True where every waypoint converged.
    """
    path = torch.as_tensor(path)
    B, T, _ = path.shape
    q = torch.as_tensor(q_start).reshape(B, 7)
    qs, pos, rot, ok = [], [], [], []
    for t in range(T):
        res = solve_ik(path[:, t], q, **kwargs)
        q = res.q
        qs.append(q)
        pos.append(res.pos_err)
        rot.append(res.rot_err)
        ok.append(res.converged)
    return IKResult(
        q=torch.stack(qs, dim=1),
        pos_err=torch.stack(pos, dim=1).amax(dim=1),
        rot_err=torch.stack(rot, dim=1).amax(dim=1),
        converged=torch.stack(ok, dim=1).all(dim=1),
    )
