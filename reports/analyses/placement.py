"""Pick-and-place success judged on the block, beside the strict criterion: {{ placement("pick-place", "STUDY", ...) }}
in a RESULTS template. Per evaluated task (pick-and-place, changing-goal pick-and-place), study (labelled by its
setting, as the lever table labels it: reports.analyses.levers) and variant, from each finished seed's rollouts:
- success (strict): the block placed and the last grip command open, what success rates report under the
  default eval.success (the rollouts' success_strict; rollouts from before it was kept: their success, the same
  criterion);
- placed: the block judged alone, at the goal within the task's tolerances, upright, untouched, the tip away,
  after settling (the rollouts' placed; rollouts from before it was kept: the same checks on the facts they
  recorded, xy_error, z_error, tilt, touching and tip_to_block; "not recorded" where they lack one);
each the mean over seeds with its seed-level interval (experiments.stats.rate_interval), and placed - strict, the
episodes that place the block and then shut the gripper again (or never open it), with its paired interval
(experiments.stats.paired_interval: both criteria judge the same episodes)."""

from __future__ import annotations

import numpy as np
import pandas as pd

from experiments.stats import interval, paired_interval, pct, points, rate_interval
from reports import paper
from reports.analyses.levers import in_variant_order, rollout_rows
from reports.analyses.pick_place_failures import AWAY, EVAL_TASKS, MAX_TILT, XY_TOL, Z_TOL
from reports.data.store import Study

NAME, TITLE = "placement", "Pick-and-place: success judged on the block beside the strict criterion"
PLACED_FACTS = ("xy_error", "z_error", "tilt", "touching", "tip_to_block")


def episode_facts(arrays: dict[str, np.ndarray]) -> pd.DataFrame:
    """One row per episode: its training seed, strict (0/1) and placed (0/1; NaN where not recorded)."""
    strict = np.asarray(arrays.get("success_strict", arrays["success"]), float)
    if "placed" in arrays:
        placed = np.asarray(arrays["placed"], float)
    elif all(k in arrays for k in PLACED_FACTS):  # the task's checks (envs.tasks.pickplace.placed_ok) on its facts
        f = {k: np.asarray(arrays[k], float) for k in PLACED_FACTS}
        placed = ((f["xy_error"] <= XY_TOL) & (np.abs(f["z_error"]) <= Z_TOL) & (f["tilt"] <= MAX_TILT)
                  & (f["touching"] < 0.5) & (f["tip_to_block"] >= AWAY)).astype(float)
    else:
        placed = np.full(len(strict), np.nan)
    seed = np.asarray(arrays["seed"], int) if "seed" in arrays else np.zeros(len(strict), int)
    return pd.DataFrame({"seed": seed, "strict": strict, "placed": placed})


def placement_rows(studies: list[Study], task: str) -> pd.DataFrame:
    """One row per (evaluated task, study, variant) with pick-and-place rollouts of `task`'s models."""
    frames = [rows.assign(eval_task=eval_task) for eval_task in EVAL_TASKS
              if not (rows := rollout_rows(studies, task, eval_task, episode_facts)).empty]
    return pd.concat(frames, ignore_index=True) if frames else pd.DataFrame()


def seed_rates(facts: pd.DataFrame) -> pd.DataFrame:
    """Per training seed: its strict and placed rates and its episodes."""
    return facts.groupby("seed").agg(strict=("strict", "mean"), placed=("placed", "mean"),
                                     episodes=("strict", "size"))


def _rate(rates: np.ndarray, episodes: np.ndarray) -> str:
    if np.isnan(rates).any():
        return "not recorded"
    return f"{pct(float(rates.mean()))} ({interval(*rate_interval(rates, episodes))})"


def placement_table(agg: pd.DataFrame) -> pd.DataFrame:
    """One row per (evaluated task, variant, study), as strings."""
    if agg.empty:
        return pd.DataFrame()
    ordered = pd.concat([in_variant_order(agg[agg["eval_task"] == e]) for e in EVAL_TASKS])
    rows = []
    for r in ordered.itertuples():
        per_seed = seed_rates(r.facts)
        strict, placed, n = (per_seed[c].to_numpy(float) for c in ("strict", "placed", "episodes"))
        if np.isnan(placed).any():
            gain = "–"
        else:
            low, high = paired_interval(placed, strict, n, n)
            gain = f"{points(float(np.mean(placed - strict)))} ({points(low)} to {points(high)})"
        rows.append({"task": paper.task_label(r.eval_task), "variant": paper.variant_label(r.variant),
                     "setting": r.setting, "success (strict)": _rate(strict, n), "placed (on the block)":
                     _rate(placed, n), "placed − strict (points)": gain, "episodes": str(len(r.facts)),
                     "seeds": str(r.seeds)})
    return pd.DataFrame(rows)


def note(task: str) -> str:
    return (f"the pick-and-place and changing-goal pick-and-place episodes of the {task} models; setting: as in the "
            "lever table; success (strict): the block placed and the last grip command open (success rates "
            "report this unless eval.success = placed); placed: the block alone judged at the goal within the "
            "task's tolerances "
            f"({XY_TOL * 100:g} cm in xy, {Z_TOL * 100:g} cm in height), upright (tilt at most {MAX_TILT:g} rad), no "
            f"finger on it and the tip at least {AWAY * 100:g} cm from it, after settling, whatever the last grip "
            "command; mean over seeds (seed-level 95% interval); placed − strict: the paired difference (the same "
            "episodes), the episodes that placed the block and then left the gripper closed.")
