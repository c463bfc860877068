"""Independent checks shared by test modules: closed-form Wilson interval (the code under test
uses scipy's quantile) and a figure-content check (a blank canvas has one or two colours)."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from PIL import Image

Z95 = 1.959963984540054  # two-sided 95% normal quantile


def wilson(k: int, n: int) -> tuple[float, float]:
    """Wilson score interval for k successes in n trials, from its closed form."""
    p, z2 = k / n, Z95**2
    centre = (p + z2 / (2 * n)) / (1 + z2 / n)
    half = Z95 / (1 + z2 / n) * math.sqrt(p * (1 - p) / n + z2 / (4 * n * n))
    return centre - half, centre + half


def drawn_colours(png: Path) -> int:
    """Distinct colours in a PNG: paths, markers, axes and text give many; a blank canvas 1 or 2."""
    with Image.open(png) as im:
        return len(np.unique(np.asarray(im.convert("RGB")).reshape(-1, 3), axis=0))


def is_pdf(path: Path) -> bool:
    return path.read_bytes()[:5] == b"%PDF-"
