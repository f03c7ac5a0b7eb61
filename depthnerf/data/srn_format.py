"""File-level reading and writing of the ShapeNet SRN format (the layout pixelNeRF uses).

One object folder ``<root>/<category>_<split>/<object_id>/`` holds::

    intrinsics.txt        4 lines: "f cx cy 0." / "0. 0. 0." / "1." / "H W"   (f, c in pixels of an H x W image)
    rgb/NNNNNN.png        RGB or RGBA, 8- or 16-bit; RGBA is composited on white, and so is a colour key
    pose/NNNNNN.txt       16 numbers, a 4x4 camera-to-world matrix, OpenCV camera axes (see ``cameras``)
    depth/NNNNNN.npz      optional: float z-depth under key "depth", 0 where there is no surface (what we write)
          NNNNNN.npy      optional: the same as one ``np.save`` array
          NNNNNN.png      optional: 16-bit grey, z-depth = value * scale (scale from ``depth_scale.txt``)
    mask/NNNNNN.png       optional: any PNG bit depth and mode, non-zero colour = object
    mesh.ply              optional: the ground-truth mesh in world coordinates

EXR depth is refused (:data:`EXR_UNSUPPORTED`). Every reader raises :class:`~depthnerf.errors.DepthnerfError`
with one line naming the file and the problem. Which files an object folder uses, and what happens when an
optional one is bad, is :mod:`depthnerf.data.srn_parts`'s business.

The text readers (intrinsics, poses, ``depth_scale.txt``) skip a UTF-8 byte-order mark (Windows editors write
one). The text writers (intrinsics, poses) write atomically through :mod:`depthnerf.files`. The image and depth writers
write in place: a dataset generator marks a finished object by writing its own marker last
(:mod:`depthnerf.data.synth.generate`), which is what makes a torn view file impossible to mistake for a
finished one.
"""

from __future__ import annotations

import io
import zipfile
from pathlib import Path

import numpy as np
from PIL import Image, UnidentifiedImageError

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.png_files import is_sixteen_bit_colour_png, with_colour_key
from depthnerf.errors import DepthnerfError
from depthnerf.files import write_text_atomic

NOT_AN_IMAGE = "not an image: the file is empty or of a format Pillow does not know"
"""Why a file that Pillow cannot identify is unreadable (its own message repeats the path)."""

RIGID_TOL = 1e-3
"""Tolerance on ``R^T R = I``, ``det R = 1`` and the last row ``[0 0 0 1]`` of a pose."""


def read_intrinsics(path: Path) -> Intrinsics:
    """Parse ``intrinsics.txt`` (focal, principal point on line 1; ``H W`` on the last line)."""
    path = Path(path)
    try:
        lines = [ln.split() for ln in path.read_text(encoding="utf-8-sig").splitlines() if ln.strip()]
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read intrinsics ({err.strerror or err})") from None
    except UnicodeDecodeError:
        raise DepthnerfError(f"{path}: malformed intrinsics (not a text file)") from None
    try:
        focal, cx, cy = (float(x) for x in lines[0][:3])
        size = [float(x) for x in lines[-1][:2]]
        if len(lines) < 2 or len(size) < 2:
            raise ValueError
    except (ValueError, IndexError):
        raise DepthnerfError(f"{path}: malformed intrinsics (expected 'f cx cy 0.' ... 'H W')") from None
    if not all(np.isfinite(size)) or not all(x.is_integer() for x in size):
        raise DepthnerfError(f"{path}: image size '{' '.join(lines[-1][:2])}' on the last line is not two whole "
                             "numbers 'H W'")
    height, width = (int(x) for x in size)
    if not all(np.isfinite([focal, cx, cy])) or focal <= 0 or height <= 0 or width <= 0:
        raise DepthnerfError(f"{path}: invalid intrinsics values f={focal} c=({cx},{cy}) size={height}x{width}")
    if not (0 <= cx <= width and 0 <= cy <= height):  # a camera's optical axis meets its own image
        raise DepthnerfError(f"{path}: principal point ({cx:g}, {cy:g}) lies outside the {height}x{width} image")
    return Intrinsics(focal=focal, cx=cx, cy=cy, height=height, width=width)


def write_intrinsics(path: Path, intr: Intrinsics) -> None:
    """Write ``intrinsics.txt`` in the SRN layout (atomically)."""
    write_text_atomic(path, f"{intr.focal:.6f} {intr.cx:.6f} {intr.cy:.6f} 0.\n0. 0. 0.\n1.\n{intr.height} {intr.width}\n")


def read_pose(path: Path) -> np.ndarray:
    """Read a 4x4 camera-to-world pose and check that it is a finite rigid transform."""
    path = Path(path)
    try:
        values = np.array(path.read_text(encoding="utf-8-sig").split(), dtype=np.float64)
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read pose ({err.strerror or err})") from None
    except ValueError:
        raise DepthnerfError(f"{path}: pose is not 16 numbers") from None
    if values.size != 16:
        raise DepthnerfError(f"{path}: pose has {values.size} numbers, expected 16 (a 4x4 matrix)")
    pose = values.reshape(4, 4)
    if not np.all(np.isfinite(pose)):
        raise DepthnerfError(f"{path}: pose contains NaN or inf")
    rot = pose[:3, :3]
    if (np.abs(rot.T @ rot - np.eye(3)).max() > RIGID_TOL or abs(np.linalg.det(rot) - 1) > RIGID_TOL
            or np.abs(pose[3] - [0, 0, 0, 1]).max() > RIGID_TOL):
        raise DepthnerfError(f"{path}: pose is not a rigid transform (rotation not orthonormal or bad last row)")
    return pose.astype(np.float32)


def check_cameras_face_origin(first_pose: Path, poses: np.ndarray) -> None:
    """Refuse poses ``[V, 4, 4]`` every one of which looks away from the world origin, where the object is
    expected: the camera's +z axis (OpenCV's viewing direction) at more than 90 degrees from the direction to the
    origin. That is what OpenGL / Blender camera axes (looking down -z) give; the loaders do not convert them."""
    away = np.einsum("vi,vi->v", poses[:, :3, 2], -poses[:, :3, 3]) < 0
    if away.size and away.all():
        raise DepthnerfError(f"{first_pose}: every camera of this object looks away from the world origin, where the "
                             "object is expected (its +z axis, OpenCV's viewing direction, points away): OpenGL / "
                             "Blender camera axes look down -z; convert each pose with c2w @ diag(1, -1, -1, 1)")


def write_pose(path: Path, c2w: np.ndarray) -> None:
    """Write a 4x4 camera-to-world pose as 16 numbers on one line (atomically)."""
    write_text_atomic(path, " ".join(f"{v:.8f}" for v in np.asarray(c2w, dtype=np.float64).reshape(-1)) + "\n")


def read_rgb(path: Path) -> np.ndarray:
    """Read an RGB(A) PNG of 8 or 16 bits as float32 ``H x W x 3`` in [0, 1], alpha composited on white (a grey or
    RGB file's colour-key transparency too, as alpha: :func:`depthnerf.data.png_files.with_colour_key`).

    A 16-bit colour PNG whose high bytes are all zero (8-bit values stored in 16 bits, which Pillow's 8-bit reading
    of 16-bit colour would turn into a black or, with alpha, a blank image) is an error naming the file.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im.load()
            im = with_colour_key(im, str(path), path)  # a grey or RGB file's transparent colour, as alpha
            if im.mode in ("P", "PA", "LA", "CMYK", "YCbCr", "HSV", "1"):
                im = im.convert("RGBA")  # palette and other modes: let PIL resolve them to colours
            arr = np.asarray(im)
            mode = im.mode
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: image file is missing") from None
    except UnidentifiedImageError:
        raise DepthnerfError(f"{path}: unreadable image ({NOT_AN_IMAGE})") from None
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable image ({err})") from None
    if arr.dtype == np.uint8:
        if not arr.any() and is_sixteen_bit_colour_png(path):
            raise DepthnerfError(f"{path}: a 16-bit colour PNG whose values all lie below 256 (8-bit values saved as "
                                 "16-bit?); it would read as a blank image: re-save it as an 8-bit PNG")
        img = arr.astype(np.float32) / 255.0
    elif arr.dtype in (np.uint16, np.int32, np.uint32) or mode.startswith("I;16") or mode == "I":
        img = arr.astype(np.float32) / 65535.0
    else:
        img = arr.astype(np.float32)
    if img.ndim == 2:
        img = np.repeat(img[..., None], 3, axis=-1)
    elif img.shape[-1] == 2:  # grey + alpha
        img = np.concatenate([np.repeat(img[..., :1], 3, axis=-1), img[..., 1:]], axis=-1)
    if img.shape[-1] == 4:
        alpha = img[..., 3:]
        img = img[..., :3] * alpha + (1.0 - alpha)
    if img.ndim != 3 or img.shape[-1] != 3:
        raise DepthnerfError(f"{path}: unsupported image layout {arr.shape} (mode {mode})")
    return np.clip(img, 0.0, 1.0)


def write_rgb(path: Path, img: np.ndarray) -> None:
    """Write float ``H x W x 3`` in [0, 1] (or uint8) as an 8-bit RGB PNG."""
    arr = np.asarray(img)
    if arr.dtype != np.uint8:
        arr = np.round(np.clip(arr, 0.0, 1.0) * 255.0).astype(np.uint8)
    Image.fromarray(arr, mode="RGB").save(path)


DEPTH_SUFFIXES = (".npz", ".npy", ".png")
"""Depth file formats read, in order of preference when one view has files in several."""

DEPTH_SCALE_FILE = "depth_scale.txt"
"""Name of the file that gives 16-bit PNG depth its scale: one number, world units per PNG unit."""

EXR_UNSUPPORTED = ("EXR depth is not supported: no kept library reads OpenEXR (Pillow has no EXR decoder, imageio "
                   "needs a FreeImage binary it would download, OpenCV is not a dependency); convert it to .npy or .npz")
"""Why ``.exr`` depth maps are refused (one line, used in errors and warnings)."""

_PNG16_MODES = ("I;16", "I;16B", "I;16L", "I")
_NUMPY_SIGNATURES = {".npz": (b"PK\x03\x04", b"PK\x05\x06"), ".npy": (b"\x93NUMPY",)}
"""The first bytes of a NumPy ``.npz`` (a zip archive, possibly empty) and ``.npy`` file."""


def _check_numpy_signature(path: Path, suffix: str) -> None:
    """One line when the file is not what its suffix says (numpy would try to unpickle it and say so)."""
    with open(path, "rb") as handle:
        head = handle.read(8)
    if not head.startswith(_NUMPY_SIGNATURES[suffix]):
        what = "empty" if not head else f"corrupt or not a NumPy {suffix} file"
        raise DepthnerfError(f"{path}: unreadable depth map: the file is {what}; rewrite it with "
                             f"numpy.{'savez' if suffix == '.npz' else 'save'}")


def _png16_mode_error(path: Path, mode: str) -> DepthnerfError:
    return DepthnerfError(f"{path}: PNG depth must be 16-bit grey, got mode {mode} (8-bit depth is too coarse; "
                          "store 16-bit PNG, .npy or .npz)")


def check_png_depth_mode(path: Path) -> None:
    """Check from its header that a PNG depth file is 16-bit grey (the error :func:`read_depth` would give), so
    that a file no scale can help is reported before a missing ``depth_scale.txt``."""
    path = Path(path)
    try:
        with Image.open(path) as im:
            mode = im.mode
    except (OSError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable depth map ({err})") from None
    if mode not in _PNG16_MODES:
        raise _png16_mode_error(path, mode)


def _depth_png(path: Path, png_scale: float | None) -> np.ndarray:
    with Image.open(path) as im:
        im.load()
        mode = im.mode
        arr = np.asarray(im)
    if mode not in _PNG16_MODES:
        raise _png16_mode_error(path, mode)
    if png_scale is None:
        raise DepthnerfError(f"{path}: 16-bit PNG depth needs a scale: write the world units per PNG unit (e.g. "
                             f"0.001) into {DEPTH_SCALE_FILE} in the object, split or dataset folder")
    return (arr.astype(np.float64) * png_scale).astype(np.float32)


def read_depth(path: Path, png_scale: float | None = None, shape: tuple[int, int] | None = None,
               allow_empty: bool = False) -> np.ndarray:
    """Read and check a z-depth map (0 = no surface) as float32 ``H x W``.

    ``.npz`` (key ``depth``) and ``.npy`` hold float arrays and are never unpickled; ``.png`` is 16-bit grey
    times ``png_scale`` (world units per PNG unit). ``shape``: the expected ``(H, W)``. A map must be finite,
    non-negative and, unless ``allow_empty``, not all zero (see :func:`check_depth`).
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        raise DepthnerfError(f"{path}: {EXR_UNSUPPORTED}")
    if suffix not in DEPTH_SUFFIXES:
        raise DepthnerfError(f"{path}: unknown depth format {suffix!r} (expected one of {', '.join(DEPTH_SUFFIXES)})")
    try:
        if suffix == ".png":
            depth = _depth_png(path, png_scale)
        elif suffix == ".npy":
            _check_numpy_signature(path, suffix)
            depth = np.load(path, allow_pickle=False)
        else:
            _check_numpy_signature(path, suffix)
            with np.load(path, allow_pickle=False) as data:
                depth = data["depth"]
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: depth file is missing") from None
    except KeyError:
        raise DepthnerfError(f"{path}: depth file has no 'depth' array") from None
    except ValueError as err:
        if "pickle" in str(err):
            raise DepthnerfError(f"{path}: unreadable depth map: it holds Python objects, not a float array "
                                 "(never unpickled); store the depth as a float array") from None
        raise DepthnerfError(f"{path}: unreadable depth map ({err})") from None
    except (zipfile.BadZipFile, EOFError) as err:
        raise DepthnerfError(f"{path}: unreadable depth map: a truncated or corrupt {suffix} file ({err})") from None
    except (OSError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable depth map ({err})") from None
    return check_depth(path, depth, shape, allow_empty)


def check_depth(path: Path, depth: np.ndarray, shape: tuple[int, int] | None = None,
                allow_empty: bool = False) -> np.ndarray:
    """``depth`` as float32 ``H x W`` (an ``H x W x 1`` array is squeezed), or an error naming ``path`` if it is
    not a float array, has the wrong shape, holds NaN/inf or negative values, or is all zero (unless
    ``allow_empty``: the caller checks that the view shows nothing, see :func:`check_empty_depth`)."""
    depth = np.asarray(depth)
    if depth.dtype.kind != "f":
        raise DepthnerfError(f"{path}: depth map holds {depth.dtype} values, expected floats (integer depth: store "
                             f"it as 16-bit PNG with {DEPTH_SCALE_FILE})")
    if depth.ndim == 3 and depth.shape[-1] == 1:
        depth = depth[..., 0]
    if depth.ndim != 2 or (shape is not None and depth.shape != tuple(shape)):
        want = f"{shape[0]}x{shape[1]} (intrinsics.txt)" if shape is not None else "H x W"
        raise DepthnerfError(f"{path}: depth map has shape {depth.shape}, expected {want}")
    bad = ~np.isfinite(depth)
    if bad.any():
        raise DepthnerfError(f"{path}: depth map holds NaN or inf ({int(bad.sum())} of {depth.size} pixels)")
    if (depth < 0).any():
        raise DepthnerfError(f"{path}: depth map holds negative values (min {float(depth.min()):g})")
    if not allow_empty and not depth.any():
        raise DepthnerfError(f"{path}: depth map is all zero (no surface)")
    return depth.astype(np.float32)


def check_empty_mask(path: Path, mask: np.ndarray, image_path: Path, image: np.ndarray) -> None:
    """An all-background mask is valid only for a view whose image shows nothing; where the image has a white
    background with something on it (pixelNeRF's rule finds object pixels, and not every pixel), the mask is broken
    (a 16-bit colour mask of 8-bit values reads as all zero, say): an error naming ``path``. On an image without
    white pixels the rule says nothing, and the mask is believed."""
    if mask.any():
        return
    shown = mask_from_white(image)
    if shown.any() and not shown.all():
        raise DepthnerfError(f"{path}: mask is all background but {image_path.parent.name}/{image_path.name} shows "
                             "an object on a white background; fix the mask or remove the object's mask/ folder")


def check_empty_depth(path: Path, depth: np.ndarray, image_path: Path, image: np.ndarray) -> None:
    """An all-zero depth map is valid only for a view whose image shows nothing (all white, pixelNeRF's rule);
    otherwise it is a broken render: an error naming ``path``."""
    if not depth.any() and mask_from_white(image).any():
        raise DepthnerfError(f"{path}: depth map is all zero (no surface) but {image_path.parent.name}/"
                             f"{image_path.name} shows an object")


def read_depth_scale(path: Path) -> float:
    """The number in a ``depth_scale.txt``: world units per 16-bit PNG depth unit (finite, > 0)."""
    path = Path(path)
    try:
        text = path.read_text(encoding="utf-8-sig").split()
        scale = float(text[0]) if len(text) == 1 else float("nan")
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read the depth scale ({err.strerror or err})") from None
    except ValueError:
        scale = float("nan")
    if not np.isfinite(scale) or scale <= 0:
        raise DepthnerfError(f"{path}: expected one positive number (world units per 16-bit PNG depth unit)")
    return scale


def write_depth(path: Path, depth: np.ndarray) -> None:
    """Write a float32 z-depth map losslessly (compressed ``.npz``, key ``depth``), byte-for-byte deterministic.

    Same container as ``np.savez_compressed`` (readable by ``np.load``), but with a fixed zip timestamp so the
    same map always gives the same bytes.
    """
    buf = io.BytesIO()
    np.lib.format.write_array(buf, np.ascontiguousarray(depth, dtype=np.float32), allow_pickle=False)
    info = zipfile.ZipInfo("depth.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr(info, buf.getvalue())


def mask_not_png(path: Path, image_format: str) -> str:
    """The error line for a mask file that is not a PNG (a JPEG's compression noise makes background pixels
    non-zero, i.e. object)."""
    return (f"{path}: mask is a {image_format} file, not a PNG (masks are read from lossless PNG only: a lossy "
            "format turns background pixels into object); re-save it as PNG")


def read_mask(path: Path) -> np.ndarray:
    """Read a mask PNG of any bit depth and mode as a boolean ``H x W`` array.

    Any other format (a JPEG named ``.png``) is an error. A pixel is object when its colour is non-zero (any
    channel; palette images by their palette colour); where the image has alpha, a fully transparent pixel is
    background. (Pillow reads 16-bit *colour* PNGs at 8-bit precision, so there a value below 256 reads as 0;
    16-bit grey keeps full precision.)
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            if im.format != "PNG":
                raise DepthnerfError(mask_not_png(path, str(im.format)))
            im.load()
            if im.mode in ("P", "PA", "CMYK", "YCbCr", "HSV"):
                im = im.convert("RGBA")
            bands = im.getbands()
            arr = np.asarray(im)
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: mask file is missing") from None
    except UnidentifiedImageError:
        raise DepthnerfError(f"{path}: unreadable mask ({NOT_AN_IMAGE})") from None
    except (OSError, ValueError, Image.DecompressionBombError) as err:
        raise DepthnerfError(f"{path}: unreadable mask ({err})") from None
    if arr.ndim == 2:
        return arr != 0
    alpha = bands[-1] == "A"
    mask = (arr[..., :-1] if alpha else arr).any(axis=-1)
    return mask & (arr[..., -1] != 0) if alpha else mask


def write_mask(path: Path, mask: np.ndarray) -> None:
    """Write a boolean mask as an 8-bit PNG (255 = object)."""
    Image.fromarray(np.asarray(mask, dtype=np.uint8) * 255, mode="L").save(path)


def mask_from_white(img: np.ndarray) -> np.ndarray:
    """pixelNeRF's mask for SRN images without one: pixels whose 8-bit RGB is not white in **all** channels.

    (pixelNeRF: ``(img != 255).all(axis=-1)`` on the uint8 image.)
    """
    return (np.round(img * 255.0) != 255).all(axis=-1)
