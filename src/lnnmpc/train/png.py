"""Figures saved as 256-colour palette PNGs: the same picture at about a third of the bytes.

Every figure this package writes (run curves, comparisons, analyses, study figures) goes through
:func:`save_png`. The results committed under ``experiments/results/`` are mostly such figures, and the whole
working tree travels with every GPU call under a size limit (``/work/.library/device/README.md``), so their size
decides how much else a call can carry. A line plot has few distinct colours: quantised to a palette of 256
without dithering it looks the same (``tests/test_png.py`` bounds the difference) at ~35% of matplotlib's RGBA
file. ``experiments/scripts/shrink_pngs.py`` re-encodes figures written before.
"""

from __future__ import annotations

import io
import os

from lnnmpc.train import runfolder

COLOURS = 256


def palette_png(image, colours: int = COLOURS):
    """``image`` (a PIL image of any mode) as a palette image: RGB (transparency flattened onto white), quantised
    to ``colours`` by median cut without dithering."""
    from PIL import Image

    if image.mode in ("RGBA", "LA") or (image.mode == "P" and "transparency" in image.info):
        rgba = image.convert("RGBA")
        white = Image.new("RGBA", rgba.size, (255, 255, 255, 255))
        image = Image.alpha_composite(white, rgba)
    return image.convert("RGB").quantize(colors=colours, method=Image.Quantize.MEDIANCUT, dither=Image.Dither.NONE)


def encode_png(image) -> bytes:
    """``image`` as palette PNG bytes (:func:`palette_png`, zlib at its best)."""
    buffer = io.BytesIO()
    palette_png(image).save(buffer, format="PNG", optimize=True)
    return buffer.getvalue()


def save_png(fig, path: str, dpi: int) -> str:
    """Renders matplotlib ``fig`` at ``dpi`` and writes it to ``path`` as a palette PNG, atomically (a reader never
    sees half a file; the folder is made). Returns ``path``."""
    from PIL import Image

    rendered = io.BytesIO()
    fig.savefig(rendered, format="png", dpi=dpi)
    rendered.seek(0)
    data = encode_png(Image.open(rendered))
    os.makedirs(os.path.dirname(os.path.abspath(path)), exist_ok=True)
    runfolder.write_atomic(path, lambda f: f.write(data), binary=True)
    return path
