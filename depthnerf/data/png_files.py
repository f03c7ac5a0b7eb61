"""What a PNG file says that Pillow's decoded image leaves out: the bit depth and colour type in its ``IHDR``
header, and a colour-key transparency (a ``tRNS`` chunk in a grey or RGB file) as an alpha channel.

Colour key
    A grey or RGB PNG may name one colour as fully transparent instead of storing an alpha channel. Pillow keeps
    that key in ``im.info["transparency"]`` and decodes the file as ``L``/``RGB`` (``I;16`` for 16-bit grey), so a
    reader that takes the pixels as they are shows the key colour where the file is transparent.
    :func:`with_colour_key` makes the key an alpha channel: grey -> ``LA``, RGB -> ``RGBA`` (8 bits; 16-bit grey
    is rounded to 8 bits, as Pillow has no 16-bit mode with alpha; the key of 2- and 4-bit grey is scaled to
    0..255 like the pixels). Palette keys are left to Pillow's own ``convert("RGBA")``, which the readers already
    apply. A 16-bit colour file is decoded by its high bytes, where a 16-bit key cannot be matched (a key of black
    would take every value below 256): refused in one line.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from PIL import Image

from depthnerf.errors import DepthnerfError

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"
"""The first 8 bytes of every PNG file."""

GREY_MODES = ("1", "L", "I", "I;16", "I;16B", "I;16L")
"""Pillow's modes of a grey PNG that may carry a colour key (16-bit grey: ``I;16``, ``I`` in older Pillow)."""


def png_ihdr(head: bytes) -> tuple[int, int] | None:
    """Bit depth and colour type (0 grey, 2 RGB, 3 palette, 4 grey+alpha, 6 RGBA) from a file's first 26 bytes,
    or None when they are not a PNG's signature and ``IHDR`` chunk."""
    if len(head) < 26 or head[:8] != PNG_SIGNATURE or head[12:16] != b"IHDR":
        return None
    return head[24], head[25]


def _ihdr_of(path: Path | None) -> tuple[int, int] | None:
    """:func:`png_ihdr` of the file ``path`` (None: no path, not a PNG, or unreadable)."""
    if path is None:
        return None
    try:
        with open(path, "rb") as fh:
            return png_ihdr(fh.read(26))
    except OSError:
        return None


def is_sixteen_bit_colour_png(path: Path) -> bool:
    """Whether ``path`` is a 16-bit colour PNG (RGB or RGBA, the layouts Pillow reads by their high bytes)."""
    ihdr = _ihdr_of(path)
    return ihdr is not None and ihdr[0] == 16 and ihdr[1] in (2, 6)


def with_colour_key(im: Image.Image, name: str, path: Path | None = None) -> Image.Image:
    """``im`` (decoded) with its colour key as an alpha channel (module docstring), or ``im`` itself when it has
    no key or is not grey or RGB. ``path``: the file ``im`` was read from, whose header gives the bit depth: a
    16-bit colour file is refused in one line naming ``name`` (a key above 255 tells one without the file), and
    the key of a 2- or 4-bit grey file is scaled as Pillow scales its values to 0..255 (Pillow leaves it as
    stored, so it would match no pixel)."""
    key = im.info.get("transparency")
    if not ((im.mode == "RGB" and isinstance(key, tuple)) or (im.mode in GREY_MODES and isinstance(key, int))):
        return im  # no key, or not a grey or RGB image's (a palette's is bytes, Pillow's own to resolve)
    ihdr = _ihdr_of(path)
    depth = ihdr[0] if ihdr is not None else None
    if im.mode == "RGB":
        if max(key) > 255 or depth == 16:
            raise DepthnerfError(f"{name}: a 16-bit colour PNG with a colour key (tRNS) is not supported (its colours "
                                 "are read at 8 bits, where the 16-bit key cannot be matched); re-save it as RGBA")
        return im.convert("RGBA")
    values = np.asarray(im).astype(np.int64) * (255 if im.mode == "1" else 1)  # Pillow's key of 1-bit grey: 255
    if im.mode == "L" and depth in (2, 4):
        key = key * 255 // (2**depth - 1)
    grey = values if im.mode in ("1", "L") else np.round(values / 257.0)
    alpha = np.where(values == key, 0, 255)
    return Image.merge("LA", [Image.fromarray(band.clip(0, 255).astype(np.uint8), "L") for band in (grey, alpha)])
