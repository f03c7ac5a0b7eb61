"""Colour-key transparency (a PNG ``tRNS`` chunk in a grey, RGB or palette image): Pillow keeps the key in
``im.info["transparency"]`` instead of an alpha channel. A photo for ``depthnerf reconstruct`` reads as the same
photo with an alpha channel (its alpha is the mask); a dataset image reads like an RGBA one (composited on
white)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from fixtures_srn import write_grey_png, write_png16
from PIL import Image

from depthnerf.data.srn_format import mask_from_white, read_rgb
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.photo import prepare_photo, read_photo

SIDE = 32
OBJECT = (slice(8, 24), slice(4, 20))
"""Rows and columns of the opaque object; every other pixel has the key colour."""


def _keyed(tmp_path: Path, mode: str) -> tuple[Path, Image.Image]:
    """A colour-keyed PNG of ``mode`` (the object on the key colour) and the same picture with an alpha channel."""
    ramp = np.linspace(60, 220, SIDE).astype(np.uint8)
    inside = np.zeros((SIDE, SIDE), dtype=bool)
    inside[OBJECT] = True
    if mode == "RGB":
        rgb = np.zeros((SIDE, SIDE, 3), dtype=np.uint8)
        rgb[..., 1] = 255  # green screen, the key
        rgb[inside] = np.stack([ramp[:, None].repeat(SIDE, 1), np.full((SIDE, SIDE), 40, np.uint8),
                                ramp[None].repeat(SIDE, 0)], axis=-1)[inside]
        im, key = Image.fromarray(rgb, "RGB"), (0, 255, 0)
    elif mode == "L":
        grey = np.where(inside, ramp[:, None], 0).astype(np.uint8)
        im, key = Image.fromarray(grey, "L"), 0
    elif mode == "I;16":
        grey = np.where(inside, ramp[:, None].astype(np.uint16) * 257 + 3, 0).astype(np.uint16)
        im, key = Image.fromarray(grey), 0
    else:  # palette: index 0 is the key
        index = np.where(inside, 1 + np.arange(SIDE)[:, None] % 4, 0).astype(np.uint8)
        im, key = Image.fromarray(index, "P"), 0
        im.putpalette([0, 0, 255, 200, 30, 30, 30, 200, 30, 30, 30, 200, 220, 220, 40])
    path = tmp_path / f"keyed_{mode.replace(';', '')}.png"
    im.save(path, transparency=key)
    with Image.open(path) as check:
        assert check.mode == im.mode and check.info["transparency"] == key  # the file holds a tRNS key
    alpha = Image.fromarray(np.where(inside, 255, 0).astype(np.uint8), "L")
    if mode == "I;16":  # 8-bit grey (Pillow's own conversion of 16-bit grey saturates above 255)
        colours = Image.fromarray(np.round(np.asarray(im) / 257).astype(np.uint8), "L")
    else:
        colours = im.convert("L" if mode == "L" else "RGB")  # in memory: no key, its colours as they are
    return path, Image.merge(colours.mode + "A", (*colours.split(), alpha))


@pytest.mark.parametrize("mode", ["RGB", "L", "I;16", "P"])
def test_a_colour_keyed_photo_reads_as_the_photo_with_alpha(tmp_path: Path, mode: str):
    path, with_alpha = _keyed(tmp_path, mode)
    rgb, alpha, _ = read_photo(path, [])
    assert alpha is not None and np.array_equal(alpha > 0.5, np.asarray(with_alpha)[..., -1] > 0)
    assert (alpha[OBJECT] == 1).all()
    want_rgb, want_alpha, _ = read_photo(with_alpha, [])
    np.testing.assert_allclose(rgb, want_rgb, atol=1e-6)
    np.testing.assert_array_equal(alpha, want_alpha)
    keyed = prepare_photo(path, None, 32, "keep")
    cut = prepare_photo(with_alpha, None, 32, "keep")
    assert "mask: alpha > 0.5" in keyed.notes and keyed.notes == cut.notes
    np.testing.assert_array_equal(keyed.mask, cut.mask)
    np.testing.assert_allclose(keyed.image, cut.image, atol=1e-6)


@pytest.mark.parametrize("mode", ["RGB", "L", "I;16", "P"])
def test_a_colour_keyed_dataset_image_is_composited_on_white(tmp_path: Path, mode: str):
    path, with_alpha = _keyed(tmp_path, mode)
    rgba_path = tmp_path / "rgba.png"
    with_alpha.save(rgba_path)
    img = read_rgb(path)
    if mode == "I;16":  # full 16-bit precision is not kept under a key: within half an 8-bit level
        np.testing.assert_allclose(img, read_rgb(rgba_path), atol=0.5 / 255 + 1e-6)
    else:
        np.testing.assert_array_equal(img, read_rgb(rgba_path))
    assert (img[~mask_from_white(img)] == 1.0).all()
    expected = np.zeros((SIDE, SIDE), dtype=bool)
    expected[OBJECT] = True
    np.testing.assert_array_equal(mask_from_white(img), expected)  # pixelNeRF's mask: the key is background


def test_a_16_bit_colour_png_with_a_key_is_refused_naming_the_file(tmp_path: Path):
    """Pillow reads 16-bit colour by its high bytes, where a 16-bit key cannot be matched (a key of black would
    make every value below 256 transparent): one line naming the file, not a wrong cut-out."""
    arr = np.zeros((SIDE, SIDE, 3), dtype=np.uint16)
    arr[OBJECT] = (40000, 9000, 100)
    path = tmp_path / "rgb16.png"
    write_png16(path, arr, key=(0, 0, 0))
    for read in (read_rgb, lambda p: read_photo(p, [])):
        with pytest.raises(DepthnerfError) as err:
            read(path)
        assert str(err.value).startswith(f"{path}: ") and "colour key" in str(err.value)
        assert "\n" not in str(err.value)


@pytest.mark.parametrize("depth", [1, 2, 4])
def test_the_key_of_a_low_bit_grey_png_matches_its_pixels(tmp_path: Path, depth: int):
    """Pillow scales 1-, 2- and 4-bit grey to 0..255 but leaves the key of a 2- or 4-bit file as stored."""
    levels = 2**depth
    stored = np.arange(SIDE * SIDE).reshape(SIDE, SIDE) % levels
    rows = np.packbits(np.unpackbits(stored.astype(np.uint8)[..., None], axis=-1)[..., -depth:].reshape(SIDE, -1),
                       axis=-1)
    path = tmp_path / f"grey{depth}.png"
    write_grey_png(path, rows, depth, key=1)
    rgb, alpha, _ = read_photo(path, [])
    assert alpha is not None
    np.testing.assert_array_equal(alpha == 0, stored == 1)
    np.testing.assert_allclose(rgb[..., 0], stored / (levels - 1), atol=1e-6)
    img = read_rgb(path)
    np.testing.assert_allclose(img[..., 0], np.where(stored == 1, 1.0, stored / (levels - 1)), atol=1e-6)
