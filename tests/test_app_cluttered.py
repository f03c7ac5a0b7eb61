"""The cluttered-background check of :mod:`depthnerf.reconstruct.photo`: a border-colour mask that is the scene,
not an object, is an error (also through ``depthnerf reconstruct``, exit 2); plain backgrounds, objects touching
the border, alpha cut-outs and the bundled examples still pass."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from depthnerf.cli import main
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.photo import MAX_BORDER_OBJECT, border_ring, prepare_photo

EXAMPLES = Path(__file__).resolve().parents[1] / "depthnerf" / "app" / "examples"


def object_on(background: np.ndarray) -> np.ndarray:
    """A red box in the middle of ``background`` (uint8 H x W x 3)."""
    img = background.copy()
    h, w = img.shape[:2]
    img[h // 3:2 * h // 3, w // 3:2 * w // 3] = (200, 30, 30)
    return img


def cluttered_backgrounds() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:120, :160]
    stripes = np.where(((xx // 7 + yy // 5) % 2)[..., None] == 1, [30, 120, 40], [200, 190, 90]).astype(np.uint8)
    gradient = np.stack([xx * 255 // 159, yy * 255 // 119, np.full_like(xx, 128)], -1).astype(np.uint8)
    return {"noise": rng.integers(0, 256, (120, 160, 3), dtype=np.uint8), "texture": stripes, "gradient": gradient}


@pytest.mark.parametrize("kind", ["noise", "texture", "gradient"])
def test_cluttered_background_is_an_error(kind):
    img = object_on(cluttered_backgrounds()[kind])
    with pytest.raises(DepthnerfError, match="background is not a plain colour.*RGBA cut-out") as info:
        prepare_photo(img, None, 64)
    assert "\n" not in str(info.value)
    # the same scene as an RGBA cut-out (alpha = the box) is fine: the alpha decides, not the colours
    alpha = np.zeros(img.shape[:2], np.uint8)
    alpha[40:80, 53:106] = 255
    prep = prepare_photo(np.dstack([img, alpha]), None, 64)
    assert "mask: alpha > 0.5" in prep.notes and prep.mask.any()


def test_border_ring_matches_a_brute_force_loop():
    mask = np.random.default_rng(2).random((10, 12)) > 0.5
    for ring in (1, 2, 3):
        expected = [mask[y, x] for y in range(10) for x in range(12) if min(y, x, 9 - y, 11 - x) < ring]
        got = border_ring(mask, ring)
        assert got.size == len(expected) and got.sum() == sum(expected)


def test_plain_backgrounds_and_objects_touching_the_border_pass():
    plain = np.full((120, 160, 3), (40, 90, 160), np.uint8)
    prep = prepare_photo(object_on(plain), None, 64)
    assert prep.mask.any()
    touching = plain.copy()
    touching[70:, 20:140] = (220, 220, 30)  # a wide object cut off by the bottom edge
    ring = border_ring(np.abs(touching.astype(int) - plain).max(-1) > 0, 2)  # the ring is 2 px at 120 px
    assert 0.1 < ring.mean() < MAX_BORDER_OBJECT
    assert prepare_photo(touching, None, 64).mask.any()
    noisy = plain.astype(np.int16) + np.random.default_rng(1).integers(-10, 11, plain.shape)  # sensor noise
    assert prepare_photo(object_on(noisy.clip(0, 255).astype(np.uint8)), None, 64).mask.any()


def test_bundled_examples_pass():
    files = sorted(EXAMPLES.glob("*.png"))
    assert len(files) >= 2
    for path in files:
        prep = prepare_photo(path, None, 64)
        assert 0.05 < prep.mask.mean() < 0.6, path


def test_reconstruct_cli_exits_2_on_a_cluttered_photo(tmp_path, capsys):
    photo = tmp_path / "scene.png"
    Image.fromarray(object_on(cluttered_backgrounds()["noise"])).save(photo)
    code = main(["reconstruct", str(photo), "--checkpoint", "cpu-cars-depth", "--out", str(tmp_path / "out"),
                 "--views", "1", "--no-progress"])
    err = capsys.readouterr().err
    assert code == 2 and err.startswith(f"error: {photo}: the background is not a plain colour")
    assert err.count("\n") == 1 and not (tmp_path / "out").exists()


@pytest.mark.parametrize("name", ["astronaut", "chelsea", "coffee", "rocket"])
def test_sample_photos_shipped_with_scikit_image_are_refused(name):
    """The issue's case: a new user tries a sample photo from an installed package (these ship inside
    scikit-image, nothing is downloaded): scenes, not objects on a plain background."""
    import skimage.data

    with pytest.raises(DepthnerfError, match="background is not a plain colour"):
        prepare_photo(getattr(skimage.data, name)(), None, 64)


def test_a_silhouette_on_white_from_scikit_image_passes():
    import skimage.data

    prep = prepare_photo(skimage.data.horse(), None, 64)  # a black horse on white: one object, plain background
    assert 0.1 < prep.mask.mean() < 0.6
