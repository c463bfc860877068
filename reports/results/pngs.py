"""Small PNGs for RESULTS.md: a report figure re-saved narrow, on white, with a palette, without metadata."""

from __future__ import annotations

from pathlib import Path

MAX_FIGURE_WIDTH = 1000  # px
MAX_FIGURE_BYTES = 300_000
MIN_FIGURE_WIDTH = 400  # px: below this a figure is unreadable, whatever its size


def small_png(src: Path, dst: Path, max_width: int = MAX_FIGURE_WIDTH, max_bytes: int = MAX_FIGURE_BYTES) -> Path:
    """Re-save a figure as a small PNG: on white, at most max_width px wide, 256 palette colours; narrower
    still while it is over max_bytes. No metadata, so the same figure gives the same bytes."""
    from PIL import Image

    dst.parent.mkdir(parents=True, exist_ok=True)
    with Image.open(src) as im:
        rgba = im.convert("RGBA")
    flat = Image.new("RGB", rgba.size, "white")
    flat.paste(rgba, mask=rgba.getchannel("A"))
    width = min(max_width, flat.width)
    while True:
        img = flat if width == flat.width else flat.resize((width, round(flat.height * width / flat.width)),
                                                          Image.Resampling.LANCZOS)
        tmp = dst.with_name(dst.name + ".tmp")
        img.quantize(256).save(tmp, format="PNG", optimize=True)
        if tmp.stat().st_size <= max_bytes or width <= MIN_FIGURE_WIDTH:
            tmp.replace(dst)
            return dst
        width = int(width * 0.8)
