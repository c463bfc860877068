"""Tool-tip forward kinematics for the training and rollout loops: a handful of ops, cheap backward.

The STM feeds back phi = f(tip(q)) at every self-fed step, so the tip position's
forward and backward run once per step in Python-sized batches, where per-op
overhead dominates. envs.kinematics.SawyerKinematics (pytorch-kinematics) computes
every frame's full pose and, backward, spreads the gradient over all of them.

Here the serial chain T_tip(q) = A_0 Rz(q_0) A_1 Rz(q_1) ... A_6 Rz(q_6) A_tip, with
the fixed A_j read off pytorch-kinematics' frames at q = 0 (in float64, and checked
against it at random configurations on construction), is expanded once into closed
form. Rz(q) = cos q C + sin q S + P, so the first joints' transform
T = A_0 Rz(q_0) ... Rz(q_2) and the rest's tip point p = A_3 Rz(q_3) ... A_tip (homogeneous)
are each linear in the products of one factor per joint out of (cos q_j, sin q_j, 1):
a few dozen monomials, of which only those with a nonzero coefficient are kept.

Forward: sin of one affine map of q gives every factor (cos q = sin(q + pi/2)); one
gather of each monomial's factors and their product; one matrix product to the
entries of T and p, one elementwise product and one more matrix product to T p.
The Jacobian comes out of the same ops: a monomial's derivative by q_j swaps its
factor of joint j (cos -> -sin, sin -> cos, 1 -> 0), and d(T p)/dq_j is (dT/dq_j) p or
T (dp/dq_j), so each joint is one more "slot" of the gather with the derivatives of
its group's monomials. The backward multiplies the gradient with the saved Jacobian;
no autograd graph.
"""

from __future__ import annotations

import copy
import itertools

import torch

from envs.kinematics import SawyerKinematics, default_kinematics
from envs.robot import TIP_LINK

JOINTS = 7
SPLIT = 3  # joints 0..SPLIT-1 give the transform T, the others the point p
COS, SIN, ONE = 0, 1, 2  # a monomial's factor of one joint
# the gather's columns: cos q (JOINTS), sin q (JOINTS), -sin q (JOINTS), then 1 and 0
COL_COS, COL_SIN, COL_NEG_SIN, COL_ONE, COL_ZERO = 0, JOINTS, 2 * JOINTS, 3 * JOINTS, 3 * JOINTS + 1
PRUNE = 1e-12  # coefficients below this (m, or unitless for rotations) are rounding noise of zeros


def _factors(q: torch.Tensor, fk: TipKinematics) -> torch.Tensor:
    """(B, 3 * JOINTS + 2): the gather's columns, as sin(q @ signs + phases) in one product and one sine."""
    return torch.sin(torch.addmm(fk.phases, q, fk.signs))


class _Plan:
    """One gather's `index` into the factors: (degree, slots, monomials)."""

    def __init__(self, index: torch.Tensor):
        self.degree, self.slots, self.monomials = index.shape
        self.index = index.flatten()


def _slots(q: torch.Tensor, fk: TipKinematics, plan: _Plan) -> torch.Tensor:
    """(B, slots, 3): T p for each slot's monomials (slot 0: the tip; slot 1 + j: its derivative by q_j)."""
    B = q.shape[0]
    monomials = _factors(q, fk).index_select(1, plan.index).view(B, plan.degree, plan.slots * plan.monomials).prod(1)
    entries = torch.mm(monomials.view(B * plan.slots, plan.monomials), fk.coef)  # T (3, 4), then p beside each row
    return torch.mm(entries[:, :12] * entries[:, 12:], fk.row_sums).view(B, plan.slots, 3)  # T p


class _TipPosition(torch.autograd.Function):
    @staticmethod
    def forward(ctx, q: torch.Tensor, fk: TipKinematics) -> torch.Tensor:
        if not ctx.needs_input_grad[0]:
            return _slots(q, fk, fk.tip_plan).view(-1, 3)
        out = _slots(q, fk, fk.grad_plan)
        ctx.save_for_backward(out)
        return out[:, 0]

    @staticmethod
    @torch.autograd.function.once_differentiable
    def backward(ctx, grad_tip: torch.Tensor):
        (out,) = ctx.saved_tensors
        return (out[:, 1:] * grad_tip.unsqueeze(1)).sum(-1), None


def _factor_table(dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """signs (JOINTS, columns) and phases (columns,): cos q = sin(q + pi/2), -sin q = sin(-q), 1 = sin(pi/2)."""
    eye = torch.eye(JOINTS, dtype=dtype)
    signs = torch.cat([eye, eye, -eye, torch.zeros(JOINTS, 2, dtype=dtype)], dim=1)
    phases = torch.zeros(signs.shape[1], dtype=dtype)
    phases[COL_COS:COL_COS + JOINTS] = phases[COL_ONE] = torch.pi / 2
    return signs, phases


def _polynomial(frames: torch.Tensor, end: torch.Tensor) -> torch.Tensor:
    """Coefficients (4, *end.shape[1:], 3, ..., 3) of prod_j f_j[k_j], f_j = (cos q_j, sin q_j, 1), in
    frames[0] Rz(q_0) frames[1] Rz(q_1) ... end (homogeneous 4x4 frames; end (4,) a point or (4, 4))."""
    dtype = frames.dtype
    rz = torch.zeros(3, 4, 4, dtype=dtype)  # Rz(q) = cos q rz[COS] + sin q rz[SIN] + rz[ONE], homogeneous
    rz[COS, 0, 0] = rz[COS, 1, 1] = rz[SIN, 1, 0] = rz[ONE, 2, 2] = rz[ONE, 3, 3] = 1.0
    rz[SIN, 0, 1] = -1.0
    coef = end
    for a in reversed(frames):
        coef = torch.einsum("kab,b...->ak...", a @ rz, coef)
    return coef.movedim(-1, 1) if end.dim() == 2 else coef  # the end's column index next to the row's


def _monomials(coef: torch.Tensor, joints: range) -> list[tuple[tuple[int, ...], torch.Tensor]]:
    """(factor kinds per joint of `joints`, coefficients) of the monomials with a nonzero coefficient."""
    flat = coef.reshape(-1, *coef.shape[-len(joints):])
    return [(kinds, flat[(slice(None), *kinds)]) for kinds in itertools.product((COS, SIN, ONE), repeat=len(joints))
            if flat[(slice(None), *kinds)].abs().max() > PRUNE]


def _columns(kinds: tuple[int, ...], joints: range, by: int | None) -> list[int]:
    """The factor columns of a monomial, or of its derivative by joint `by` (None: the monomial itself)."""
    if by is not None and kinds[by - joints.start] == ONE:
        return [COL_ZERO]
    cols = []
    for j, k in zip(joints, kinds, strict=True):
        if j == by:
            cols.append(COL_NEG_SIN + j if k == COS else COL_COS + j)
        elif k != ONE:
            cols.append((COL_COS if k == COS else COL_SIN) + j)
    return cols


class TipKinematics:
    """What the STM loops need from the kinematics: tip_position (..., 7) -> (..., 3), lower, upper."""

    def __init__(self, kin: SawyerKinematics | None = None):
        kin = kin if kin is not None else default_kinematics(torch.float32)
        self.kin, self.dtype = kin, kin.dtype
        self.lower, self.upper = kin.lower, kin.upper
        frames = self._frames(kin if kin.dtype == torch.float64 else SawyerKinematics(kin.urdf_path, torch.float64))
        first, rest = range(SPLIT), range(SPLIT, JOINTS)
        transform = _monomials(_polynomial(frames[:SPLIT], torch.eye(4, dtype=frames.dtype))[:3], first)
        point = _monomials(_polynomial(frames[SPLIT:JOINTS], frames[JOINTS, :, 3]), rest)
        # monomials -> T (3 x 4), then p (4,) once for each of T's rows; row_sums: T p out of their products
        self.coef = torch.zeros(len(transform) + len(point), 24, dtype=torch.float64)
        self.coef[: len(transform), :12] = torch.stack([c.flatten() for _, c in transform])
        self.coef[len(transform):, 12:] = torch.stack([c for _, c in point]).repeat(1, 3)
        self.coef = self.coef.to(self.dtype)
        self.row_sums = torch.eye(3, dtype=self.dtype).repeat_interleave(4, dim=0)
        self.signs, self.phases = _factor_table(self.dtype)
        self.tip_plan = self._plan(transform, point, first, rest, with_jacobian=False)
        self.grad_plan = self._plan(transform, point, first, rest, with_jacobian=True)
        self._check()

    @staticmethod
    def _frames(kin: SawyerKinematics) -> torch.Tensor:
        """(JOINTS + 1, 4, 4): each joint's frame in its parent's at q = 0, then the tip's in the last joint's."""
        chain = kin.chain
        if not torch.all(chain.axes == torch.tensor([0.0, 0.0, 1.0], dtype=chain.axes.dtype)):
            raise ValueError("TipKinematics expects every arm joint to rotate about its own z axis")
        names = {chain.find_frame(n).joint.name: n for n in chain.get_frame_names(exclude_fixed=True)}
        idx = chain.get_frame_indices(*[names[j] for j in chain.get_joint_parameter_names()], TIP_LINK)
        with torch.no_grad():
            T0 = chain.forward_kinematics_tensor(torch.zeros(1, JOINTS, dtype=kin.dtype))[idx, 0]
        return torch.stack([T0[0]] + [torch.linalg.inv(T0[i - 1]) @ T0[i] for i in range(1, JOINTS + 1)])

    @staticmethod
    def _plan(transform, point, first: range, rest: range, with_jacobian: bool) -> _Plan:
        """Slot 0: T's and p's monomials; slot 1 + j: d(T p)/dq_j = dT/dq_j p or T dp/dq_j (the other group's
        monomials as they are, so that the same product T p gives the derivative)."""
        rows = []
        for by in [None] + (list(range(JOINTS)) if with_jacobian else []):
            for group, joints in ((transform, first), (point, rest)):
                rows += [_columns(kinds, joints, by if by in joints else None) for kinds, _ in group]
        degree = max(map(len, rows))
        index = torch.tensor([r + [COL_ONE] * (degree - len(r)) for r in rows])
        return _Plan(index.view(-1, len(transform) + len(point), degree).permute(2, 0, 1).contiguous())

    def _check(self) -> None:
        q = self.kin.neutral + torch.linspace(-1.0, 1.0, JOINTS * 16, dtype=self.dtype).reshape(16, JOINTS).roll(3, 0)
        with torch.no_grad():
            err = (self.tip_position(q) - self.kin.tip_position(q)).abs().max().item()
        if err > (1e-5 if self.dtype == torch.float32 else 1e-10):
            raise ValueError(f"TipKinematics differs from pytorch-kinematics by {err:.2e} m; unsupported chain")

    def tip_position(self, q: torch.Tensor) -> torch.Tensor:
        q = torch.as_tensor(q, dtype=self.dtype)
        if q.dim() == 2:
            return _TipPosition.apply(q, self)
        return _TipPosition.apply(q.reshape(-1, JOINTS), self).reshape(*q.shape[:-1], 3)

    def clamp(self, q: torch.Tensor) -> torch.Tensor:
        return torch.clamp(q, self.lower, self.upper)

    def to(self, device: torch.device | str) -> TipKinematics:
        """This kinematics with its constants on `device` (itself where they are there already); the
        pytorch-kinematics chain it was read from stays where it is."""
        device = torch.device(device)
        if self.coef.device == device:
            return self
        moved = self.__dict__.setdefault("_moved", {})  # one copy per device (rollouts ask once per call)
        if device in moved:
            return moved[device]
        out = moved[device] = copy.copy(self)
        for name in ("coef", "row_sums", "signs", "phases", "lower", "upper"):
            setattr(out, name, getattr(self, name).to(device))
        for name in ("tip_plan", "grad_plan"):
            plan = copy.copy(getattr(self, name))
            plan.index = plan.index.to(device)
            setattr(out, name, plan)
        return out


_DEFAULT: dict[torch.dtype, TipKinematics] = {}


def default_tip_kinematics(dtype: torch.dtype = torch.float32) -> TipKinematics:
    """A shared instance over envs.kinematics.default_kinematics(dtype)."""
    if dtype not in _DEFAULT:
        _DEFAULT[dtype] = TipKinematics(default_kinematics(dtype))
    return _DEFAULT[dtype]
