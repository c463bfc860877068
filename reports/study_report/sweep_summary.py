"""An Optuna sweep tracked in MLflow: its figures (objective per trial, objective vs each sampled value,
intermediate values, the pruning signal, per trial; the parameter importances) and its table of the best
trials (with each trial's per-seed objectives and the sweep's parameter importances)."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib.ticker
import numpy as np
import pandas as pd

from reports.data.store import Study
from reports.plotting import FigureResult, gap, panel_grid, plt, save
from reports.study_report.tables import GAP, Table, num

TOP_TRIALS = 5


def _objective(study: Study) -> tuple[str, pd.Series] | None:
    for col in ("metrics.objective", "metrics.val/metric"):
        if col in study.children.columns and study.children[col].notna().any():
            return col.removeprefix("metrics."), study.children[col]
    return None


def _sweep_frame(study: Study) -> pd.DataFrame:
    ch = study.children.copy()
    found = _objective(study)
    ch["objective"] = found[1] if found else np.nan
    if "metrics.val/metric" in ch:  # pruned trials have no objective: show their last intermediate value
        ch["objective"] = ch["objective"].fillna(ch["metrics.val/metric"])
    ch["trial_no"] = ch["trial"].fillna(pd.Series(range(len(ch)), index=ch.index, dtype="Int64"))
    state = ch["trial_state"].fillna(ch["status"])  # MLflow status when the trial tag is missing
    ch["trial_state"] = state.replace({"FINISHED": "COMPLETE", "FAILED": "FAIL", "KILLED": "PRUNED"})
    return ch.sort_values("trial_no")


OBJECTIVE_LABELS = {"val": "validation metric", "final_distance": "final distance to goal (m)"}


def _objective_label(study: Study, metric: str) -> str:
    """What the objective measures, from the sweep parent's param sweep.objective where logged."""
    kind = study.parent.get("params.sweep.objective")
    return f"objective: {OBJECTIVE_LABELS.get(kind, kind)}" if kind else metric


def _direction(study: Study) -> str:
    d = study.parent.get("tags.direction") or study.parent.get("params.direction") or "minimize"
    return "maximize" if str(d).lower().startswith("max") else "minimize"


def sweep_history(study: Study, folder: Path) -> FigureResult:
    name, title = "sweep_history", "Sweep: objective per trial"
    found = _objective(study)
    if found is None:
        return gap(name, title, "no trial logged 'objective' or 'val/metric'")
    df = _sweep_frame(study)
    fig, ax = plt.subplots(figsize=(7, 4))
    for state, marker, color in (("COMPLETE", "o", "tab:blue"), ("PRUNED", "s", "tab:gray"), ("FAIL", "x", "tab:red")):
        part = df[df["trial_state"] == state]
        if len(part):
            ax.scatter(part["trial_no"], part["objective"], marker=marker, color=color,
                       label="pruned (last intermediate value)" if state == "PRUNED" else state.lower())
    done = df[df["trial_state"] == "COMPLETE"].dropna(subset=["objective"])
    if len(done):
        best = done["objective"].cummin() if _direction(study) == "minimize" else done["objective"].cummax()
        ax.step(done["trial_no"], best, where="post", color="black", lw=1.2, label="best so far")
    ax.set_xlabel("trial number")
    ax.xaxis.set_major_locator(matplotlib.ticker.MaxNLocator(integer=True))
    ax.set_ylabel(f"{_objective_label(study, found[0])} ({_direction(study)}d)")
    ax.set_title(f"{title} — {study.name}")
    ax.grid(alpha=0.3)
    ax.legend()
    return save(fig, folder, name, title)


def sweep_params(study: Study, folder: Path) -> FigureResult:
    name, title = "sweep_params", "Sweep: objective vs each hyperparameter"
    found = _objective(study)
    df = _sweep_frame(study)
    # the sampled values (params trial.<name>); without them every param that varies between trials
    params = [c for c in df.columns if c.startswith("params.trial.") and df[c].nunique(dropna=True) > 1] or \
        [c for c in df.columns if c.startswith("params.") and df[c].nunique(dropna=True) > 1]
    if found is None or not params:
        return gap(name, title, "no objective or no varied params among the trials")
    fig, axes = panel_grid(len(params), 3.6, 3.3)
    for ax, p in zip(axes.flat, params, strict=False):
        vals = pd.to_numeric(df[p], errors="coerce")
        if vals.isna().any():  # categorical: positions by sorted category
            cats = sorted(df[p].dropna().astype(str).unique())
            vals = df[p].astype(str).map({c: i for i, c in enumerate(cats)})
            ax.set_xticks(range(len(cats)), cats, rotation=30)
        colors = df["trial_state"].map({"COMPLETE": "tab:blue", "PRUNED": "tab:gray"}).fillna("tab:red")
        ax.scatter(vals, df["objective"], c=list(colors))
        ax.set_xlabel(p.removeprefix("params.").removeprefix("trial."))
        ax.set_ylabel(_objective_label(study, found[0]))
        ax.grid(alpha=0.3)
    axes[0][0].scatter([], [], c="tab:blue", label="complete")
    axes[0][0].scatter([], [], c="tab:gray", label="pruned")
    axes[0][0].legend()
    fig.suptitle(f"{title} — {study.name}")
    return save(fig, folder, name, title)


def sweep_intermediate(study: Study, folder: Path, metric: str = "val/metric") -> FigureResult:
    name, title = "sweep_intermediate", f"Sweep: intermediate {metric} per trial (pruning)"
    df = _sweep_frame(study)
    fig, ax = plt.subplots(figsize=(7, 4))
    drew = False
    for row in df.itertuples():
        h = study.metric_history(row.run_id, metric)
        if h.empty:
            continue
        pruned = row.trial_state == "PRUNED"
        ax.plot(h["step"], h["value"], color="tab:gray" if pruned else "tab:blue", lw=0.8,
                alpha=0.6 if pruned else 0.9, marker=".", ms=3)
        drew = True
    if not drew:
        plt.close(fig)
        return gap(name, title, f"no trial logged {metric} history")
    ax.plot([], [], color="tab:blue", label="complete")
    ax.plot([], [], color="tab:gray", label="pruned")
    ax.set_xlabel("iteration")
    ax.set_ylabel(f"{metric} (lower is better)")
    ax.set_title(f"{title} — {study.name}", fontsize=10)
    ax.grid(alpha=0.3)
    ax.legend()
    return save(fig, folder, name, title)



IMPORTANCE = "metrics.importance/"


def sweep_importances(study: Study) -> dict[str, float]:
    """The parameter importances the sweep logged on its parent run (importance/<param>), largest first."""
    found = {k.removeprefix(IMPORTANCE): float(v) for k, v in study.parent.items()
             if k.startswith(IMPORTANCE) and v is not None and not (isinstance(v, float) and math.isnan(v))}
    return dict(sorted(found.items(), key=lambda kv: -kv[1]))


def _param_label(name: str) -> str:
    return "(u, v)" if name == "uv" else name  # the grid's (u, v) pairs: one Optuna parameter


def importance_note(study: Study) -> str:
    """One line: the importances, or why there are none."""
    imp = sweep_importances(study)
    if imp:
        evaluator = study.parent.get("tags.importance_evaluator") or "Optuna's default evaluator"
        return (f"parameter importances ({evaluator} over the complete trials, normalised to sum 1): "
                + ", ".join(f"{_param_label(k)} {num(v, 2)}" for k, v in imp.items()) + ".")
    return str(study.parent.get("tags.importance_note")
               or "parameter importances: none logged (a sweep from before they were, or one that did not finish).")


def sweep_importance(study: Study, folder: Path) -> FigureResult:
    name, title = "sweep_importance", "Sweep: parameter importances"
    imp = sweep_importances(study)
    if not imp:
        return gap(name, title, importance_note(study))
    fig, ax = plt.subplots(figsize=(5, 0.5 + 0.45 * len(imp)))
    labels = [_param_label(k) for k in imp][::-1]
    ax.barh(labels, list(imp.values())[::-1], color="tab:blue")
    ax.set_xlim(0, 1)
    ax.set_xlabel(f"importance ({study.parent.get('tags.importance_evaluator') or 'Optuna'}, sum 1)")
    ax.set_title(f"{title} — {study.name}", fontsize=10)
    ax.grid(axis="x", alpha=0.3)
    return save(fig, folder, name, title)


def _per_seed(row: pd.Series) -> str:
    """A trial's per-seed objectives ("objective/seed<s>"), in seed order."""
    cols = sorted((c for c in row.index if c.startswith("metrics.objective/seed") and pd.notna(row[c])),
                  key=lambda c: int(c.rsplit("seed", 1)[1]))
    return " / ".join(num(row[c], 3) for c in cols) or "–"


# Public views of the helpers above, for the RESULTS.md tables (reports.results.writer).
def sweep_frame(study: Study) -> pd.DataFrame:
    """One row per trial, sorted by trial number: trial_no, trial_state (COMPLETE/PRUNED/FAIL), objective
    (a pruned trial's last intermediate value), the params.trial.<name> columns."""
    return _sweep_frame(study)


def direction(study: Study) -> str:
    """'minimize' or 'maximize', as the sweep's parent run logged it (default minimize)."""
    return _direction(study)


def objective_label(study: Study) -> str:
    """What the objective measures ('objective: validation metric', ...), or the metric's name."""
    found = _objective(study)
    return _objective_label(study, found[0] if found else "objective")


def sweep_task(study: Study) -> str:
    """The task a sweep study tuned (param sweep.task, else tag task)."""
    return str(study.parent.get("params.sweep.task") or study.parent.get("tags.task") or "?")


def _fmt_param(v) -> str:
    if v is None or (isinstance(v, float) and math.isnan(v)):
        return "–"
    try:
        f = float(v)
    except (TypeError, ValueError):
        return str(v)
    return str(int(f)) if f.is_integer() and "." not in str(v) else num(f, 3)


def sweep_table(study: Study) -> Table:
    """The sweep's best TOP_TRIALS complete trials (every complete one of a grid), ranked: objective, per-seed
    objectives (several seeds per trial), sampled values; its trial counts by state, its best trial as the
    parent run logged it and its parameter importances."""
    df = sweep_frame(study)
    direction_ = direction(study)
    states = df["trial_state"].value_counts()
    space = str(study.parent.get("params.sweep.space") or "").split(",")
    sampled = [c.removeprefix("params.trial.") for c in df.columns if c.startswith("params.trial.")]
    params = [p for p in space if p in sampled] + sorted(p for p in sampled if p not in space)
    done = df[(df["trial_state"] == "COMPLETE") & df["objective"].notna()]
    done = done.assign(_key=done["objective"] if direction_ == "minimize" else -done["objective"])
    grid = study.parent.get("params.sweep.sampler") == "grid"  # every point of a grid: the grid is the result
    top = done.sort_values(["_key", "trial_no"]).head(len(done) if grid else TOP_TRIALS)
    seeds = int(float(study.parent.get("params.sweep.seeds") or 1))
    per_seed = seeds > 1
    rows = [[str(i + 1), str(r["trial_no"]), num(r["objective"], 4), *([_per_seed(r)] if per_seed else []),
             *(_fmt_param(r.get(f"params.trial.{p}")) for p in params)] for i, (_, r) in enumerate(top.iterrows())]
    if not rows:
        rows = [[GAP, "–", "no complete trial with an objective", *(["–"] if per_seed else []),
                 *("–" for _ in params)]]
    best_trial = study.parent.get("metrics.best_trial")
    best_value = study.parent.get("metrics.best_value")
    best_params = {p: study.parent.get(f"tags.best.{p}") for p in params}
    best_row = df[df["trial_no"].astype(str) == str(int(float(best_trial)))] if best_trial is not None else df[:0]
    for p in params:  # a value the parent did not tag (the grid's (u, v) pair): the best trial's own
        if best_params[p] is None and len(best_row):
            best_params[p] = best_row.iloc[0].get(f"params.trial.{p}")
    if best_value is None and len(top):  # a sweep that did not log its best on the parent
        r = top.iloc[0]
        best_trial, best_value = r["trial_no"], r["objective"]
        best_params = {p: r.get(f"params.trial.{p}") for p in params}
    if best_value is None:
        best = "best trial: none (no complete trial)"
    else:
        best = ("best trial: " + (f"#{int(best_trial)}, " if best_trial is not None else "")
                + f"objective {num(best_value, 4)}; "
                + ", ".join(f"{p} = {_fmt_param(v)}" for p, v in best_params.items()))
    counted = {k: int(states.get(k, 0)) for k in ("COMPLETE", "PRUNED", "FAIL")}
    notes = [f"Study {study.name!r} ({study.profile} profile), variant "
             f"{study.parent.get('params.sweep.variant') or study.parent.get('tags.variant') or '?'}, sampler "
             f"{study.parent.get('params.sweep.sampler') or '?'}; {objective_label(study)} ({direction_}d).",
             f"trials: {len(df)} (complete {counted['COMPLETE']}, pruned {counted['PRUNED']}, failed "
             f"{counted['FAIL']}, other {len(df) - sum(counted.values())}).",
             best, importance_note(study)]
    if per_seed:
        first = int(float(study.parent.get("params.sweep.seed") or 0))
        notes.insert(1, f"{seeds} training seeds per trial ({first}..{first + seeds - 1}); a trial's objective is "
                        "the mean of its per-seed objectives (column 'per seed').")
    title = f"all {len(top)} complete grid points" if grid else f"top {TOP_TRIALS} trials"
    return Table(f"sweep_{sweep_task(study)}", f"Sweep on {sweep_task(study)}: {title}",
                 ["rank", "trial", "objective", *(["per seed"] if per_seed else []), *params], rows, notes)
