"""The view store: every view of a split decoded once, at one resolution, into memory-mappable arrays.

Training draws its target rays from all views of an object but the source (pixelNeRF's protocol), so each item
built from the PNG files decodes every view of its object: about 25 ms per object with 50 views at 128 px on one
CPU core (``benchmarks/bench_loader.py``), several times the compiled GPU step for a 4-object batch. The store decodes
each object once (:func:`load_object`, the same function, so the same checks and values) and a training item then
reads only its source view and the pixels its rays hit (:class:`StoredObject`). Items built from it are equal, to
the bit, to items built from the PNG files.

Layout (``root`` is the folder a user names with ``--data.view_store``)::

    <root>/manifest.json                                   {"format": 1, "resolution": R, "pixel_center": c}
    <root>/<category>_<split>/<object_id>/meta.json        fingerprint, image dtype, intrinsics
    <root>/<category>_<split>/<object_id>/images.npy       [V H W 3] uint8 (value / 255), or float32
    <root>/<category>_<split>/<object_id>/masks.npy        [V H W] bool
    <root>/<category>_<split>/<object_id>/poses.npy        [V 4 4] camera-to-world, as loaded
    <root>/<category>_<split>/<object_id>/bboxes.npy       [V 4] int64, x0 y0 x1 y1 inclusive

Images are stored as uint8 when every decoded value is exactly ``k / 255`` in float32 (8-bit PNGs at their own
size), else as float32 (16-bit PNGs, alpha composited on white, resized views), so reading them back is exact
either way. An object folder is written under a temporary name and renamed, so a crash leaves no partial object.

Stale detection: an object's fingerprint is the SHA-256 of its view names and the size and modification time of its
``intrinsics.txt`` and of each RGB, pose and mask file. A changed dataset rebuilds the changed objects (and says how
many); a store made at another resolution or pixel centre is refused in one line.
"""

from __future__ import annotations

import hashlib
import json
import os
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.records import ObjectRecord
from depthnerf.data.srn import ObjectViews, load_object
from depthnerf.errors import DepthnerfError
from depthnerf.files import write_json_atomic

STORE_FORMAT = 1
"""Version of the layout above; a store of another version is refused."""


@dataclass(frozen=True)
class StoredObject:
    """Views of one object as arrays (memory-mapped from a store, or in memory from :meth:`from_views`).

    Indices are positions in ``images``' first axis: view indices of the record for a stored object, positions
    in the loaded list for one made by :meth:`from_views`.
    """

    images: np.ndarray
    """``[V H W 3]`` uint8 (the value is ``k / 255``) or float32, RGB in [0, 1] composited on white."""
    masks: np.ndarray
    """``[V H W]`` bool, object pixels."""
    poses: Float[Tensor, "V 4 4"]
    """Camera-to-world, OpenCV camera axes."""
    bboxes: Int[Tensor, "V 4"]
    """``[x0, y0, x1, y1]`` of each mask, inclusive (:func:`depthnerf.data.srn.mask_bboxes`)."""
    intrinsics: Intrinsics
    """Intrinsics of the stored images."""

    @classmethod
    def from_views(cls, obj: ObjectViews) -> StoredObject:
        """The loaded views of ``obj`` in the same form (float32)."""
        return cls(images=obj.images.permute(0, 2, 3, 1).numpy(), masks=obj.masks.numpy(), poses=obj.poses,
                   bboxes=obj.bboxes, intrinsics=obj.intrinsics)

    def _float(self, values: np.ndarray) -> Tensor:
        if values.dtype == np.uint8:
            return torch.from_numpy(values.astype(np.float32) / 255.0)  # read_rgb's own arithmetic
        return torch.from_numpy(np.array(values, dtype=np.float32))

    def views(self, indices: Sequence[int]) -> tuple[Float[Tensor, "V 3 H W"], Bool[Tensor, "V H W"]]:
        """Whole views: images and masks."""
        idx = np.asarray(indices, dtype=np.int64)
        return (self._float(self.images[idx]).permute(0, 3, 1, 2).contiguous(),
                torch.from_numpy(np.array(self.masks[idx])))

    def pixels(self, views: Int[Tensor, " R"], rows: Int[Tensor, " R"], cols: Int[Tensor, " R"]
               ) -> tuple[Float[Tensor, "R 3"], Bool[Tensor, " R"]]:
        """Colour and mask of single pixels (view, row, col): reads only those pixels from a store."""
        v, r, c = views.numpy(), rows.numpy(), cols.numpy()
        return self._float(self.images[v, r, c]), torch.from_numpy(np.array(self.masks[v, r, c]))


def object_fingerprint(record: ObjectRecord) -> str:
    """SHA-256 of the view names and the size and modification time of ``intrinsics.txt`` and every RGB, pose and
    mask file."""
    digest = hashlib.sha256()
    st = (record.path / "intrinsics.txt").stat()
    digest.update(f"intrinsics:{st.st_size}:{st.st_mtime_ns}\n".encode())
    for index, name in enumerate(record.view_names):
        paths = [record.rgb_path(index), record.pose_path(index)]
        if record.has_mask:
            paths.append(record.mask_path(index))
        digest.update(f"{name}\n".encode())
        for path in paths:
            try:
                st = Path(path).stat()
            except OSError:
                raise DepthnerfError(f"{path}: file is missing (it was indexed a moment ago)") from None
            digest.update(f"{st.st_size}:{st.st_mtime_ns}\n".encode())
    return digest.hexdigest()


def _exact_uint8(images: np.ndarray) -> np.ndarray | None:
    """``images`` as uint8 if ``u / 255.0`` in float32 gives back every value exactly, else None."""
    u = np.rint(images * 255.0)
    if u.min() < 0 or u.max() > 255:
        return None
    u8 = u.astype(np.uint8)
    return u8 if np.array_equal(u8.astype(np.float32) / 255.0, images) else None


class ViewStore:
    """A view store folder for one resolution and pixel centre (see the module docstring)."""

    def __init__(self, root: str | os.PathLike, resolution: int, pixel_center: float) -> None:
        self.root = Path(root)
        self.resolution = resolution
        self.pixel_center = pixel_center

    def object_dir(self, record: ObjectRecord) -> Path:
        """Folder of one object's arrays."""
        return self.root / f"{record.category}_{record.split}" / record.object_id

    def _check_manifest(self) -> None:
        """Write the manifest of a new store; refuse one made for another resolution, pixel centre or format."""
        want = {"format": STORE_FORMAT, "resolution": self.resolution, "pixel_center": self.pixel_center}
        path = self.root / "manifest.json"
        if not path.exists():
            self.root.mkdir(parents=True, exist_ok=True)
            write_json_atomic(path, want)
            return
        try:
            have = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise DepthnerfError(f"{path}: unreadable view store manifest ({err})") from None
        if not isinstance(have, dict) or any(have.get(k) != v for k, v in want.items()):
            raise DepthnerfError(f"{path}: the view store was made for {have}, this run needs {want}; name "
                                 "another --data.view_store folder")

    def _meta(self, record: ObjectRecord) -> dict | None:
        try:
            return json.loads((self.object_dir(record) / "meta.json").read_text())
        except (OSError, ValueError):
            return None

    def write(self, record: ObjectRecord, fingerprint: str, replace: bool = False) -> None:
        """Decode every view of ``record`` and write its folder (atomically: temporary folder, then rename).

        ``replace``: the folder there is stale and is moved aside first; without it a folder that another process
        finished in the meantime is kept and this one dropped (runs that share a store may start together)."""
        obj = load_object(record, resolution=self.resolution, pixel_center=self.pixel_center)
        images = obj.images.permute(0, 2, 3, 1).contiguous().numpy()
        stored = _exact_uint8(images)
        final = self.object_dir(record)
        tmp = final.with_name(f".{final.name}.tmp-{os.getpid()}")
        shutil.rmtree(tmp, ignore_errors=True)
        tmp.mkdir(parents=True)
        np.save(tmp / "images.npy", images if stored is None else stored)
        np.save(tmp / "masks.npy", obj.masks.numpy())
        np.save(tmp / "poses.npy", obj.poses.numpy())
        np.save(tmp / "bboxes.npy", obj.bboxes.numpy())
        i = obj.intrinsics
        meta = {"fingerprint": fingerprint, "views": record.num_views, "images": str((images if stored is None
                                                                                       else stored).dtype),
                "intrinsics": {"focal": i.focal, "cx": i.cx, "cy": i.cy, "height": i.height, "width": i.width}}
        write_json_atomic(tmp / "meta.json", meta)
        if replace and final.exists():
            old = final.with_name(f".{final.name}.old-{os.getpid()}")
            final.rename(old)
            shutil.rmtree(old, ignore_errors=True)
        try:
            tmp.rename(final)
        except OSError:  # another process wrote the same object first: theirs is as good
            shutil.rmtree(tmp, ignore_errors=True)
            if self._meta(record) is None:
                raise

    def ensure(self, records: Sequence[ObjectRecord], *, rank: int = 0, world: int = 1, check_all: bool = True,
               progress: bool = False) -> dict[str, int]:
        """Build the objects of ``records[rank::world]`` that are missing or stale; with ``check_all``, their
        fingerprints are compared (else only that each object exists). Returns counts ``built`` / ``rebuilt`` /
        ``reused``."""
        self._check_manifest()
        counts = {"built": 0, "rebuilt": 0, "reused": 0}
        share = list(records)[rank::world]
        t0, last = time.perf_counter(), time.perf_counter()
        for n, record in enumerate(share):
            meta = self._meta(record)
            if meta is not None and not check_all:
                counts["reused"] += 1
                continue
            fingerprint = object_fingerprint(record)
            if meta is not None and meta.get("fingerprint") == fingerprint:
                counts["reused"] += 1
                continue
            self.write(record, fingerprint, replace=meta is not None or self.object_dir(record).exists())
            counts["rebuilt" if meta is not None else "built"] += 1
            if progress and time.perf_counter() - last > 10:
                last = time.perf_counter()
                print(f"view store {self.root}: {n + 1}/{len(share)} objects ({last - t0:.0f} s)", file=sys.stderr,
                      flush=True)
        return counts

    def open(self, record: ObjectRecord) -> StoredObject:
        """One object's arrays, memory-mapped (a missing or unreadable object is one line naming it)."""
        folder = self.object_dir(record)
        meta = self._meta(record)
        if meta is None:
            raise DepthnerfError(f"{folder}: missing from the view store (it is built when training starts)")
        try:
            arrays = {n: np.load(folder / f"{n}.npy", mmap_mode="r", allow_pickle=False)
                      for n in ("images", "masks", "poses", "bboxes")}
        except (OSError, ValueError) as err:
            raise DepthnerfError(f"{folder}: unreadable view store object ({err}); delete the folder to rebuild it"
                                 ) from None
        if arrays["images"].shape[0] != record.num_views or meta.get("views") != record.num_views:
            raise DepthnerfError(f"{folder}: holds {arrays['images'].shape[0]} views, the dataset has "
                                 f"{record.num_views}; delete the folder to rebuild it")
        return StoredObject(images=arrays["images"], masks=arrays["masks"],
                            poses=torch.from_numpy(np.array(arrays["poses"])),
                            bboxes=torch.from_numpy(np.array(arrays["bboxes"])),
                            intrinsics=Intrinsics(**meta["intrinsics"]))
