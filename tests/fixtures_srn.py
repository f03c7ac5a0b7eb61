"""Tiny real-format SRN datasets for tests (import as ``from fixtures_srn import make_srn_fixture``).

Each object is a sphere at the world origin whose albedo is a function of the surface normal (so views differ and
are multi-view consistent), ray-cast exactly at pixel centres (no anti-aliasing): object pixels are never pure
white, background pixels are exactly white, so pixelNeRF's non-white mask, the written mask and ``depth > 0``
all agree. Cameras look at the origin from the category's camera radius (``cameras.look_at``), with intrinsics
like the SRN release (focal ``131.25 * size / 128``, principal point ``size / 2``).

:func:`to_srn_style` rewrites an object folder the way the public SRN files look (RGBA and 16-bit PNGs, poses as
4 lines of 4 numbers, ``131.25 64. 64. 0.``-style intrinsics) so tests can check both spellings load the same.
"""

from __future__ import annotations

import hashlib
import math
import struct
import zlib
from pathlib import Path

import numpy as np
import torch
from PIL import Image

from depthnerf.data import srn_format
from depthnerf.data.cameras import Intrinsics, look_at, pixel_directions

CAMERA_RADIUS = {"cars": 1.3, "chairs": 2.0}
"""Camera distance per category (SRN values); other categories use 1.5."""


def object_id(category: str, split: str, k: int) -> str:
    """A deterministic 32-hex-digit object id, like ShapeNet's."""
    return hashlib.md5(f"{category}/{split}/{k}".encode()).hexdigest()


def sphere_radius(camera_radius: float) -> float:
    """Radius of the fixture sphere for cameras at ``camera_radius`` (fills about half the image)."""
    return 0.23 * camera_radius


def fixture_intrinsics(size: int) -> Intrinsics:
    """SRN-like intrinsics of a ``size x size`` fixture image."""
    return Intrinsics(focal=131.25 * size / 128, cx=size / 2, cy=size / 2, height=size, width=size)


def fixture_pose(view: int, views: int, camera_radius: float, phase: float = 0.0) -> np.ndarray:
    """Camera-to-world pose of view ``view`` of ``views``: around the object, elevations 15-45 degrees."""
    azimuth = 2 * math.pi * view / views + phase
    elevation = math.radians(15 + 15 * (view % 3))
    eye = camera_radius * torch.tensor([math.cos(elevation) * math.cos(azimuth),
                                        math.cos(elevation) * math.sin(azimuth), math.sin(elevation)])
    return look_at(eye).numpy()


def render_sphere(c2w: np.ndarray, intr: Intrinsics, radius: float, tint: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Ray-cast a sphere at the origin: uint8 ``H x W x 3`` RGB on white, bool mask, float32 z-depth (0 = miss)."""
    dirs_cam = pixel_directions(intr).numpy().astype(np.float64)  # unit, camera frame
    rot, origin = c2w[:3, :3].astype(np.float64), c2w[:3, 3].astype(np.float64)
    dirs = dirs_cam @ rot.T
    b = dirs @ origin  # |o + t d|^2 = r^2  ->  t^2 + 2 b t + (|o|^2 - r^2) = 0
    disc = b**2 - (origin @ origin - radius**2)
    hit = disc > 0
    t = np.where(hit, -b - np.sqrt(np.maximum(disc, 0.0)), 0.0)
    normal = (origin + t[..., None] * dirs) / radius
    albedo = np.clip(0.45 + 0.4 * normal, 0.05, 0.9) * tint
    rgb = np.where(hit[..., None], albedo, 1.0)
    depth = np.where(hit, t * dirs_cam[..., 2], 0.0).astype(np.float32)
    return np.round(rgb * 255).astype(np.uint8), hit, depth


def make_srn_fixture(root: Path, category: str = "cars", splits: dict[str, int] | None = None, views: int = 3,
                     size: int = 16, with_depth: bool = False, with_mask: bool = False, with_mesh: bool = False,
                     chairs_nesting: bool = True) -> Path:
    """Write ``<root>/<category>_<split>/<object_id>/`` folders with :mod:`srn_format` writers; returns ``root``.

    ``splits`` maps split name to object count (default ``{"train": 2, "test": 1}``). With ``chairs_nesting``,
    ``chairs`` train objects go to ``chairs_train/chairs_2.0_train/`` as in the public release.
    """
    splits = {"train": 2, "test": 1} if splits is None else splits
    root = Path(root)
    cam_radius = CAMERA_RADIUS.get(category, 1.5)
    radius = sphere_radius(cam_radius)
    intr = fixture_intrinsics(size)
    for split, count in splits.items():
        split_path = root / f"{category}_{split}"
        if category == "chairs" and split == "train" and chairs_nesting:
            split_path = split_path / "chairs_2.0_train"
        for k in range(count):
            obj = split_path / object_id(category, split, k)
            for sub in ["rgb", "pose"] + ["depth"] * with_depth + ["mask"] * with_mask:
                (obj / sub).mkdir(parents=True, exist_ok=True)
            srn_format.write_intrinsics(obj / "intrinsics.txt", intr)
            rng = np.random.default_rng(k)
            tint = rng.uniform(0.5, 1.0, size=3)
            for v in range(views):
                c2w = fixture_pose(v, views, cam_radius, phase=0.7 * k)
                rgb, mask, depth = render_sphere(c2w, intr, radius, tint)
                name = f"{v:06d}"
                srn_format.write_rgb(obj / "rgb" / f"{name}.png", rgb)
                srn_format.write_pose(obj / "pose" / f"{name}.txt", c2w)
                if with_depth:
                    srn_format.write_depth(obj / "depth" / f"{name}.npz", depth)
                if with_mask:
                    srn_format.write_mask(obj / "mask" / f"{name}.png", mask)
            if with_mesh:
                import trimesh

                trimesh.creation.icosphere(subdivisions=2, radius=radius).export(obj / "mesh.ply")
    return root


def _chunk(kind: bytes, data: bytes) -> bytes:
    """One PNG chunk: length, type, data, CRC."""
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data) & 0xFFFFFFFF)


def write_png16(path: Path, arr: np.ndarray, key: tuple[int, int, int] | None = None) -> None:
    """Write a 16-bit RGB or RGBA PNG (``H x W x 3|4`` uint16); Pillow cannot write these itself. ``key``: an RGB
    file's colour-key transparency (a ``tRNS`` chunk: pixels of exactly that colour are transparent)."""
    height, width, channels = arr.shape
    color_type = {3: 2, 4: 6}[channels]
    raw = b"".join(b"\x00" + np.ascontiguousarray(row, dtype=">u2").tobytes() for row in arr)

    header = struct.pack(">IIBBBBB", width, height, 16, color_type, 0, 0, 0)
    trns = b"" if key is None else _chunk(b"tRNS", struct.pack(">HHH", *key))
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + trns
                           + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))


def write_grey_png(path: Path, rows: np.ndarray, depth: int, key: int | None = None) -> None:
    """Write a grey PNG of bit ``depth`` from its packed rows (``H x row bytes`` uint8, as the file stores them);
    ``key``: its colour-key transparency (a ``tRNS`` chunk), a stored value."""
    height = rows.shape[0]
    width = rows.shape[1] * 8 // depth
    raw = b"".join(b"\x00" + bytes(row) for row in np.asarray(rows, dtype=np.uint8))
    header = struct.pack(">IIBBBBB", width, height, depth, 0, 0, 0, 0)
    trns = b"" if key is None else _chunk(b"tRNS", struct.pack(">H", key))
    Path(path).write_bytes(b"\x89PNG\r\n\x1a\n" + _chunk(b"IHDR", header) + trns
                           + _chunk(b"IDAT", zlib.compress(raw)) + _chunk(b"IEND", b""))


def _srn_number(x: float) -> str:
    """A float the way the SRN files spell it: ``64.``, ``131.25``, ``0.``."""
    text = repr(float(x))
    return text[:-1] if text.endswith(".0") else text


STYLES = ("rgba8", "rgb16", "rgba16")
"""PNG flavours :func:`to_srn_style` cycles through, view by view."""


def to_srn_style(src: Path, dst: Path) -> Path:
    """Copy object folder ``src`` to ``dst`` spelled like the public SRN files; the loaded tensors are unchanged.

    Views cycle through :data:`STYLES`: white pixels become transparent (alpha 0, RGB black) and everything else
    opaque, so compositing on white gives back the same values; 16-bit values are ``v8 * 257``. Depth, mask and
    mesh are copied as they are.
    """
    src, dst = Path(src), Path(dst)
    for sub in ("rgb", "pose"):
        (dst / sub).mkdir(parents=True, exist_ok=True)
    intr = srn_format.read_intrinsics(src / "intrinsics.txt")
    (dst / "intrinsics.txt").write_text(
        f"{_srn_number(intr.focal)} {_srn_number(intr.cx)} {_srn_number(intr.cy)} 0.\n0. 0. 0.\n1.\n"
        f"{intr.height} {intr.width}\n")
    names = sorted(p.stem for p in (src / "rgb").glob("*.png"))
    for v, name in enumerate(names):
        pose = srn_format.read_pose(src / "pose" / f"{name}.txt")
        (dst / "pose" / f"{name}.txt").write_text(
            "\n".join(" ".join(repr(float(x)) for x in row) for row in pose) + "\n")
        rgb8 = np.asarray(Image.open(src / "rgb" / f"{name}.png").convert("RGB"))
        white = (rgb8 == 255).all(axis=-1)
        alpha = np.where(white, 0, 255).astype(np.uint8)[..., None]
        rgba8 = np.concatenate([np.where(white[..., None], 0, rgb8).astype(np.uint8), alpha], axis=-1)
        style = STYLES[v % len(STYLES)]
        out = dst / "rgb" / f"{name}.png"
        if style == "rgba8":
            Image.fromarray(rgba8, mode="RGBA").save(out)
        elif style == "rgb16":
            write_png16(out, rgb8.astype(np.uint16) * 257)
        else:
            write_png16(out, rgba8.astype(np.uint16) * 257)
    for sub in ("depth", "mask"):
        if (src / sub).is_dir():
            (dst / sub).mkdir(exist_ok=True)
            for f in (src / sub).iterdir():
                (dst / sub / f.name).write_bytes(f.read_bytes())
    if (src / "mesh.ply").is_file():
        (dst / "mesh.ply").write_bytes((src / "mesh.ply").read_bytes())
    return dst


def first_object(root: Path, category: str = "cars", split: str = "train") -> Path:
    """The first (sorted) object folder of a fixture split (not for nested chairs train)."""
    return sorted(p for p in (Path(root) / f"{category}_{split}").iterdir() if p.is_dir())[0]


def _break_pose(values: list[float] | None = None, scale: float = 1.0):
    def mutate(root: Path) -> tuple[str, Path, str]:
        path = first_object(root) / "pose" / "000001.txt"
        if values is not None:
            path.write_text(" ".join(str(v) for v in values) + "\n")
            return "train", path, "NaN or inf" if len(values) == 16 else f"{len(values)} numbers"
        pose = srn_format.read_pose(path)
        pose[:3, :3] *= scale
        srn_format.write_pose(path, pose)
        return "train", path, "not a rigid transform"
    return mutate


def _rgb_bytes(transform):
    def mutate(root: Path) -> tuple[str, Path, str]:
        path = first_object(root) / "rgb" / "000001.png"
        path.write_bytes(transform(path.read_bytes()))
        return "train", path, "unreadable image"
    return mutate


def _missing_png(root: Path) -> tuple[str, Path, str]:
    obj = first_object(root)
    (obj / "rgb" / "000001.png").unlink()
    return "train", obj, "pose/000001.txt has no rgb/000001.png"


def _extra_pose(root: Path) -> tuple[str, Path, str]:
    obj = first_object(root)
    (obj / "pose" / "000003.txt").write_bytes((obj / "pose" / "000002.txt").read_bytes())
    return "train", obj, "3 images in rgb/ but 4 files in pose/"


def _unpaired_stems(root: Path) -> tuple[str, Path, str]:
    obj = first_object(root)
    (obj / "pose" / "000001.txt").rename(obj / "pose" / "000009.txt")
    return "train", obj, "rgb/000001.png has no pose/000001.txt"


def _missing_intrinsics(root: Path) -> tuple[str, Path, str]:
    path = first_object(root) / "intrinsics.txt"
    path.unlink()
    return "train", path, "cannot read intrinsics"


def _malformed_intrinsics(root: Path) -> tuple[str, Path, str]:
    path = first_object(root) / "intrinsics.txt"
    path.write_text("131.25 sixty-four 64. 0.\n0. 0. 0.\n1.\n128 128\n")
    return "train", path, "malformed intrinsics"


def _empty_split(root: Path) -> tuple[str, Path, str]:
    import shutil

    split = Path(root) / "cars_test"
    for obj in split.iterdir():
        shutil.rmtree(obj)
    return "test", split, "empty split"


def _image_size(root: Path) -> tuple[str, Path, str]:
    path = first_object(root) / "rgb" / "000001.png"
    srn_format.write_rgb(path, np.full((20, 20, 3), 0.5, dtype=np.float32))
    return "train", path, "is 20x20 but"


def _stray_file(root: Path) -> tuple[str, Path, str]:
    path = first_object(root) / "rgb" / "notes.txt"
    path.write_text("not an image\n")
    return "train", path, "unexpected entry"



def _opengl_poses(root: Path) -> tuple[str, Path, str]:
    """Every pose of the first object in OpenGL camera axes (y up, looking down -z): each camera looks away."""
    obj = first_object(root)
    for path in sorted((obj / "pose").iterdir()):
        srn_format.write_pose(path, srn_format.read_pose(path) @ np.diag([1.0, -1.0, -1.0, 1.0]))
    return "train", obj / "pose" / "000000.txt", "every camera of this object looks away from the world origin"

BAD_INPUT_CASES = {
    "missing_png": _missing_png,
    "unreadable_png": _rgb_bytes(lambda data: b"this is not a PNG file"),
    "truncated_png": _rgb_bytes(lambda data: data[: len(data) // 2]),
    "pose_count_mismatch": _extra_pose,
    "stems_do_not_pair": _unpaired_stems,
    "pose_not_rigid": _break_pose(scale=2.0),
    "pose_nan": _break_pose(values=[1, 0, 0, 0, 0, 1, 0, 0, 0, 0, 1, float("nan"), 0, 0, 0, 1]),
    "pose_inf": _break_pose(values=[1, 0, 0, float("inf"), 0, 1, 0, 0, 0, 0, 1, 1.3, 0, 0, 0, 1]),
    "pose_15_numbers": _break_pose(values=[1.0] * 15),
    "missing_intrinsics": _missing_intrinsics,
    "malformed_intrinsics": _malformed_intrinsics,
    "empty_split": _empty_split,
    "image_size_vs_intrinsics": _image_size,
    "stray_file_in_rgb": _stray_file,
    "poses_in_opengl_axes": _opengl_poses,
}
"""Ways to break the *required* files of a ``make_srn_fixture(..., with_depth=True, with_mask=True)`` folder. Each
mutates the folder and returns ``(split, path, text)``: indexing that split must fail with a one-line message
containing ``path`` and ``text``, strict or not."""
