"""A sweep's figures: optuna.visualization's matplotlib plots (history, intermediate values,
slice, importances, contour), saved as PNG and PDF for the sweep's parent run."""

from __future__ import annotations

import logging
from pathlib import Path

from envs.figures import save_figure

log = logging.getLogger(__name__)


def sweep_figures(study, out: Path) -> list[Path]:
    """optuna.visualization.matplotlib figures: history, importances, slice, contour; a figure
    that cannot be drawn yet (too few finished trials, one parameter) is skipped with a log line."""
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
        plots["param_importances"] = ovm.plot_param_importances
    if len(params) >= 2 and len(complete) >= 2:
        plots["contour"] = ovm.plot_contour
    paths = []
    for name, fn in plots.items():
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
