"""Writing a :class:`~depthnerf.reconstruct.reconstructor.Reconstruction` to a folder, with a JSON manifest.

Layout of ``OUT`` (every path in ``manifest.json`` is relative to ``OUT``)::

    input.png, input_mask.png     the prepared input view (on white, at the training resolution) and its mask
    cutout.png                    the photo as read with the background model's alpha (RGBA; only when a
                                  background model removed the background)
    depth_prior.png               the prior the encoder saw (depth-aware models): normalised disparity as 8-bit
                                  grey, foreground [-4, 4] -> [64, 255] (brighter = nearer), background 0
    views/view_NNN.png            the N orbit views (view 000 = the input camera)
    depths/depth_NNN.png          rendered depth as 8-bit grey: 255 at z-near ... 0 at z-far (ray distance), 0
                                  where opacity < 0.5; exact float ray distances and opacities in depths.npz
    depths.npz                    ``depth`` [N, H, W] (ray distance), ``opacity`` [N, H, W], ``poses`` [N, 4, 4]
                                  (camera-to-world, OpenCV axes), ``intrinsics`` (f, cx, cy, H, W)
    turntable.gif                 the orbit views as an endless GIF (``TURNTABLE_FPS``)
    turntable.mp4                 the same as H.264 when ``imageio-ffmpeg`` is installed (else the manifest says so)
    mesh.ply                      vertex-coloured world-frame mesh, +z up (may be empty: ``mesh.empty`` in the
                                  manifest; not written with ``mesh_resolution`` 0: ``mesh.made`` false)
    mesh.glb                      the same mesh in glTF's frame (+y up, :data:`GLTF_FROM_WORLD`), so any glTF
                                  viewer shows it upright
    points.ply                    coloured world-frame point cloud
    manifest.json                 all of the above + checkpoint, settings, notes and timings

These names (:data:`OUTPUT_NAMES`, :data:`NUMBERED_OUTPUTS`) are the files a reconstruction owns in ``OUT``:
writing one removes an earlier reconstruction's (so no stale frame of a longer orbit survives) and leaves every
other file alone. Every file is first written into a hidden staging folder in ``OUT`` (:data:`STAGING_PREFIX`);
only when all of them are written are the earlier outputs removed and the new ones renamed into place,
``manifest.json`` last. So a failure while writing (a full disk, a bad mesh export, Ctrl-C) leaves an earlier
reconstruction as it was and removes the staging folder; ``manifest.json`` present means the folder is complete.
(A process killed outright may leave its staging folder behind; it is hidden, and nothing reads it.) :func:`check_output_dir` is what ``depthnerf reconstruct`` runs before any work: the
folder must be creatable and writable, may hold an earlier reconstruction only with ``--overwrite``, and
never holds the photo or mask under one of these names (writing would replace it).
"""

from __future__ import annotations

import importlib.util
import json
import os
import re
import shutil
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import imageio.v3 as iio
import numpy as np
import trimesh
from PIL import Image

from depthnerf.depth.normalize import BACKGROUND_VALUE, FOREGROUND_CLAMP
from depthnerf.errors import DepthnerfError
from depthnerf.files import folder_problem, nearest_existing, write_text_atomic
from depthnerf.reconstruct.result import Reconstruction

TURNTABLE_FPS = 12
"""Frames per second of the turntable GIF / MP4."""
GLTF_FROM_WORLD = np.array([[1.0, 0, 0, 0], [0, 0, 1, 0], [0, -1, 0, 0], [0, 0, 0, 1]])
"""World (+z up) to glTF (+y up): ``(x, y, z) -> (x, z, -y)``, a rotation of -90 degrees about +x."""
OUTPUT_NAMES = ("manifest.json", "input.png", "input_mask.png", "cutout.png", "depth_prior.png", "depths.npz",
                "turntable.gif", "turntable.mp4", "mesh.ply", "mesh.glb", "points.ply")
"""Files a reconstruction writes at the top of its folder."""
NUMBERED_OUTPUTS = {"views": re.compile(r"view_\d{3,}\.png"), "depths": re.compile(r"depth_\d{3,}\.png")}
"""Sub-folder -> the per-view files a reconstruction writes there."""
STAGING_PREFIX = ".depthnerf-staging-"
"""Name prefix of the hidden folder in ``OUT`` that a reconstruction is written into before it is moved into place."""


def earlier_outputs(out: Path) -> list[Path]:
    """The files of an earlier reconstruction in ``out``: :data:`OUTPUT_NAMES` and :data:`NUMBERED_OUTPUTS`."""
    found = [out / name for name in OUTPUT_NAMES if (out / name).is_file()]
    for sub, pattern in NUMBERED_OUTPUTS.items():
        if (out / sub).is_dir():
            found += sorted(p for p in (out / sub).iterdir() if p.is_file() and pattern.fullmatch(p.name))
    return found


def owned_output(out: Path, path: Path) -> bool:
    """Whether ``path`` is a file a reconstruction in ``out`` writes, and so replaces (:data:`OUTPUT_NAMES`,
    :data:`NUMBERED_OUTPUTS`)."""
    out, path = Path(out).resolve(), Path(path).resolve()
    if path.parent == out:
        return path.name in OUTPUT_NAMES
    pattern = NUMBERED_OUTPUTS.get(path.parent.name)
    return path.parent.parent == out and pattern is not None and pattern.fullmatch(path.name) is not None


def check_output_dir(out: Path, overwrite: bool = False, inputs: Sequence[Path] = ()) -> None:
    """Fail at once, before any work, when ``out`` cannot take a reconstruction: a file, not creatable or not
    writable, holding an earlier reconstruction (unless ``overwrite``), or where the reconstruction would replace
    one of its ``inputs`` (the photo, the mask). Creates nothing."""
    out = Path(out)
    if (problem := folder_problem(out, "--out")) is not None:
        raise DepthnerfError(problem)
    for path in inputs:
        if owned_output(out, path):
            raise DepthnerfError(f"{path}: a reconstruction in {out} writes a file of this name; choose another "
                                 "--out, or move the file")
    existing = nearest_existing(out)
    try:
        handle, probe = tempfile.mkstemp(dir=existing, prefix=".depthnerf-write-check-")
        os.close(handle)
        os.unlink(probe)
    except OSError as err:
        raise DepthnerfError(f"{out}: cannot write the output folder{'' if existing == out else f' in {existing}'} "
                             f"({err.strerror or err})") from None
    earlier = earlier_outputs(out) if existing == out else []
    if earlier and not overwrite:
        raise DepthnerfError(f"{out}: holds an earlier reconstruction ({len(earlier)} files: "
                             f"{', '.join(p.relative_to(out).as_posix() for p in earlier[:3])}"
                             f"{', ...' if len(earlier) > 3 else ''}); pass --overwrite to replace it, or choose "
                             "another --out")


def clear_outputs(out: Path) -> None:
    """Remove an earlier reconstruction's files from ``out`` (and its sub-folders when that empties them)."""
    for path in earlier_outputs(out):
        path.unlink()
    for sub in NUMBERED_OUTPUTS:
        if (out / sub).is_dir() and not any((out / sub).iterdir()):
            (out / sub).rmdir()


def to_u8(x: np.ndarray) -> np.ndarray:
    """Float image in [0, 1] (clipped) as 8-bit, rounded."""
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def even_sized(frames: np.ndarray) -> np.ndarray:
    """``frames`` ``[T, H, W, 3]`` with an odd height or width grown by one edge-copied row or column: H.264 in
    yuv420p (the MP4 turntable) needs both even, and ffmpeg writes an empty file otherwise."""
    pad_h, pad_w = frames.shape[1] % 2, frames.shape[2] % 2
    if not (pad_h or pad_w):
        return frames
    return np.pad(frames, ((0, 0), (0, pad_h), (0, pad_w), (0, 0)), mode="edge")


def prior_image(prior: np.ndarray) -> np.ndarray:
    """8-bit grey of a normalised prior: foreground [-4, 4] -> [64, 255], background (-5) -> 0."""
    fg = prior > BACKGROUND_VALUE + 0.5
    grey = 64.0 + (np.clip(prior, -FOREGROUND_CLAMP, FOREGROUND_CLAMP) + FOREGROUND_CLAMP) / (2 * FOREGROUND_CLAMP) * 191
    return np.where(fg, np.round(grey), 0).astype(np.uint8)


def depth_image(depth: np.ndarray, opacity: np.ndarray, near: float, far: float) -> np.ndarray:
    """8-bit grey of a rendered depth map: 255 at ``near`` ... 0 at ``far``, 0 where opacity < 0.5."""
    grey = to_u8((far - depth) / (far - near))
    return np.where(opacity >= 0.5, grey, 0).astype(np.uint8)


def save_reconstruction(result: Reconstruction, out_dir: Path, provenance: dict[str, Any]) -> dict[str, Any]:
    """Write every output of ``result`` into ``out_dir`` (layout in the module docstring) through a staging folder,
    so that an earlier reconstruction there is replaced only once the new one is complete; returns the manifest."""
    t0 = time.perf_counter()
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
        stage = Path(tempfile.mkdtemp(dir=out, prefix=STAGING_PREFIX))
    except OSError as err:
        raise DepthnerfError(f"{out}: cannot create the output folder ({err.strerror or err})") from None
    try:
        try:
            manifest = write_outputs(result, stage, provenance, t0)
        except OSError as err:
            kept = "; the earlier reconstruction there is left as it was" if earlier_outputs(out) else ""
            raise DepthnerfError(f"{out}: cannot write the reconstruction ({err.strerror or err}){kept}") from None
        try:
            move_into_place(stage, out)
        except OSError as err:
            raise DepthnerfError(f"{out}: cannot move the reconstruction into place ({err.strerror or err}); the "
                                 "folder has no manifest.json, so it is incomplete: run again with --overwrite") from None
    finally:
        shutil.rmtree(stage, ignore_errors=True)
    return manifest


def move_into_place(stage: Path, out: Path) -> None:
    """Replace the reconstruction in ``out`` by the complete one in ``stage``: the earlier ``manifest.json`` goes
    first and the new one comes last, so a manifest is only ever beside the files it lists."""
    (out / "manifest.json").unlink(missing_ok=True)
    clear_outputs(out)
    staged = sorted(p.relative_to(stage) for p in stage.rglob("*") if p.is_file())
    for rel in sorted(staged, key=lambda r: r.as_posix() == "manifest.json"):
        (out / rel).parent.mkdir(exist_ok=True)
        os.replace(stage / rel, out / rel)


def write_outputs(result: Reconstruction, out: Path, provenance: dict[str, Any], t0: float) -> dict[str, Any]:
    """Write every output of ``result`` into the empty folder ``out``; returns the manifest (``save_s`` counted from
    ``t0``)."""
    (out / "views").mkdir()
    (out / "depths").mkdir()
    near, far = result.settings["z_range"]
    files: dict[str, Any] = {}
    Image.fromarray(to_u8(result.input.image)).save(out / "input.png")
    Image.fromarray(result.input.mask.astype(np.uint8) * 255).save(out / "input_mask.png")
    files["input"], files["input_mask"] = "input.png", "input_mask.png"
    files["cutout"] = None
    if result.input.cutout is not None:
        Image.fromarray(to_u8(result.input.cutout), "RGBA").save(out / "cutout.png")
        files["cutout"] = "cutout.png"
    if result.prior_normalized is not None:
        Image.fromarray(prior_image(result.prior_normalized)).save(out / "depth_prior.png")
        files["depth_prior"] = "depth_prior.png"
    else:
        files["depth_prior"] = None
    frames = to_u8(result.views)
    files["views"], files["depths"] = [], []
    for k, frame in enumerate(frames):
        Image.fromarray(frame).save(out / "views" / f"view_{k:03d}.png")
        Image.fromarray(depth_image(result.depths[k], result.opacity[k], near, far)).save(
            out / "depths" / f"depth_{k:03d}.png")
        files["views"].append(f"views/view_{k:03d}.png")
        files["depths"].append(f"depths/depth_{k:03d}.png")
    intr = result.intrinsics
    np.savez_compressed(out / "depths.npz", depth=result.depths.astype(np.float32),
                        opacity=result.opacity.astype(np.float32), poses=result.poses.astype(np.float32),
                        intrinsics=np.array([intr.focal, intr.cx, intr.cy, intr.height, intr.width], np.float64))
    files["depths_npz"] = "depths.npz"
    iio.imwrite(out / "turntable.gif", frames, duration=round(1000 / TURNTABLE_FPS), loop=0)
    files["turntable_gif"] = "turntable.gif"
    if importlib.util.find_spec("imageio_ffmpeg") is not None:
        iio.imwrite(out / "turntable.mp4", even_sized(frames), fps=TURNTABLE_FPS, plugin="FFMPEG",
                    macro_block_size=1)
        if (out / "turntable.mp4").stat().st_size > 0:
            files["turntable_mp4"], mp4_status = "turntable.mp4", "ok"
        else:  # ffmpeg reports on stderr and leaves an empty file
            (out / "turntable.mp4").unlink()
            files["turntable_mp4"], mp4_status = None, "not written: ffmpeg wrote an empty file"
    else:
        files["turntable_mp4"] = None
        mp4_status = "not written: imageio-ffmpeg is not installed (pip install 'depthnerf[video]')"
    made = result.settings.get("mesh_resolution", 1) != 0
    if made:
        result.mesh.export(out / "mesh.ply")
        result.mesh.copy().apply_transform(GLTF_FROM_WORLD).export(out / "mesh.glb")
    files["mesh_ply"], files["mesh_glb"] = ("mesh.ply", "mesh.glb") if made else (None, None)
    rgba = np.concatenate([to_u8(result.point_colors), np.full((len(result.points), 1), 255, np.uint8)], axis=1)
    if len(result.points):
        trimesh.PointCloud(result.points, colors=rgba).export(out / "points.ply")
    else:  # trimesh cannot write an empty cloud: the same header, no vertices
        write_text_atomic(out / "points.ply", "ply\nformat ascii 1.0\nelement vertex 0\nproperty float x\n"
                          "property float y\nproperty float z\nproperty uchar red\nproperty uchar green\n"
                          "property uchar blue\nproperty uchar alpha\nend_header\n")
    files["point_cloud"] = "points.ply"
    empty = len(result.mesh.faces) == 0
    mesh_note = ("not made (mesh resolution 0)" if not made else
                 "the density never reached the marching-cubes level inside the input frustum" if empty else
                 f"world frame, vertex colours by the {result.settings.get('mesh_color_rule')} rule (settings: "
                 "mesh_colors)")
    manifest = {
        **provenance,
        "files": files,
        "turntable_mp4_status": mp4_status,
        "input": {"source_size": list(result.input.source_size), "notes": result.input.notes,
                  "object_pixels": int(result.input.mask.sum())},
        "settings": result.settings,
        "intrinsics": {"focal": intr.focal, "cx": intr.cx, "cy": intr.cy, "height": intr.height,
                       "width": intr.width},
        "mesh": {"made": made, "vertices": int(len(result.mesh.vertices)), "faces": int(len(result.mesh.faces)),
                 "empty": empty, "note": mesh_note},
        "point_cloud": {"points": int(len(result.points)),
                        "rule": f"rendered depth of every view where opacity > {result.settings['point_opacity']}"},
        "conventions": "world +z up, object at the origin, poses camera-to-world with OpenCV axes; depths are "
                       "ray distances along unit directions",
        "timings": {**result.timings, "save_s": time.perf_counter() - t0},
    }
    write_text_atomic(out / "manifest.json", json.dumps(manifest, indent=1) + "\n")
    return manifest
