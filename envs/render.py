"""3D figures of a task's demonstrations (or, for evaluation-only tasks, of the expert
on a few episodes): tip paths, starts, goals, the table and the blocks."""

from __future__ import annotations

from pathlib import Path

import matplotlib

from envs.figure_files import save_figure

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from mpl_toolkits.mplot3d.art3d import Poly3DCollection  # noqa: E402

from envs.kinematics import tip_position_np  # noqa: E402
from envs.sim import TABLE_CENTER_XY, TABLE_HALF_EXTENTS, TABLE_TOP_Z  # noqa: E402
from envs.tasks.base import Demos, Task  # noqa: E402

MAX_PATHS = 50  # more paths than this turn into a blur; the title says how many are shown
MAX_PATHS_WITH_BLOCKS = 12  # each path of a block task also draws its goal's blocks


def _cube_faces(bottom_centre, size: float) -> list[np.ndarray]:
    x, y, z = bottom_centre
    h = size / 2
    c = np.array([[x + sx * h, y + sy * h, z + sz * size] for sz in (0, 1) for sy in (-1, 1) for sx in (-1, 1)])
    idx = [(0, 1, 3, 2), (4, 5, 7, 6), (0, 1, 5, 4), (2, 3, 7, 6), (0, 2, 6, 4), (1, 3, 7, 5)]
    return [c[list(f)] for f in idx]


def _draw_cube(ax, bottom_centre, size: float, color, alpha: float = 0.35) -> None:
    ax.add_collection3d(Poly3DCollection(_cube_faces(bottom_centre, size), facecolor=color, edgecolor="k",
                                         linewidths=0.3, alpha=alpha))


def _goal_points(task: Task, psi_rows: np.ndarray) -> np.ndarray:
    """Distinct goal positions in a psi sequence (tasks whose psi is a position)."""
    if task.layout.psi_dim != 3:
        return np.zeros((0, 3))
    keep = np.ones(len(psi_rows), dtype=bool)
    keep[1:] = np.any(np.abs(np.diff(psi_rows, axis=0)) > 1e-9, axis=1)
    return psi_rows[keep]


def _paths_from_demos(demos: Demos) -> tuple[list[np.ndarray], list[np.ndarray]]:
    tips = tip_position_np(demos.q)
    n = len(demos)
    paths = [tips[i, : demos.lengths[i] + 1] for i in range(n)]
    psis = [demos.psi[i, : demos.lengths[i] + 1] for i in range(n)]
    return paths, psis


def _paths_from_episodes(task: Task, n: int) -> tuple[list[np.ndarray], list[np.ndarray]]:
    paths, psis = [], []
    for ep in task.episodes(n, seed=0):
        q, _ = task.expert_episode(ep)
        paths.append(tip_position_np(q))
        psis.append(ep.psi)
    return paths, psis


def render_task(task: Task, demos: Demos | None, out: Path, n_episodes: int = 6) -> list[Path]:
    """Draw `demos` (or, when None, the expert on `n_episodes` episodes of an evaluation-only
    task) to out (.png) and the .pdf beside it; returns both paths."""
    if demos is not None:
        paths, psis = _paths_from_demos(demos)
        what = f"{len(paths)} demonstrations"
    else:
        paths, psis = _paths_from_episodes(task, n_episodes)
        what = f"expert on {len(paths)} evaluation episodes"
    total = len(paths)
    block = task.block_size
    limit = MAX_PATHS_WITH_BLOCKS if block else MAX_PATHS
    shown = np.linspace(0, total - 1, min(total, limit)).round().astype(int)
    if len(shown) < total:
        what += f" ({len(shown)} shown)"

    fig = plt.figure(figsize=(8.5, 7))
    ax = fig.add_subplot(projection="3d")
    colors = plt.cm.viridis(np.linspace(0, 1, len(shown)))
    pts = [np.zeros((1, 3))]
    goals_drawn = switched_drawn = False
    for c, i in zip(colors, shown, strict=True):
        p = paths[i]
        ax.plot(p[:, 0], p[:, 1], p[:, 2], color=c, lw=1.0, alpha=0.85)
        ax.scatter(*p[0], color=c, s=12, marker="o")
        goals = _goal_points(task, psis[i])
        if len(goals):  # the first goal, then any goal it switches to
            ax.scatter(*goals[0], color="crimson", marker="*", s=70, edgecolor="k", linewidths=0.3,
                       label=None if goals_drawn else "goal", depthshade=False)
            if len(goals) > 1:
                ax.scatter(goals[1:, 0], goals[1:, 1], goals[1:, 2], color="darkorange", marker="D", s=30,
                           edgecolor="k", linewidths=0.3, depthshade=False,
                           label=None if switched_drawn else "later goal(s)")
                switched_drawn = True
            goals_drawn = True
            if block:
                _draw_goal_blocks(ax, goals, block, c)
        pts += [p, goals]
    if block:
        for bottom in task.scene_blocks():
            _draw_cube(ax, bottom, block, "tab:red", alpha=0.6)
            pts.append(np.array([bottom]))
        ax.scatter([], [], color="tab:red", marker="s", s=40, label="block at the start")
        ax.scatter([], [], color="lightgrey", edgecolor="k", marker="s", s=40, label="placed block / support")
    for label, point in task.landmarks().items():
        ax.scatter(*point, color="k", marker="+", s=60, label=label)
    note = task.describe_paths(psis)
    what += f", {note}" if note else ""
    ax.scatter([], [], color="grey", s=12, marker="o", label="start")
    pts = np.concatenate([p.reshape(-1, 3) for p in pts[1:]])
    lo, hi = pts.min(axis=0) - 0.03, pts.max(axis=0) + 0.03
    lo[2] = min(lo[2], TABLE_TOP_Z)
    _draw_table(ax, lo, hi)
    ax.set_xlim(lo[0], hi[0])
    ax.set_ylim(lo[1], hi[1])
    ax.set_zlim(lo[2], hi[2])
    ax.set_box_aspect(hi - lo)
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.set_zlabel("z (m)")
    ax.view_init(elev=28, azim=-125)
    ax.set_title(f"{task.name}: tool-tip paths, {what}\n(robot base frame; table top z = {TABLE_TOP_Z} m)")
    ax.legend(loc="upper left", fontsize=8)
    fig.tight_layout()
    out = Path(out)
    return [Path(p) for p in save_figure(fig, out.with_suffix(""), dpi=150)]


def _draw_goal_blocks(ax, goals: np.ndarray, size: float, color) -> None:
    """Blocks placed at the goals (psi is the position of a placed block's bottom face),
    with the support blocks under a goal above the table in grey. A goal that was
    switched away from (another xy than the last goal) gets no block."""
    cubes: dict[tuple[float, float, int], bool] = {}
    final_xy = goals[-1, :2]
    for g in goals[np.linalg.norm(goals[:, :2] - final_xy, axis=1) < 1e-6]:
        level = int(round((g[2] - TABLE_TOP_Z) / size))
        for k in range(level + 1):
            key = (round(float(g[0]), 4), round(float(g[1]), 4), k)
            cubes[key] = cubes.get(key, False) or k == level
    for (x, y, k), placed in cubes.items():
        _draw_cube(ax, (x, y, TABLE_TOP_Z + k * size), size, color if placed else "lightgrey",
                   alpha=0.3 if placed else 0.15)


def _draw_table(ax, lo, hi) -> None:
    """The part of the table top that falls inside the plotted x-y range."""
    cx, cy = TABLE_CENTER_XY
    hx, hy = TABLE_HALF_EXTENTS[:2]
    x0, x1 = max(lo[0], cx - hx), min(hi[0], cx + hx)
    y0, y1 = max(lo[1], cy - hy), min(hi[1], cy + hy)
    if x0 >= x1 or y0 >= y1:
        return
    z = TABLE_TOP_Z
    ax.add_collection3d(Poly3DCollection([np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]])],
                                         facecolor=(0.55, 0.4, 0.25), alpha=0.18, edgecolor="none"))
