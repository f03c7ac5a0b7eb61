"""Reading, masking and framing a photo (:mod:`depthnerf.reconstruct.photo`) against the rules of its module
docstring, on images whose answer is known by construction: crops that land on whole pixels (so the framed image
is a copy of photo pixels), masks reduced by a loop over blocks, and thresholds probed on both sides."""

from __future__ import annotations

import re

import numpy as np
import pytest

from depthnerf.data.photo_framing import frame_photo
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.photo import photo_mask, prepare_photo, read_photo


def _photo(h: int, w: int, seed: int = 0) -> np.ndarray:
    """Random float32 colours: no symmetry of the picture can hide a shifted or transposed crop."""
    return np.random.default_rng(seed).uniform(0.0, 0.9, (h, w, 3)).astype(np.float32)


def _box(mask: np.ndarray) -> tuple[int, int, int, int]:
    rows, cols = np.where(mask.any(1))[0], np.where(mask.any(0))[0]
    return int(cols[0]), int(rows[0]), int(cols[-1]), int(rows[-1])


@pytest.mark.parametrize("x0, y0", [(11, 5), (12, 6), (20, 13)])
def test_auto_framing_centres_the_box_and_copies_the_photos_pixels(x0, y0):
    """An 8 px square object at fill 0.5 frames a 16 px square centred on the box, i.e. starting 4 px before it;
    at resolution 16 the result is that crop itself: the object at 4..11 and every pixel the photo's."""
    rgb = _photo(40, 40)
    mask = np.zeros((40, 40), bool)
    mask[y0:y0 + 8, x0:x0 + 8] = True
    image, small = frame_photo(rgb, None, mask, 16, "auto", 0.5, [])
    assert _box(small) == (4, 4, 11, 11)
    crop = np.where(mask[..., None], rgb, 1.0)[y0 - 4:y0 + 12, x0 - 4:x0 + 12]
    np.testing.assert_array_equal(image, crop)


def test_a_fill_of_one_frames_the_box_exactly_and_fills_outside_0_1_are_refused():
    rgb = _photo(30, 30)
    mask = np.zeros((30, 30), bool)
    mask[7:15, 9:17] = True
    image, small = frame_photo(rgb, None, mask, 8, "auto", 1.0, [])
    assert small.all()
    np.testing.assert_array_equal(image, rgb[7:15, 9:17])
    for fill in (0.0, -0.5, 1.01):
        with pytest.raises(DepthnerfError, match="--fill must be in"):
            frame_photo(rgb, None, mask, 8, "auto", fill, [])


def test_keep_framing_pads_a_wide_photo_above_and_below():
    """A 20 x 40 photo framed with ``keep``: a 40 px square, the photo in rows 10..29, white above and below."""
    rgb = _photo(20, 40)
    mask = np.ones((20, 40), bool)
    image, small = frame_photo(rgb, None, mask, 40, "keep", 0.5, [])
    want = np.ones((40, 40, 3), np.float32)
    want[10:30] = rgb
    np.testing.assert_array_equal(image, want)
    assert small[10:30].all() and not small[:10].any() and not small[30:].any()


def test_the_framed_mask_is_any_coverage_of_each_output_pixel():
    """Downsampling 32 -> 8: an output pixel is object when any of its 4 x 4 photo pixels is (a loop over blocks)."""
    rng = np.random.default_rng(3)
    mask = rng.random((32, 32)) < 0.03
    mask[0, 0] = True
    _, small = frame_photo(_photo(32, 32), None, mask, 8, "keep", 0.5, [])
    want = np.array([[mask[4 * i:4 * i + 4, 4 * j:4 * j + 4].any() for j in range(8)] for i in range(8)])
    assert 5 < want.sum() < 64
    np.testing.assert_array_equal(small, want)


def test_alpha_is_composited_on_white():
    """Black at alpha 0.6: ``0 * 0.6 + 1 * (1 - 0.6)`` = 0.4 (a photo framed as it is)."""
    rgb = np.zeros((16, 16, 3), np.float32)
    alpha = np.full((16, 16), 0.6, np.float32)
    image, _ = frame_photo(rgb, alpha, np.ones((16, 16), bool), 16, "keep", 0.5, [])
    np.testing.assert_allclose(image, 0.4, atol=1e-6)


def test_the_border_ring_is_2_percent_of_the_shorter_side():
    """A blue 100 x 400 photo with a grey frame 6 px wide, 2 px inside its edge: the ring is 2 px wide (2 % of
    100, not 8 of 400), so the background colour is the blue and the frame is object."""
    img = np.empty((100, 400, 3), np.uint8)
    img[:] = (40, 90, 160)
    img[2:8, 2:-2], img[-8:-2, 2:-2], img[2:-2, 2:8], img[2:-2, -8:-2] = 200, 200, 200, 200
    img[40:60, 180:220] = (200, 40, 40)
    prep = prepare_photo(img, None, 32, "keep")
    assert any("border colour [40, 90, 160]" in n for n in prep.notes), prep.notes


@pytest.mark.parametrize("levels, is_object", [(25, False), (26, True), (60, True)])
def test_the_border_colour_mask_uses_the_largest_channel_difference(levels, is_object):
    """Tolerance 0.1 (25.5 of 255 levels) on the *largest* channel difference: a pixel off in one channel only by
    26 levels is object, by 25 levels background."""
    rgb = np.full((40, 40, 3), 0.4, np.float32)
    rgb[15:25, 15:25] = 0.2
    rgb[18, 18] = (0.4 + levels / 255, 0.4, 0.4)
    out = photo_mask(rgb, None, None, [])
    assert out[18, 18] == is_object and out[15, 15] and not out[0, 0]


def test_alpha_above_one_half_is_object():
    rgb = np.zeros((20, 20, 3), np.float32)
    alpha = np.zeros((20, 20), np.float32)
    alpha[5:10, 5:10], alpha[12:16, 12:16] = 0.5, 0.75
    out = photo_mask(rgb, alpha, None, [])
    assert not out[5:10, 5:10].any() and out[12:16, 12:16].all() and out.sum() == 16


def test_a_given_mask_is_object_above_half_its_maximum_and_a_clean_mask_gets_no_note():
    """A pixel is object where its value is above half the mask's own maximum: with 255 present, 127 is
    background and 128 object (an anti-aliased edge splits at 127.5); a mask of dark (<= 32 of 255) and bright
    (>= 223) values only, both scaled by its maximum, is no photo (no note), one of middle greys is."""
    rgb = np.zeros((20, 20, 3), np.float32)
    given = np.zeros((20, 20), np.uint8)
    given[2:6, 2:6], given[10:14, 10:14], given[0, 19] = 127, 128, 255
    notes: list[str] = []
    out = photo_mask(rgb, None, given, notes)
    assert not out[2:6, 2:6].any() and out[10:14, 10:14].all() and out.sum() == 17
    assert "mask: given (object: value > 127.5, half its maximum 255)" in notes
    assert not any("neither dark nor bright" in n for n in notes)
    clean = np.full((20, 20), 10, np.uint8)  # dark and bright, not 0 and 255
    clean[:, 10:] = 240
    notes = []
    photo_mask(rgb, None, clean, notes)
    assert not any("neither dark nor bright" in n for n in notes), notes
    notes = []
    photo_mask(rgb, None, np.linspace(0, 255, 400).reshape(20, 20).astype(np.uint8), notes)
    assert any("74% of its pixels are neither dark nor bright" in n for n in notes), notes


@pytest.mark.parametrize("peak", [1, 100, 255])
def test_a_mask_of_0_and_any_value_marks_the_same_object(peak):
    """0/1 (a boolean array saved as it is), 0/100 and 0/255 masks mark the same pixels, with no note; also when
    the mask is downscaled with a photo larger than ``MAX_SIDE`` (a 0/1 mask's averages are kept)."""
    given = np.zeros((20, 20), np.uint8)
    given[3:9, 4:15] = peak
    notes: list[str] = []
    assert np.array_equal(photo_mask(np.zeros((20, 20, 3), np.float32), None, given, notes), given > 0)
    assert not any("neither dark nor bright" in n for n in notes), notes
    big = np.kron(given, np.ones((2, 2), np.uint8))  # the mask of a photo twice the side, downscaled with it
    small = photo_mask(np.zeros((20, 20, 3), np.float32), None, big, [], source_size=big.shape)
    assert np.array_equal(small, given > 0)


def test_an_all_zero_mask_is_refused():
    with pytest.raises(DepthnerfError, match=r"^mask: the mask marks no object \(every pixel is 0\)$"):
        photo_mask(np.zeros((20, 20, 3), np.float32), None, np.zeros((20, 20), np.uint8), [])


def test_16_bit_pixels_are_divided_by_65535():
    arr = np.zeros((20, 20, 3), np.uint16)
    arr[0, 0], arr[0, 1] = 65535, (32768, 1, 0)
    rgb, alpha, _ = read_photo(arr, [])
    assert alpha is None and rgb[0, 0].tolist() == [1.0, 1.0, 1.0]
    np.testing.assert_allclose(rgb[0, 1], [32768 / 65535, 1 / 65535, 0.0], rtol=1e-6)


def test_a_side_below_the_minimum_once_downscaled_is_refused(tmp_path, capsys):
    """A 4000x20 photo is 1024x5 once its longer side is downscaled to ``MAX_SIDE``: refused like a 5 px photo
    (it was reconstructed into nothing, with exit status 0), by the header check ``reconstruct`` makes before
    loading a model and by the reader alike; 4000x63 (1024x16) is taken."""
    from PIL import Image

    from depthnerf.cli import main

    line = (f"{tmp_path / 'long.png'}: image is 4000x20 px, 1024x5 once downscaled to 1024 px on its longer side; "
            "at least 16 px per side are needed")
    Image.fromarray(np.full((20, 4000, 3), 255, np.uint8)).save(tmp_path / "long.png")
    assert main(["reconstruct", str(tmp_path / "long.png"), "--checkpoint", "cpu-cars-sym-pp", "--out",
                 str(tmp_path / "out")]) == 2
    assert capsys.readouterr().err == f"error: {line}\n"
    assert not (tmp_path / "out").exists()
    with pytest.raises(DepthnerfError, match=f"^{re.escape(line)}$"):
        read_photo(tmp_path / "long.png", [])
    with pytest.raises(DepthnerfError, match=r"^image: image is 20x4000 px, 5x1024 once downscaled"):
        read_photo(np.zeros((4000, 20, 3), np.uint8), [])
    notes: list[str] = []
    rgb, _, size = read_photo(np.zeros((63, 4000, 3), np.uint8), notes)
    assert rgb.shape[:2] == (16, 1024) and size == (63, 4000)
    assert notes == ["downscaled from 4000x63 to 1024x16 (box filter) first"]


def test_an_object_below_the_minimum_size_is_refused():
    """An object whose mask box is under ``MIN_OBJECT_SIDE`` (4) px on its longer side is a speck that framing
    would blow up to the model's fill: refused in one line naming the mask (or the photo, for a found mask)."""
    rgb = np.ones((40, 40, 3), np.float32)
    for box, taken in (((1, 1), False), ((3, 2), False), ((4, 1), True)):
        given = np.zeros((40, 40), np.uint8)
        given[10:10 + box[1], 20:20 + box[0]] = 255
        if taken:
            assert photo_mask(rgb, None, given, []).sum() == box[0] * box[1]
        else:
            with pytest.raises(DepthnerfError, match=rf"^mask: the object is {box[0]}x{box[1]} px \(its mask's box\); "
                                                     r"at least 4 px on its longer side are needed$"):
                photo_mask(rgb, None, given, [])
    speck = rgb.copy()
    speck[20, 20] = 0.0  # one dark pixel on white: the border-colour mask finds it alone
    with pytest.raises(DepthnerfError, match=r"^photo.png: the object is 1x1 px \(its mask's box\)"):
        photo_mask(speck, None, None, [], "photo.png")
    big = np.zeros((2048, 2048), np.uint8)
    big[1000:1006, 1000:1006] = 255  # 3 x 3 px once downscaled with a 2048 px photo
    with pytest.raises(DepthnerfError, match=r"^mask: the object is 3x3 px of the photo downscaled to 1024x1024 "):
        photo_mask(np.ones((1024, 1024, 3), np.float32), None, big, [], source_size=(2048, 2048))


@pytest.mark.parametrize("dtype, peak", [(np.float32, 0.9), (np.float64, 1.0), (np.uint16, 65535), (np.int32, 40000)])
def test_a_float_or_16_bit_mask_is_object_above_half_its_own_maximum(dtype, peak, tmp_path):
    """A soft mask (a segmentation model's scores in [0, 1], a 16-bit matte) splits at half its own maximum as an
    8-bit one does; read as 8-bit grey first, floats below 1 became 0 (a mask peaking at 0.9 'marked no object')
    and 16-bit values above 255 saturated (an edge at 200 of 65535 was object)."""
    rng = np.random.default_rng(5)
    given = np.zeros((20, 20), dtype)
    given[4:16, 4:16] = (rng.uniform(0.0, 1.0, (12, 12)) * peak).astype(dtype)
    given[0, 0] = dtype(peak)
    want = given.astype(np.float64) > float(given.max()) / 2
    assert 10 < want.sum() < 140
    notes: list[str] = []
    np.testing.assert_array_equal(photo_mask(np.zeros((20, 20, 3), np.float32), None, given, notes), want)
    assert f"half its maximum {float(given.max()):g}" in notes[0], notes
    if dtype == np.uint16:  # a 16-bit PNG mask file alike
        from PIL import Image

        Image.fromarray(given).save(tmp_path / "mask.png")
        np.testing.assert_array_equal(photo_mask(np.zeros((20, 20, 3), np.float32), None, tmp_path / "mask.png", []),
                                      want)


@pytest.mark.parametrize("channels", [2, 4])
def test_downscaling_an_array_with_alpha_does_not_bleed_transparent_colours(channels):
    """A 2048 px cut-out array (its transparent pixels random colours, as cut-outs leave them) downscaled 2x: each
    pixel composited on white is the 2 x 2 block's composite, ``mean(alpha * c) + 1 - mean(alpha)`` (straight
    colours averaged with alpha, as a PIL image is resampled); averaging the colours unweighted darkened or
    tinted the object's edge by the hidden colours."""
    rng = np.random.default_rng(7)
    arr = rng.integers(0, 256, (2048, 2048, channels)).astype(np.uint8)
    arr[..., -1] = 0
    arr[501:1501, 301:1701, :-1] = (200, 90, 30)[:channels - 1]
    arr[501:1501, 301:1701, -1] = 255
    arr[1600:1700, 101:201, -1] = 128  # half transparent, random colours
    rgb, alpha, _ = read_photo(arr, [])
    f = arr.astype(np.float64) / 255
    a = f[..., -1:]
    c = np.repeat(f[..., :1], 3, -1) if channels == 2 else f[..., :3]
    block = (a * c + 1 - a).reshape(1024, 2, 1024, 2, 3).mean(axis=(1, 3))
    np.testing.assert_allclose(rgb * alpha[..., None] + 1 - alpha[..., None], block, atol=1e-5)
    np.testing.assert_allclose(alpha, a[..., 0].reshape(1024, 2, 1024, 2).mean(axis=(1, 3)), atol=1e-6)


def test_a_given_mask_cuts_out_an_rgba_photo_whose_alpha_is_empty():
    """An RGBA photo whose alpha is 0 everywhere (an export that dropped it) with a mask: the mask's pixels are the
    photo's colours on white, noted; compositing on the empty alpha first made the whole input white, silently."""
    arr = np.zeros((32, 32, 4), np.uint8)
    arr[..., :3] = np.random.default_rng(2).integers(0, 200, (32, 32, 3))
    mask = np.zeros((32, 32), np.uint8)
    mask[8:24, 10:22] = 255
    prep = prepare_photo(arr, mask, 32, "keep")
    want = np.where(mask[..., None] > 0, arr[..., :3] / 255, 1.0)
    np.testing.assert_allclose(prep.image, want, atol=1e-6)
    assert any("alpha channel" in n and "ignored" in n for n in prep.notes), prep.notes
