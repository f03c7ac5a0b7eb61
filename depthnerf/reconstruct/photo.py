"""Reading, masking and framing one photo for a model (the first step of :mod:`depthnerf.reconstruct`).

Input photo (assumption: ONE object, roughly centred, on a plain background)
    A PNG, JPEG or WebP file (:data:`PHOTO_FORMATS`; other formats, GIF animations included, are refused with one
    line, by ``depthnerf reconstruct`` and the app alike; arrays and in-memory images are taken as they are, an
    array as uint8, uint16 or float values in [0, 1] (NaN, floats outside [0, 1] and other integer types holding
    8-bit values are an error); of an animated PNG or WebP the first frame is read, noted);
    a file with an EXIF orientation tag (a camera's portrait JPEG) is turned upright as viewers show it, and so
    is a mask file (noted); grayscale is replicated to RGB (noted); sides below :data:`MIN_SIDE` px are an error;
    images larger than :data:`MAX_SIDE` px are first downscaled (box filter, aspect ratio kept) so the longer side
    is ``MAX_SIDE`` (noted), and a side that this leaves below :data:`MIN_SIDE` is an error too (a 4000x20
    photo). An object whose mask box is below :data:`MIN_OBJECT_SIDE` px on its longer side is an error. Mask, in
    order: the given mask (a pixel is object where its value is above half the mask's own maximum, so 0/1, 0/100
    and 0/255 masks all work and an anti-aliased 0..255 edge splits at 127.5; an all-zero mask is an error; same
    size as the upright image; an alpha channel with no pixel above 0.5 is then ignored, noted);
    else the alpha channel (``alpha > 0.5``) when the image has a non-opaque alpha (a grey or RGB PNG's colour
    key counts as alpha: :func:`depthnerf.data.png_files.with_colour_key`); else, with a background model
    (:mod:`depthnerf.reconstruct.background`), its foreground score as the alpha (then as for alpha; the RGBA
    cut-out is kept in :attr:`PreparedImage.cutout`); else the *background colour* = the per-channel median
    of the image border (a ring ``max(1, 2%)`` of the shorter side wide) and object = pixels whose largest channel
    difference from it exceeds :data:`BACKGROUND_TOLERANCE` (0.1, i.e. ~26 of 255 levels). Background pixels are
    then set to white (alpha is composited on white), as in the SRN training images.
Cluttered background (border-colour mask only)
    A plain background makes the border ring nearly all background. When more than :data:`MAX_BORDER_OBJECT`
    (35 %) of the ring's pixels differ from the border colour (a non-uniform border: texture, a scene, a
    gradient), or the mask covers more than :data:`MAX_OBJECT_AREA` (90 %) of the image, the mask is not an
    object but the scene: a :class:`~depthnerf.errors.DepthnerfError` says why no background model removed it
    (the extra or its weights missing: how to get them) and asks for an RGBA cut-out or a mask instead of
    reconstructing smears. (An object may touch the border: it then covers a minority of the ring.)
Framing rule
    :mod:`depthnerf.data.photo_framing` (recentred on the mask, scaled to the model's fill, resampled).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
import torch.nn.functional as F
from jaxtyping import Bool, Float
from PIL import Image, ImageOps

from depthnerf.data.photo_framing import DEFAULT_FILL, frame_photo
from depthnerf.data.png_files import with_colour_key
from depthnerf.data.srn import mask_bboxes
from depthnerf.errors import DepthnerfError
from depthnerf.reconstruct.background import BackgroundRemover

MIN_SIDE = 16
"""Smallest accepted image side (pixels), also after a downscale to :data:`MAX_SIDE`."""
MIN_OBJECT_SIDE = 4
"""Smallest accepted longer side (pixels) of the object's mask box: a smaller object is a speck, which framing
would blow up to the model's fill."""
MAX_SIDE = 1024
"""Longer image sides are downscaled to this first."""
FLOAT_SLACK = 0.01
"""How far outside [0, 1] a float photo array may go (resampling overshoot, clipped); further is an error."""
BACKGROUND_TOLERANCE = 0.1
"""Largest per-channel difference from the border colour that still counts as background (in [0, 1])."""
ALPHA_THRESHOLD = 0.5
"""Alpha above this is object."""
MAX_BORDER_OBJECT = 0.35
"""Largest fraction of the border ring the border-colour mask may cover before the background counts as cluttered."""
MAX_OBJECT_AREA = 0.9
"""Largest fraction of the image the border-colour mask may cover before the background counts as cluttered."""
PHOTO_FORMATS = {"PNG": "PNG", "JPEG": "JPEG", "MPO": "JPEG", "WEBP": "WebP"}
"""Accepted photo file formats: Pillow's format name -> the name shown (MPO: a camera's multi-picture JPEG)."""
ImageLike = str | Path | np.ndarray | Image.Image
EXIF_ORIENTATION = 0x0112
"""The EXIF tag that says how a file's stored pixels are turned for display (1: as stored)."""
MASK_DARK = 32
"""A given mask's values <= this (or >= 255 - this) count as dark (bright) when its maximum is 255, scaled by its
own maximum else; a mask is mostly one or the other."""
MASK_GREY_SHARE = 0.1
"""A given mask with more than this share of values between dark and bright gets a note (it may be a photo)."""


@dataclass
class PreparedImage:
    """The photo as the model sees it."""

    image: Float[np.ndarray, "H W 3"]
    """RGB in [0, 1] on white, square, at the training resolution."""
    mask: Bool[np.ndarray, "H W"]
    """Object pixels."""
    notes: list[str]
    """What was done to the input (grayscale, downscaled, mask source, crop)."""
    source_size: tuple[int, int]
    """(height, width) of the file as read."""
    cutout: Float[np.ndarray, "h w 4"] | None = None
    """The photo as read (after any downscale) with the background model's alpha, in [0, 1]; None when no model
    ran."""


def _to_float(arr: np.ndarray) -> np.ndarray:
    """Float32 ``H x W x C`` in [0, 1] from 8-bit, 16-bit or float pixels."""
    arr = arr[..., None] if arr.ndim == 2 else arr
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / 255.0
    if arr.dtype.kind in "iu":
        return arr.astype(np.float32) / 65535.0
    return np.clip(arr.astype(np.float32), 0.0, 1.0)


def _check_array_values(arr: np.ndarray) -> None:
    """A photo given as an array whose values :func:`_to_float` would misread (NaN, floats outside [0, 1], 8-bit
    values in a wide integer type, which read as 16-bit are nearly black): one line saying what was expected."""
    if arr.dtype.kind not in "biuf":
        raise DepthnerfError(f"image: an array of {arr.dtype} is not pixels; pass uint8, uint16 or float values "
                             "in [0, 1]")
    if arr.dtype.kind == "f":
        bad = int((~np.isfinite(arr)).sum())
        if bad:
            raise DepthnerfError(f"image: the array holds NaN or inf ({bad} of {arr.size} values)")
        low, high = float(arr.min()), float(arr.max())
        if low < -FLOAT_SLACK or high > 1 + FLOAT_SLACK:
            hint = "; divide 8-bit values by 255 or pass a uint8 array" if low >= 0 and high <= 255 else ""
            raise DepthnerfError(f"image: a float array is read as values in [0, 1], got {low:g} to {high:g}{hint}")
    elif arr.dtype.kind in "iu" and arr.dtype not in (np.uint8, np.uint16) and arr.size:
        low, high = int(arr.min()), int(arr.max())
        if low < 0 or high > 65535 or high <= 255:
            raise DepthnerfError(f"image: {arr.dtype} pixels are read as 16-bit values (0-65535), got {low} to "
                                 f"{high}; pass 8-bit values as a uint8 array and 16-bit ones as uint16")


def check_photo_format(fmt: str | None, name: str) -> None:
    """One line when a file's Pillow format ``fmt`` is not a :data:`PHOTO_FORMATS` one (None: not from a file)."""
    if fmt is not None and fmt not in PHOTO_FORMATS:
        raise DepthnerfError(f"{name}: {fmt} images are not supported; use a PNG, JPEG or WebP photo")


def upright(im: Image.Image, notes: list[str] | None = None, what: str = "image") -> Image.Image:
    """A file's image as viewers show it: turned / mirrored by its EXIF orientation tag (a camera's portrait JPEG
    stores landscape pixels and this tag), noted in ``notes``; unchanged without a tag."""
    try:
        orientation = im.getexif().get(EXIF_ORIENTATION, 1)
    except (OSError, ValueError, SyntaxError):  # an unreadable EXIF block: the pixels as stored
        return im
    if orientation not in range(2, 9):
        return im
    if notes is not None:
        notes.append(f"{what}: turned upright by its EXIF orientation tag ({orientation})")
    return ImageOps.exif_transpose(im)


@contextmanager
def _read_errors(name: str, what: str, *more: type[Exception]) -> Iterator[None]:
    """Reading the photo (``what="image"``) or a mask file named ``name`` inside: a missing file, a folder or an
    unreadable file (``more``: other exception types that mean unreadable) becomes one line naming it."""
    try:
        yield
    except FileNotFoundError:
        raise DepthnerfError(f"{name}: {what} file not found") from None
    except IsADirectoryError:
        raise DepthnerfError(f"{name}: is a folder, not {'an image' if what == 'image' else 'a mask'} file") from None
    except (OSError, ValueError, Image.DecompressionBombError, *more) as err:
        raise DepthnerfError(f"{name}: unreadable {what} ({err})") from None


def checked_size(size: tuple[int, int], name: str) -> tuple[int, int]:
    """The ``(height, width)`` a photo of ``size`` is read at: downscaled so that its longer side is at most
    :data:`MAX_SIDE` (aspect ratio kept); either side below :data:`MIN_SIDE`, as given or after the downscale, is
    one line naming the photo ``name`` and its sizes."""
    height, width = size
    if min(size) < MIN_SIDE:
        raise DepthnerfError(f"{name}: image is {width}x{height} px; at least {MIN_SIDE} px per side are needed")
    if max(size) <= MAX_SIDE:
        return size
    scale = MAX_SIDE / max(size)
    small = (max(1, round(height * scale)), max(1, round(width * scale)))
    if min(small) < MIN_SIDE:
        raise DepthnerfError(f"{name}: image is {width}x{height} px, {small[1]}x{small[0]} once downscaled to "
                             f"{MAX_SIDE} px on its longer side; at least {MIN_SIDE} px per side are needed")
    return small


def check_image_file(path: str | Path, what: str = "image") -> None:
    """Fail at once, before any model loads, when ``path`` cannot be the photo (``what="image"``: missing, a
    folder, not an image, not a :data:`PHOTO_FORMATS` format, a side below :data:`MIN_SIDE` as read or once
    downscaled, :func:`checked_size`) or the mask
    (``what="mask"``); only the header is read (a truncated file fails when :func:`prepare_photo` reads it)."""
    name = str(path)
    with _read_errors(name, what), Image.open(path) as im:
        size = im.size
        if what == "image":
            check_photo_format(im.format, name)
    if what == "image":
        checked_size((size[1], size[0]), name)


def _open(source: str | Path | Image.Image, name: str, notes: list[str]) -> Image.Image:
    with _read_errors(name, "image"):
        im = source if isinstance(source, Image.Image) else Image.open(source)
        if not isinstance(source, Image.Image):
            check_photo_format(im.format, name)
        im.load()
        if getattr(im, "is_animated", False):  # an animated PNG or WebP: its first frame, as a viewer's still
            notes.append(f"animated image: the first of its {im.n_frames} frames is used")
        im = with_colour_key(im, name, None if isinstance(source, Image.Image) else Path(source))
        if not isinstance(source, Image.Image):
            im = upright(im, notes)
    if im.mode in ("P", "PA", "CMYK", "YCbCr", "HSV", "LAB", "RGBa", "La"):
        return im.convert("RGBA")
    if im.mode == "1" or im.mode.startswith("I;16"):
        return im.convert("L" if im.mode == "1" else "I")
    return im


def read_photo(source: ImageLike, notes: list[str]) -> tuple[np.ndarray, np.ndarray | None, tuple[int, int]]:
    """``(rgb [H, W, 3], alpha [H, W] or None, (H, W) as read)`` in [0, 1], grayscale replicated, images
    larger than :data:`MAX_SIDE` downscaled (see the module docstring); ``notes`` collects what was done."""
    if not isinstance(source, str | Path | np.ndarray | Image.Image):
        raise DepthnerfError(f"image must be a file path, a PIL image or a numpy array, got {type(source).__name__}")
    name = str(source) if isinstance(source, str | Path) else "image"
    im = None if isinstance(source, np.ndarray) else _open(source, name, notes)
    if im is None:
        arr = np.asarray(source)
        if arr.ndim not in (2, 3) or (arr.ndim == 3 and arr.shape[-1] not in (1, 2, 3, 4)):
            raise DepthnerfError(f"image: expected an H x W (x 1|2|3|4) array, got shape {arr.shape}")
        _check_array_values(arr)
        size = arr.shape[:2]
    else:
        size = (im.height, im.width)
    small = checked_size(size, name)
    if small != size:
        notes.append(f"downscaled from {size[1]}x{size[0]} to {small[1]}x{small[0]} (box filter) first")
        if im is not None:
            im = im.resize((small[1], small[0]), Image.Resampling.BOX)
    if im is not None:
        img = _to_float(np.asarray(im))
    else:
        img = _to_float(arr)
        if small != size:  # colours averaged with alpha (premultiplied), as Pillow resamples an image with alpha
            has_alpha = img.shape[-1] in (2, 4)
            if has_alpha:
                img = np.concatenate([img[..., :-1] * img[..., -1:], img[..., -1:]], axis=-1)
            t = torch.from_numpy(np.ascontiguousarray(img)).permute(2, 0, 1)[None]
            img = F.interpolate(t, size=small, mode="area")[0].permute(1, 2, 0).numpy()
            if has_alpha:
                a = img[..., -1:]
                img = np.concatenate([np.clip(img[..., :-1] / np.maximum(a, 1e-12), 0.0, 1.0), a], axis=-1)
    if img.shape[-1] in (1, 2):
        notes.append("grayscale image: replicated to RGB")
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    alpha = img[..., 3] if img.shape[-1] == 4 else None
    if alpha is not None and alpha.min() >= 1.0:
        alpha = None
    return np.ascontiguousarray(img[..., :3]), alpha, size


def photo_mask(rgb: np.ndarray, alpha: np.ndarray | None, mask: ImageLike | None, notes: list[str],
               name: str = "image", source_size: tuple[int, int] | None = None, hint: str | None = None
               ) -> np.ndarray:
    """The object mask by the rule of the module docstring (given mask, alpha, or border background colour).

    A given mask must have the image's size as read (``source_size``); it is downscaled with the image. ``hint``:
    why no background model ran (part of the cluttered-background error).
    """
    height, width = rgb.shape[:2]
    if mask is not None:
        where = "mask" if isinstance(mask, np.ndarray | Image.Image) else str(mask)
        with _read_errors(where, "mask", TypeError):  # TypeError: an array Pillow cannot take
            im = Image.fromarray(np.asarray(mask)) if isinstance(mask, np.ndarray) else (
                mask if isinstance(mask, Image.Image) else upright(Image.open(mask), notes, "mask"))
            # float: a downscaled 0/1 mask keeps its averages; float and 16/32-bit masks keep their values (8-bit
            # grey first made soft scores below 1 zero and saturated 16-bit values above 255)
            wide = im.mode in ("F", "I") or im.mode.startswith("I;16")
            im = im.convert("F") if wide else im.convert("L").convert("F")
        if source_size is not None and (im.height, im.width) == source_size != (height, width):
            im = im.resize((width, height), Image.Resampling.BOX)
        if (im.height, im.width) != (height, width):
            raise DepthnerfError(f"{where}: mask is {im.width}x{im.height} but the image is "
                                 f"{(source_size or (height, width))[1]}x{(source_size or (height, width))[0]}")
        values = np.asarray(im, dtype=np.float32)
        peak = float(values.max())
        if peak <= 0:
            raise DepthnerfError(f"{where}: the mask marks no object (every pixel is 0)")
        notes.append(f"mask: given (object: value > {peak / 2:g}, half its maximum {peak:g})")
        dark, bright = peak * MASK_DARK / 255, peak * (255 - MASK_DARK) / 255
        grey = float(((values > dark) & (values < bright)).mean())
        if grey > MASK_GREY_SHARE:
            notes.append(f"mask: {grey:.0%} of its pixels are neither dark nor bright (a photo rather than a mask?); "
                         "check input_mask.png")
        out = values > peak / 2
    elif alpha is not None:
        notes.append(f"mask: alpha > {ALPHA_THRESHOLD}")
        out = alpha > ALPHA_THRESHOLD
    else:
        ring = max(1, round(0.02 * min(height, width)))
        border = np.concatenate([rgb[:ring].reshape(-1, 3), rgb[-ring:].reshape(-1, 3),
                                 rgb[:, :ring].reshape(-1, 3), rgb[:, -ring:].reshape(-1, 3)])
        bg = np.median(border, axis=0)
        out = np.abs(rgb - bg).max(axis=-1) > BACKGROUND_TOLERANCE
        notes.append(f"mask: pixels differing from the border colour {np.round(bg * 255).astype(int).tolist()} by "
                     f"more than {BACKGROUND_TOLERANCE}")
        check_plain_background(out, ring, name, hint)
    if not out.any():
        if alpha is not None:
            raise DepthnerfError(f"{name}: no object found (the alpha channel is transparent everywhere)")
        raise DepthnerfError(f"{name}: no object found (every pixel has the border's colour); pass a mask (--mask)")
    check_object_size(out, where if mask is not None else name, source_size)
    return out


def check_object_size(mask: np.ndarray, name: str, source_size: tuple[int, int] | None = None) -> None:
    """Refuse an object whose mask box is below :data:`MIN_OBJECT_SIDE` px on its longer side, in one line naming
    ``name`` (the mask file, or the photo); ``source_size``: the photo's size as read, named when it was
    downscaled."""
    x0, y0, x1, y1 = mask_bboxes(torch.from_numpy(mask)[None])[0].tolist()
    height, width = y1 - y0 + 1, x1 - x0 + 1
    if max(height, width) >= MIN_OBJECT_SIDE:
        return
    scaled = (f" of the photo downscaled to {mask.shape[1]}x{mask.shape[0]}"
              if source_size is not None and tuple(source_size) != mask.shape else "")
    raise DepthnerfError(f"{name}: the object is {width}x{height} px{scaled} (its mask's box); at least "
                         f"{MIN_OBJECT_SIDE} px on its longer side are needed")


def border_ring(mask: np.ndarray, ring: int) -> np.ndarray:
    """The values of ``mask`` in the border ring ``ring`` pixels wide (corners counted once)."""
    inner = np.ones(mask.shape, dtype=bool)
    inner[ring:-ring, ring:-ring] = False
    return mask[inner]


def check_plain_background(mask: np.ndarray, ring: int, name: str, hint: str | None = None) -> None:
    """Reject a border-colour mask that is the scene rather than an object (module docstring); ``hint`` says why
    no background model removed the background."""
    border = float(border_ring(mask, ring).mean())
    area = float(mask.mean())
    if border > MAX_BORDER_OBJECT or area > MAX_OBJECT_AREA:
        raise DepthnerfError(
            f"{name}: the background is not a plain colour (the border-colour mask covers {border:.0%} of the border "
            f"and {area:.0%} of the image), so no object can be cut out; {hint + '; or ' if hint else ''}use an "
            "RGBA cut-out with a transparent background or pass a mask (--mask)")


def prepare_photo(image: ImageLike, mask: ImageLike | None, resolution: int, framing: str = "auto",
                  fill: float = DEFAULT_FILL, background: BackgroundRemover | None = None) -> PreparedImage:
    """Read, mask and frame a photo for a model trained at ``resolution`` (module docstring); ``background``
    removes the background of a photo without mask or alpha (when it holds a model; else its reason goes into
    the cluttered-background error)."""
    notes: list[str] = []
    rgb, alpha, size = read_photo(image, notes)
    name = str(image) if isinstance(image, str | Path) else "image"
    if mask is not None and alpha is not None and not (alpha > ALPHA_THRESHOLD).any():
        notes.append("alpha channel: transparent everywhere, ignored (the given mask cuts out the object)")
        alpha = None  # composited on it, the whole photo was white
    cutout = None
    if mask is None and alpha is None and background is not None:
        if background.available:
            alpha = background.foreground(rgb)
            cutout = np.dstack([rgb, alpha])
            notes.append(f"background removed by the {background.name} model (rembg): its foreground score is the "
                         "alpha")
        elif background.required:
            raise DepthnerfError(f"{name}: {background.reason}")
    m = photo_mask(rgb, alpha, mask, notes, name, size, background.reason if background is not None else None)
    img, m_small = frame_photo(rgb, alpha, m, resolution, framing, fill, notes)
    return PreparedImage(image=img, mask=m_small, notes=notes, source_size=size, cutout=cutout)
