"""Where the stacking episodes fail, read from the rollouts themselves: {{ stacking("pick-place", "STUDY", ...) }}
in a RESULTS template. A tower is three pick-and-place sub-episodes in a row (envs/tasks/stack.py); each next
block starts where the last place ended, with the model restarted there. Per study (labelled by its setting, as
the lever table labels it: reports.analyses.levers) and variant, over every finished seed's stacking episodes: the share
of episodes whose tool tip came for block k (within REACH of the point where the block is grasped, during
block k's sub-episode), the share whose tower stands at least k blocks high, and the median closest approach to
each block. The figure draws both shares against the block."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pandas as pd

from reports import paper
from reports.analyses.levers import in_variant_order, rollout_rows
from reports.data.store import Study, order_variants
from reports.plotting import FigureResult, gap, legend_below, panel_grid, plt, save, variant_color

NAME, TITLE = "stacking", "Stacking: which block the episodes get to"
EVAL_TASK = "stack"
BLOCKS = 3
REACH = 0.02  # m from the grasp point: the tip came for the block (the gripper's clearance is ~5 mm a side)


def grasp_point() -> np.ndarray:
    """Where the tool tip grasps a block that waits at the pick position (base frame, m)."""
    from envs.blocks import PICK_XY  # here: envs pulls in pybullet
    from envs.sim import TABLE_TOP_Z
    from envs.tasks.pickplace_expert import GRASP_HEIGHT

    return np.array([*PICK_XY, TABLE_TOP_Z + GRASP_HEIGHT])


def episode_facts(arrays: dict[str, np.ndarray], sub_horizon: int, grasp: np.ndarray) -> pd.DataFrame:
    """One row per stacking episode: success, blocks in the tower and, per block k (1-based), the tip's closest
    approach to the grasp point during block k's sub-episode (`closest_k`, m)."""
    tip = np.asarray(arrays["tip"], float)
    rows = {"success": np.asarray(arrays["success"], float),
            "tower": np.asarray(arrays["blocks_in_tower"], float)}
    for k in range(BLOCKS):
        part = tip[:, k * sub_horizon: (k + 1) * sub_horizon + 1]
        rows[f"closest_{k + 1}"] = np.linalg.norm(part - grasp, axis=-1).min(axis=1)
    return pd.DataFrame(rows)


def stacking_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (study, variant) with stacking rollouts of `task`'s models (reports.analyses.levers.rollout_rows)."""
    from envs.tasks.stack import SUB_HORIZON

    grasp = grasp_point()
    return rollout_rows(studies, task, EVAL_TASK, lambda arrays: episode_facts(arrays, SUB_HORIZON, grasp))


def shares(facts: pd.DataFrame) -> tuple[list[float], list[float]]:
    """Per block k: the share of episodes that came for it, and the share whose tower is at least k high."""
    came = [float((facts[f"closest_{k}"] < REACH).mean()) for k in range(1, BLOCKS + 1)]
    tower = [float((facts["tower"] >= k).mean()) for k in range(1, BLOCKS + 1)]
    return came, tower


def stacking_table(agg: pd.DataFrame) -> pd.DataFrame:
    """One row per (variant, study), as strings; a / b / c are blocks 1, 2 and 3."""
    if agg.empty:
        return pd.DataFrame()
    rows = []
    for r in in_variant_order(agg).itertuples():
        came, tower = shares(r.facts)
        closest = [100 * r.facts[f"closest_{k}"].median() for k in range(1, BLOCKS + 1)]
        rows.append({
            "variant": paper.variant_label(r.variant), "setting": r.setting,
            "success": f"{100 * r.facts['success'].mean():.0f}%",
            f"came for block 1 / 2 / 3 (< {REACH * 100:g} cm)": " / ".join(f"{100 * s:.0f}%" for s in came),
            "tower of at least 1 / 2 / 3": " / ".join(f"{100 * s:.0f}%" for s in tower),
            "median closest approach (cm)": " / ".join(f"{c:.1f}" for c in closest),
            "episodes": str(len(r.facts)), "seeds": str(r.seeds),
        })
    return pd.DataFrame(rows)


def stacking_figure(agg: pd.DataFrame, task: str, folder: Path) -> FigureResult:
    """One panel per study: against the block, the share of episodes that came for it (solid) and the share with a
    tower at least that high (dashed), a colour per variant."""
    if agg.empty:
        return gap(NAME, TITLE, f"no stacking rollouts of {task} models in the named studies")
    studies = list(dict.fromkeys(agg["study"]))
    variants = order_variants(agg["variant"].unique())
    blocks = np.arange(1, BLOCKS + 1)
    fig, axes = panel_grid(len(studies), 4.0, 3.2)
    for ax, study in zip(axes.flat, studies, strict=False):
        mine = agg[agg["study"] == study]
        for r in mine.itertuples():
            came, tower = shares(r.facts)
            color = variant_color(r.variant, variants)
            label = paper.variant_label(r.variant)
            ax.plot(blocks, 100 * np.array(came), "o-", color=color,
                    label=f"{label}: came for it (tip < {REACH * 100:g} cm)")
            ax.plot(blocks, 100 * np.array(tower), "s--", color=color, label=f"{label}: tower this high")
        ax.set_xticks(blocks, [f"block {k}" for k in blocks])
        ax.set_title(f"{study}\n{mine['setting'].iloc[0]}", fontsize=8)
        ax.set_ylabel("episodes (%)")
        ax.set_ylim(-3, 103)
        ax.grid(alpha=0.3)
    legend_below(fig, axes.flat[0])
    fig.suptitle(TITLE)
    out = save(fig, folder, NAME, TITLE)
    plt.close(fig)
    return out
