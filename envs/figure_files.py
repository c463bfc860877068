"""Saving a figure: one PNG and one PDF per figure, the single place that does it (task renders, rollout
figures, sweeps, the smoothing and IDM studies, the reports). In envs, the lowest layer, so every package
can import it."""

from __future__ import annotations

from pathlib import Path

FORMATS = (".png", ".pdf")


def save_figure(fig, path_stem: str | Path, dpi: float | None = 130, **savefig) -> list[str]:
    """Write `fig` as <stem>.png and <stem>.pdf (creating the folder), close it, return the paths.
    dpi None: matplotlib's rcParams["savefig.dpi"] (the caller's style decides); other keywords (e.g.
    bbox_inches="tight") go to Figure.savefig."""
    import matplotlib.pyplot as plt

    stem = Path(path_stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [str(stem.parent / f"{stem.name}{ext}") for ext in FORMATS]
    if dpi is not None:
        savefig["dpi"] = dpi
    for p in paths:
        fig.savefig(p, **savefig)
    plt.close(fig)
    return paths
