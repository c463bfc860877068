"""Figure plumbing shared by the report's figure modules: matplotlib set-up (files only), the result of a
figure (paths or the gap that replaced it), colours per variant, saving as PNG + PDF (envs.figure_files.save_figure),
gap panels."""

from __future__ import annotations

import logging
from dataclasses import dataclass, field
from pathlib import Path

import matplotlib

matplotlib.use("Agg")  # files only; never a window
import matplotlib.pyplot as plt  # noqa: E402

from envs.figure_files import save_figure  # noqa: E402

log = logging.getLogger(__name__)

plt.rcParams.update({"font.size": 10, "axes.titlesize": 11, "figure.titlesize": 12, "legend.fontsize": 8,
                     "savefig.dpi": 150, "savefig.bbox": "tight", "figure.constrained_layout.use": True})


@dataclass
class FigureResult:
    """A figure of the report: its PNG + PDF paths, or the gap (reason) that replaced it."""

    name: str
    title: str
    paths: list[Path] = field(default_factory=list)
    gap: str | None = None  # why the figure (or part of it) is missing
    partial: list[str] = field(default_factory=list)  # panels drawn as gaps


def variant_color(variant: str, variants: list[str]) -> tuple:
    cmap = plt.get_cmap("tab10")
    return cmap(variants.index(variant) % 10 if variant in variants else 9)


def panel_grid(n: int, panel_w: float, panel_h: float, max_cols: int = 3):
    """A figure with n panels in rows of at most max_cols; unused axes switched off."""
    cols = min(max_cols, n)
    rows = -(-n // cols)
    fig, axes = plt.subplots(rows, cols, figsize=(panel_w * cols, panel_h * rows), squeeze=False)
    for ax in axes.flat[n:]:
        ax.set_axis_off()
    return fig, axes


def save(fig, folder: Path, name: str, title: str, partial: list[str] | None = None) -> FigureResult:
    """<folder>/<name>.png + .pdf through envs.figure_files.save_figure, at this module's rcParams dpi."""
    paths = save_figure(fig, folder / name, dpi=None)
    return FigureResult(name, title, [Path(p) for p in paths], partial=partial or [])


def legend_below(fig, ax) -> None:
    """One legend for the whole figure, under its panels, from the entries of `ax`."""
    handles, names = ax.get_legend_handles_labels()
    fig.legend(handles, names, loc="outside lower center", ncol=len(names), fontsize=8)


def gap(name: str, title: str, reason: str) -> FigureResult:
    log.info("figure %s is a gap: %s", name, reason)
    return FigureResult(name, title, gap=reason)


def mark_gap(ax, text: str) -> None:
    """An empty panel that says what is missing."""
    kw = dict(ha="center", va="center", color="#900", fontsize=9, wrap=True)
    if hasattr(ax, "text2D"):  # 3D panel: no empty box around the message
        ax.set_axis_off()
        ax.text2D(0.5, 0.5, f"gap: {text}", transform=ax.transAxes, **kw)
    else:
        ax.set_xticks([])
        ax.set_yticks([])
        ax.text(0.5, 0.5, f"gap: {text}", transform=ax.transAxes, **kw)
