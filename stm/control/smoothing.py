"""Trajectory smoothing of STM skeletons (the paper's post-processing).

Given a skeleton q~_0..q~_T (B, T+1, 7), find q with q_0 = q~_0 (the start is the
robot's measured configuration and stays fixed) that minimises

    V(q) = sum_t ||q_t - q~_t||^2 + gamma * sum_t ||q_{t+1} - q_t||^2
           [+ goal_weight * ||tip(q_T) - goal||^2]

- `smooth_gd`: the paper's method, batched gradient descent (Nesterov momentum,
  step size from the curvature bound) with autograd through the differentiable
  forward kinematics for the optional goal term.
- `smooth_exact`: the exact minimiser of the quadratic part. Setting dV/dq_t = 0
  gives, per joint, the symmetric tridiagonal system
      (1 + 2 gamma) q_t - gamma (q_{t-1} + q_{t+1}) = q~_t      (0 < t < T)
      (1 + gamma)   q_T - gamma q_{T-1}             = q~_T
  with q_0 moved to the right-hand side; one banded Cholesky solve covers every
  trajectory and joint (they share the matrix).
- `smoothness_metrics`: mean squared jerk, peak joint speed, deviation from the
  skeleton, final goal error.
- `smoothing_study`: before/after metrics and the tip-path figure for four goals.
"""

from __future__ import annotations

import logging
import time
from pathlib import Path

import numpy as np
import scipy.linalg
import torch

from envs.figure_files import save_figure
from envs.kinematics import SawyerKinematics, default_kinematics

log = logging.getLogger(__name__)


def _as_tensor(x, dtype=torch.float64) -> torch.Tensor:
    return x if isinstance(x, torch.Tensor) else torch.as_tensor(np.asarray(x, dtype=float), dtype=dtype)


def _as_numpy(x) -> np.ndarray:
    return x.detach().cpu().double().numpy() if isinstance(x, torch.Tensor) else np.asarray(x, dtype=float)


def _check_skeleton(skeleton) -> None:
    if skeleton.ndim != 3 or skeleton.shape[-1] != 7 or skeleton.shape[1] < 2:
        raise ValueError(f"skeleton must have shape (B, T+1, 7) with T >= 1, got {tuple(skeleton.shape)}")
    finite = torch.isfinite(skeleton).all() if isinstance(skeleton, torch.Tensor) else np.isfinite(skeleton).all()
    if not bool(finite):
        raise ValueError("skeleton contains NaN or infinite joint values")


def smoothing_objective(q: torch.Tensor, skeleton: torch.Tensor, gamma: float, goal: torch.Tensor | None = None,
                        goal_weight: float = 0.0, kin: SawyerKinematics | None = None) -> torch.Tensor:
    """V per trajectory, shape (B,)."""
    v = (q - skeleton).square().sum(dim=(1, 2)) + gamma * (q[:, 1:] - q[:, :-1]).square().sum(dim=(1, 2))
    if goal is not None and goal_weight > 0:
        kin = kin or default_kinematics(q.dtype)
        v = v + goal_weight * (kin.tip_position(q[:, -1]) - goal).square().sum(-1)
    return v


def smooth_gd(skeleton, gamma: float = 5.0, goal=None, goal_weight: float = 0.0, iters: int = 300,
              lr: float | None = None, momentum: float | None = None, tol: float = 1e-9,
              kin: SawyerKinematics | None = None):
    """Minimise V by gradient descent from the skeleton; returns q like the input
    (numpy in -> numpy out). Stops early when every gradient entry is below `tol`.

    Default step size 1/L with L an upper bound of V's curvature: 2 (1 + 4 gamma)
    for the quadratic part (the path Laplacian's eigenvalues are < 4), plus
    2 goal_weight ||J||^2 (1.5x the tip Jacobian at the skeleton's end) for the
    goal term. Default momentum (sqrt(k) - 1) / (sqrt(k) + 1) with k = L / 2,
    the quadratic part's condition number bound.
    """
    numpy_in = not isinstance(skeleton, torch.Tensor)
    sk = _as_tensor(skeleton).detach()
    _check_skeleton(sk)
    if gamma < 0 or goal_weight < 0:
        raise ValueError(f"gamma and goal_weight must be >= 0, got {gamma}, {goal_weight}")
    use_goal = goal is not None and goal_weight > 0
    if use_goal:
        kin = kin or default_kinematics(sk.dtype)
        goal = _as_tensor(goal, sk.dtype).reshape(-1, 3).expand(sk.shape[0], 3)
    curvature = 2.0 * (1.0 + 4.0 * gamma)
    if use_goal:
        with torch.no_grad():
            jn = torch.linalg.matrix_norm(kin.jacobian(sk[:, -1])[:, :3], ord=2).max()
        curvature += 2.0 * goal_weight * 1.5 * float(jn) ** 2
    lr = lr if lr is not None else 1.0 / curvature
    if momentum is None:
        k = curvature / 2.0
        momentum = (k**0.5 - 1.0) / (k**0.5 + 1.0)
    free = sk[:, 1:].clone().requires_grad_(True)
    opt = torch.optim.SGD([free], lr=lr, momentum=momentum, nesterov=momentum > 0)
    start = sk[:, :1]
    for i in range(iters):
        opt.zero_grad(set_to_none=True)
        q = torch.cat([start, free], dim=1)
        v = smoothing_objective(q, sk, gamma, goal if use_goal else None, goal_weight, kin).sum()
        v.backward()
        if free.grad.abs().max() < tol:
            log.debug("smooth_gd converged after %d iterations", i)
            break
        opt.step()
    out = torch.cat([start, free.detach()], dim=1)
    return out.numpy() if numpy_in else out


def _banded_matrix(T: int, gamma: float) -> np.ndarray:
    """Upper banded form (2, T) of the SPD tridiagonal matrix over q_1..q_T."""
    ab = np.empty((2, T))
    ab[0, 0] = 0.0
    ab[0, 1:] = -gamma
    ab[1, :] = 1.0 + 2.0 * gamma
    ab[1, -1] = 1.0 + gamma
    return ab


def smooth_exact(skeleton, gamma: float = 5.0):
    """Exact minimiser of the quadratic part (no goal term), same type as the input."""
    torch_in = isinstance(skeleton, torch.Tensor)
    sk = skeleton.detach().cpu().double().numpy() if torch_in else np.asarray(skeleton, dtype=float)
    _check_skeleton(sk)
    if gamma < 0:
        raise ValueError(f"gamma must be >= 0, got {gamma}")
    B, T1, J = sk.shape
    T = T1 - 1
    rhs = sk[:, 1:].copy()  # (B, T, J)
    rhs[:, 0] += gamma * sk[:, 0]
    # one factorisation, B * J right-hand sides as columns
    cols = rhs.transpose(1, 0, 2).reshape(T, B * J)
    sol = scipy.linalg.solveh_banded(_banded_matrix(T, gamma), cols, check_finite=False)
    q = np.concatenate([sk[:, :1], sol.reshape(T, B, J).transpose(1, 0, 2)], axis=1)
    if torch_in:
        return torch.as_tensor(q, dtype=skeleton.dtype, device=skeleton.device)
    return q


def smoothness_metrics(q, skeleton=None, goal=None, step_seconds: float = 0.1, reduce: bool = True) -> dict:
    """Metrics of joint trajectories q (B, T+1, 7), means over the batch (or (B,) arrays
    with reduce=False):
      mean_sq_jerk        mean over steps and joints of (third difference / dt^3)^2  [rad^2/s^6]
      peak_joint_speed    max over steps and joints of |q_{t+1} - q_t| / dt          [rad/s]
      deviation_rad       mean over steps of ||q_t - q~_t||                           [rad]
      tip_deviation_m     mean over steps of ||tip(q_t) - tip(q~_t)||                 [m]
      goal_error_m        ||tip(q_T) - goal||                                         [m]
    """
    q = _as_numpy(q)
    _check_skeleton(q)
    dt = float(step_seconds)
    out: dict[str, np.ndarray] = {}
    if q.shape[1] >= 4:
        jerk = np.diff(q, n=3, axis=1) / dt**3
        out["mean_sq_jerk"] = (jerk**2).mean(axis=(1, 2))
    out["peak_joint_speed"] = np.abs(np.diff(q, axis=1)).max(axis=(1, 2)) / dt
    need_fk = skeleton is not None or goal is not None
    if need_fk:
        kin = default_kinematics(torch.float64)
        with torch.no_grad():
            tip = kin.tip_position(torch.as_tensor(q)).numpy()
    if skeleton is not None:
        sk = _as_numpy(skeleton)
        if sk.shape != q.shape:
            raise ValueError(f"skeleton shape {sk.shape} differs from trajectory shape {q.shape}")
        out["deviation_rad"] = np.linalg.norm(q - sk, axis=-1).mean(axis=1)
        with torch.no_grad():
            sk_tip = kin.tip_position(torch.as_tensor(sk)).numpy()
        out["tip_deviation_m"] = np.linalg.norm(tip - sk_tip, axis=-1).mean(axis=1)
    if goal is not None:
        g = np.broadcast_to(np.asarray(goal, dtype=float).reshape(-1, 3), (q.shape[0], 3))
        out["goal_error_m"] = np.linalg.norm(tip[:, -1] - g, axis=-1)
    return {k: float(v.mean()) for k, v in out.items()} if reduce else out


# study --------------------------------------------------------------------------

def smoothing_study(skeletons=None, goals=None, *, gamma: float = 5.0, goal_weight: float = 50.0,
                    iters: int = 300, step_seconds: float = 0.1, seed: int = 0, steps: int = 60,
                    out_dir: str | Path | None = None, torch_threads: int = 1) -> dict:
    """Smooth skeletons (B, T+1, 7) reaching `goals` (B, 3) three ways (exact quadratic,
    gradient descent, gradient descent with the goal term) and measure them.

    Without skeletons: IK straight-line plans to the four reacher goals with STM-like
    jitter and drift (stm.control.plans.jittery_skeletons). Returns a flat metrics dict
    ('<variant>/<metric>' for variant in skeleton, exact, gd, gd_goal, plus timings);
    with `out_dir`, also writes the tip-path figure (PNG + PDF) and lists its paths
    under 'figures'.
    """
    from stm.control.plans import FOUR_GOALS, jittery_skeletons, straight_line_plans

    if skeletons is None:
        goals = FOUR_GOALS if goals is None else np.asarray(goals, dtype=float)
        skeletons = jittery_skeletons(straight_line_plans(goals, steps=steps), seed=seed)
    skeletons = np.asarray(skeletons, dtype=float)
    threads = torch.get_num_threads()
    torch.set_num_threads(torch_threads)  # small tensors: more threads only add hand-off waits
    try:
        t0 = time.perf_counter()
        exact = smooth_exact(skeletons, gamma)
        t1 = time.perf_counter()
        gd = smooth_gd(skeletons, gamma, iters=iters)
        t2 = time.perf_counter()
        gd_goal = None
        if goals is not None:
            gd_goal = smooth_gd(skeletons, gamma, goal=goals, goal_weight=goal_weight, iters=iters)
        t3 = time.perf_counter()
    finally:
        torch.set_num_threads(threads)
    results: dict = {"gamma": gamma, "goal_weight": goal_weight, "n_trajectories": len(skeletons),
                     "steps": skeletons.shape[1] - 1, "time_exact_s": t1 - t0, "time_gd_s": t2 - t1}
    variants = {"skeleton": skeletons, "exact": exact, "gd": gd}
    if gd_goal is not None:
        variants["gd_goal"] = gd_goal
        results["time_gd_goal_s"] = t3 - t2
    for name, q in variants.items():
        for k, v in smoothness_metrics(q, skeletons, goals, step_seconds).items():
            results[f"{name}/{k}"] = v
    results["gd_vs_exact_max_abs_rad"] = float(np.abs(gd - exact).max())
    if out_dir is not None:
        results["figures"] = plot_tip_paths(variants, goals, Path(out_dir) / "smoothing_tip_paths")
    return results


def plot_tip_paths(variants: dict[str, np.ndarray], goals=None, path_stem: str | Path = "smoothing_tip_paths",
                   max_panels: int = 4) -> list[str]:
    """One 3D panel per trajectory (up to `max_panels`): tip paths of each variant and
    the goal. Writes <path_stem>.png and .pdf; returns their paths."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from envs.kinematics import tip_position_np

    tips = {name: tip_position_np(q) for name, q in variants.items()}
    n = min(max_panels, next(iter(tips.values())).shape[0])
    fig = plt.figure(figsize=(4.2 * n, 4.2))
    styles = {"skeleton": dict(color="0.6", lw=1.0, marker=".", ms=3), "exact": dict(color="C0", lw=1.5),
              "gd": dict(color="C1", lw=1.5, ls="--"), "gd_goal": dict(color="C2", lw=2.0)}
    for i in range(n):
        ax = fig.add_subplot(1, n, i + 1, projection="3d")
        for name, tip in tips.items():
            ax.plot(*tip[i].T, label=name, **styles.get(name, {}))
        if goals is not None:
            ax.scatter(*np.asarray(goals, dtype=float).reshape(-1, 3)[i], color="red", marker="*", s=80, label="goal")
        pts = np.concatenate([tip[i] for tip in tips.values()])
        centre, half = (pts.max(0) + pts.min(0)) / 2, (pts.max(0) - pts.min(0)).max() / 2 + 0.02
        ax.set(xlim=(centre[0] - half, centre[0] + half), ylim=(centre[1] - half, centre[1] + half),
               zlim=(centre[2] - half, centre[2] + half))  # equal scales: straight stays straight
        ax.set_title(f"goal {i + 1}")
        ax.set_xlabel("x [m]")
        ax.set_ylabel("y [m]")
        ax.set_zlabel("z [m]")
        if i == 0:
            ax.legend(loc="upper left", fontsize=7)
    fig.suptitle("Tool-tip paths before and after smoothing")
    fig.tight_layout()
    return save_figure(fig, path_stem)
