"""A sweep's figures: optuna.visualization's matplotlib plots (history, intermediate values,
slice, importances, contour), saved as PNG and PDF for the sweep's parent run; and its
parameter importances (fANOVA; why that evaluator: experiments/sweeps/runner.py)."""

from __future__ import annotations

import logging
from pathlib import Path

from envs.figure_files import save_figure

log = logging.getLogger(__name__)


def importance_evaluator(seed: int):
    """Optuna's fANOVA, seeded (its random forest), so that the logged numbers and the figure agree."""
    from optuna.importance import FanovaImportanceEvaluator

    return FanovaImportanceEvaluator(seed=seed)


def param_importances(study, seed: int) -> tuple[dict[str, float], str]:
    """(importance of each swept parameter over the COMPLETE trials, normalised to sum 1, largest
    first; "") or ({}, why they cannot be computed)."""
    import warnings

    from optuna.importance import get_param_importances
    from optuna.trial import TrialState

    complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    params = sorted({p for t in complete for p in t.params})
    if len(complete) < 2 or len(params) < 2:
        return {}, (f"parameter importances need >= 2 complete trials and >= 2 swept parameters; this sweep has "
                    f"{len(complete)} complete trial(s) and {len(params)} parameter(s)")
    if len({t.value for t in complete}) < 2:
        return {}, "parameter importances: every complete trial has the same objective (no variance to explain)"
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")  # fANOVA is an experimental feature of Optuna
            raw = get_param_importances(study, evaluator=importance_evaluator(seed), normalize=False)
    except (RuntimeError, ValueError) as exc:  # e.g. zero variance in every tree of the forest
        return {}, f"parameter importances could not be computed: {exc}"
    total = sum(raw.values())
    if not total > 0:
        return {}, "parameter importances: no parameter explains any of the objective's variance"
    return {k: float(v) / total for k, v in sorted(raw.items(), key=lambda kv: -kv[1])}, ""


def sweep_figures(study, out: Path, evaluator=None) -> list[Path]:
    """optuna.visualization.matplotlib figures: history, importances (with `evaluator`, else
    Optuna's default), slice, contour; a figure that cannot be drawn yet (too few finished
    trials, one parameter) is skipped with a log line."""
    import warnings

    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from optuna.trial import TrialState
    from optuna.visualization import matplotlib as ovm

    complete = [t for t in study.get_trials(deepcopy=False) if t.state == TrialState.COMPLETE]
    params = sorted({p for t in complete for p in t.params})
    plots = {"optimization_history": ovm.plot_optimization_history,
             "intermediate_values": ovm.plot_intermediate_values}
    if complete:
        plots["slice"] = ovm.plot_slice
    if len(complete) >= 2 and params:
        plots["param_importances"] = lambda st: ovm.plot_param_importances(st, evaluator=evaluator)
    if len(params) >= 2 and len(complete) >= 2:
        plots["contour"] = ovm.plot_contour
    paths = []
    for name, fn in plots.items():
        # each of optuna's plots sets the ggplot style for the whole process: it stays inside this figure
        with matplotlib.rc_context():
            try:
                with warnings.catch_warnings():
                    warnings.simplefilter("ignore")
                    ax = fn(study)
                fig = ax.flat[0].figure if hasattr(ax, "flat") else ax.figure
                paths += [Path(p) for p in save_figure(fig, out / name, dpi=110, bbox_inches="tight")]
            except Exception as exc:  # optuna raises for degenerate studies (e.g. zero-variance importances)
                log.info("figure %s skipped: %s", name, exc)
                plt.close("all")
    return paths
