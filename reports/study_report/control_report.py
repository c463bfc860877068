"""Report parts of the post-processing studies (`python -m experiments smoothing|idm`): a metrics table
from the parent run's metrics and the study's own figures, copied from its `figures/` artifacts.

Contract (experiments.control_studies writes it): one parent run per study, no children; metrics at step 0
named `<variant>/<metric>` (smoothing: variants skeleton, exact, gd, gd_goal; metrics mean_sq_jerk,
peak_joint_speed, deviation_rad, tip_deviation_m, goal_error_m; plus time_exact_s, time_gd_s,
time_gd_goal_s) and `<condition>/<metric>` (idm: conditions position, sim, real_sim_idm, real_finetuned,
real_scratch; metrics tip_rmse_vs_plan_m, tip_rmse_vs_position_m, final_error_m, success_rate; plus
latency_fast_ms, latency_torch_ms); artifacts figures/smoothing_tip_paths.{png,pdf},
figures/idm_tracking.{png,pdf}; tag skeleton_source. Missing pieces are gaps.
"""

from __future__ import annotations

import math
import shutil
from pathlib import Path

from reports.data.store import Study
from reports.plotting import FigureResult, gap
from reports.study_report.tables import GAP, Table, num, pct

SMOOTHING_VARIANTS = {"skeleton": "skeleton (before)", "exact": "exact quadratic solve",
                      "gd": "gradient descent", "gd_goal": "gradient descent + goal term"}
SMOOTHING_COLUMNS = {"mean_sq_jerk": "mean sq. jerk [rad²/s⁶]", "peak_joint_speed": "peak joint speed [rad/s]",
                     "deviation_rad": "deviation [rad]", "tip_deviation_m": "tip deviation [m]",
                     "goal_error_m": "final goal error [m]"}
IDM_CONDITIONS = {"position": "position control (reference)", "sim": "IDM, sim robot",
                  "real_sim_idm": "IDM trained in sim, perturbed robot",
                  "real_finetuned": "IDM fine-tuned on perturbed robot",
                  "real_scratch": "IDM trained on perturbed data only"}
IDM_COLUMNS = {"tip_rmse_vs_plan_m": "tip RMSE vs plan [m]", "tip_rmse_vs_position_m": "tip RMSE vs position ctrl [m]",
               "final_error_m": "final goal error [m]", "success_rate": "success (4 goals)"}
NOT_APPLICABLE = {("position", "tip_rmse_vs_position_m")}  # the reference itself
FIGURES = {"smoothing": [("smoothing_tip_paths", "Tool-tip paths before and after smoothing (four reacher goals)")],
           "idm": [("idm_tracking", "Tool-tip tracking over time: plan vs IDM torque control")]}


def _metric(study: Study, key: str) -> float:
    value = study.parent.get(f"metrics.{key}")
    try:
        return float(value)
    except (TypeError, ValueError):
        return math.nan


def _grid(study: Study, name: str, title: str, rows_spec: dict[str, str], cols_spec: dict[str, str],
          notes: list[str], fmt=num) -> Table:
    import pandas as pd

    rows, data = [], []
    for key, label in rows_spec.items():
        values = {c: _metric(study, f"{key}/{c}") for c in cols_spec}
        if all(math.isnan(v) for v in values.values()):
            continue  # a condition the study did not run (e.g. scratch baseline off)
        rows.append([label] + [("–" if (key, c) in NOT_APPLICABLE else GAP) if math.isnan(v) else fmt(c, v)
                               for c, v in values.items()])
        data.append({"row": key, **values})
    if not rows:
        rows = [[GAP] + ["–"] * len(cols_spec)]
    return Table(name, title, ["", *cols_spec.values()], rows, notes, pd.DataFrame(data))


def smoothing_table(study: Study) -> Table:
    t = {k: _metric(study, k) for k in ("time_exact_s", "time_gd_s", "time_gd_goal_s", "n_trajectories", "steps",
                                        "gamma", "goal_weight")}
    notes = [f"{num(t['n_trajectories'])} trajectories of {num(t['steps'])} steps, gamma {num(t['gamma'])}, "
             f"goal weight {num(t['goal_weight'])}; skeletons: {study.parent.get('tags.skeleton_source') or '?'}.",
             f"Wall time: exact solve {num(t['time_exact_s'])} s, gradient descent {num(t['time_gd_s'])} s, "
             f"with goal term {num(t['time_gd_goal_s'])} s (one run on a shared CPU).",
             "Deviation: mean over steps of the joint-space (and tip) distance to the skeleton."]
    return _grid(study, "smoothing_table", "Trajectory smoothing: before and after", SMOOTHING_VARIANTS,
                 SMOOTHING_COLUMNS, notes, fmt=lambda c, v: num(v, 4))


def idm_table(study: Study) -> Table:
    fast, slow = _metric(study, "latency_fast_ms"), _metric(study, "latency_torch_ms")
    notes = [f"Means over the plans to four reacher goals; plans: {study.parent.get('tags.skeleton_source') or '?'}.",
             "Success: final tip within 5 cm of the goal. The perturbed robot stands in for the real one.",
             f"IDM latency per control step (batch 1, median): {num(fast)} ms (numpy path), {num(slow)} ms (torch)."]
    return _grid(study, "idm_table", "Inverse dynamics model: tool-tip tracking", IDM_CONDITIONS, IDM_COLUMNS, notes,
                 fmt=lambda c, v: pct(v) if c == "success_rate" else num(v, 3))


def study_figures(study: Study, folder: Path) -> list[FigureResult]:
    """The study's own figures, copied from the parent run's figures/ artifacts (PNG + PDF)."""
    out = []
    for name, title in FIGURES.get(study.kind, []):
        paths = []
        for ext in ("png", "pdf"):
            local = study._download(study.run_id, f"figures/{name}.{ext}")
            if local is None:
                break
            dst = folder / f"{name}.{ext}"
            shutil.copyfile(local, dst)
            paths.append(dst)
        out.append(FigureResult(name, title, paths) if len(paths) == 2
                   else gap(name, title, f"no figures/{name}.png and .pdf artifacts in run {study.run_id}"))
    return out


def parts(study: Study, folder: Path) -> tuple[list[Table], list[FigureResult]]:
    table = smoothing_table(study) if study.kind == "smoothing" else idm_table(study)
    return [table], study_figures(study, folder)
