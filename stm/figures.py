"""Saving the library's figures: one PNG and one PDF per figure."""

from __future__ import annotations

from pathlib import Path


def save_figure(fig, path_stem: str | Path, dpi: int = 130) -> list[str]:
    """Write `fig` as <stem>.png and <stem>.pdf (creating the folder), close it, return the paths."""
    import matplotlib.pyplot as plt

    stem = Path(path_stem)
    stem.parent.mkdir(parents=True, exist_ok=True)
    paths = [str(stem.with_suffix(ext)) for ext in (".png", ".pdf")]
    for p in paths:
        fig.savefig(p, dpi=dpi)
    plt.close(fig)
    return paths
