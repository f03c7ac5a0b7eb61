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
many); a store made at another resolution or pixel centre is refused in one line. A run keeps the fingerprints it
found at start-up and refuses an object rebuilt from other files since (two datasets with the same object ids
sharing one store). The folder named as a store must be new, empty or a store, and outside the dataset's split
folders (there it would read as an object); an object folder holding anything but the store's files is never
replaced; temporary folders that a killed build left are removed after an hour.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import shutil
import sys
import tempfile
import time
import uuid
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
from depthnerf.files import folder_problem, write_bytes_atomic, write_json_atomic

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


def store_fingerprint(record: ObjectRecord) -> str:
    """SHA-256 of the view names and the size and modification time of ``intrinsics.txt`` and every RGB, pose and
    mask file (not :func:`depthnerf.depth.cache.rgb_fingerprint`, which covers the RGB files alone: the store
    also holds poses, masks and intrinsics)."""
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


LEFTOVER_AGE_S = 3600.0
"""Temporary folders (``.<id>.tmp-*``, ``.<id>.old-*``) older than this are a killed build's and are removed; a
live build of one object takes about a second."""

STORE_FILES = frozenset({"images.npy", "masks.npy", "poses.npy", "bboxes.npy", "meta.json"})
"""What an object folder of a store holds; a folder holding anything else is never replaced."""


def _save_durably(path: Path, array: np.ndarray) -> None:
    buffer = io.BytesIO()
    np.save(buffer, array)
    write_bytes_atomic(path, buffer.getvalue())


class ViewStore:
    """A view store folder for one resolution and pixel centre (see the module docstring).

    :meth:`ensure` remembers each object's fingerprint, and :meth:`open` (also in DataLoader workers, which get a
    copy) refuses an object rebuilt from other files since: a run never trains on views that changed under it.
    """

    def __init__(self, root: str | os.PathLike, resolution: int, pixel_center: float) -> None:
        self.root = Path(root)
        self.resolution = resolution
        self.pixel_center = pixel_center
        self.expected: dict[str, str] = {}
        """Object key -> the fingerprint :meth:`ensure` found or wrote."""

    def object_dir(self, record: ObjectRecord) -> Path:
        """Folder of one object's arrays."""
        return self.root / f"{record.category}_{record.split}" / record.object_id

    def check(self) -> None:
        """Refuse, writing nothing, a folder that cannot be this store (:meth:`_check_manifest`'s refusals): a run
        calls it before it writes its own folder."""
        self._check_manifest(write=False)

    def _check_manifest(self, write: bool = True) -> None:
        """Write the manifest of a new store (``write``); refuse one made for another resolution, pixel centre or
        format, a file in the way, and a folder that holds other things (the dataset itself, say: the store would
        replace its object folders)."""
        want = {"format": STORE_FORMAT, "resolution": self.resolution, "pixel_center": self.pixel_center}
        path = self.root / "manifest.json"
        problem = folder_problem(self.root, "--data.view_store")
        if problem is not None:
            raise DepthnerfError(problem)
        if not path.exists():
            others = sorted(p.name for p in self.root.iterdir() if not p.name.startswith(".")) \
                if self.root.is_dir() else []
            if not path.exists():  # checked again after listing: another process may have just made this store
                if others:
                    raise DepthnerfError(f"{self.root}: not empty and not a view store (it holds "
                                         f"{', '.join(others[:3])}{', ...' if len(others) > 3 else ''}); name an "
                                         "empty or new folder for --data.view_store, never the dataset's")
                if not write:
                    return
                try:
                    write_json_atomic(path, want)
                except OSError as err:
                    raise DepthnerfError(f"{path}: cannot write the view store manifest ({err})") from None
                return
        try:
            have = json.loads(path.read_text())
        except (OSError, ValueError) as err:
            raise DepthnerfError(f"{path}: unreadable view store manifest ({err})") from None
        if not isinstance(have, dict) or any(have.get(k) != v for k, v in want.items()):
            raise DepthnerfError(f"{path}: the view store was made for {have}, this run needs {want}; name "
                                 "another --data.view_store folder")

    def _read_meta(self, record: ObjectRecord) -> dict | None:
        """One object's ``meta.json``; None when there is none, one line naming the file when it is unreadable."""
        path = self.object_dir(record) / "meta.json"
        try:
            meta = json.loads(path.read_text())
        except FileNotFoundError:
            return None
        except (OSError, ValueError) as err:
            raise DepthnerfError(f"{path}: unreadable view store metadata ({err}); delete the folder to rebuild "
                                 "it") from None
        if not isinstance(meta, dict):
            raise DepthnerfError(f"{path}: unreadable view store metadata (not a JSON object); delete the folder to "
                                 "rebuild it")
        return meta

    def _meta(self, record: ObjectRecord) -> dict | None:
        """One object's ``meta.json``, None when it is missing or unreadable (the object is built again)."""
        try:
            return self._read_meta(record)
        except DepthnerfError:
            return None

    def write(self, record: ObjectRecord, fingerprint: str, replace: bool = False) -> bool:
        """Decode every view of ``record`` and write its folder (atomically: temporary folder, then rename);
        returns whether this folder is the one in the store now.

        ``replace``: the folder there is stale and is moved aside first, unless another process has written the
        same fingerprint there since (a folder that appeared between :meth:`ensure`'s look and this call is not
        stale: moving it aside would leave the other processes, which found it, without it); without ``replace`` a
        folder that another process finished in the meantime is kept and this one dropped (runs that share a store
        may start together). A folder holding anything but the store's files is never replaced."""
        obj = load_object(record, resolution=self.resolution, pixel_center=self.pixel_center)
        decoded = obj.images.permute(0, 2, 3, 1).contiguous().numpy()
        exact = _exact_uint8(decoded)
        images = decoded if exact is None else exact
        final = self.object_dir(record)
        i = obj.intrinsics
        meta = {"fingerprint": fingerprint, "views": record.num_views, "images": str(images.dtype),
                "intrinsics": {"focal": i.focal, "cx": i.cx, "cy": i.cy, "height": i.height, "width": i.width}}
        try:
            final.parent.mkdir(parents=True, exist_ok=True)
            tmp = Path(tempfile.mkdtemp(prefix=f".{final.name}.tmp-", dir=final.parent))
            for name, array in (("images", images), ("masks", obj.masks.numpy()), ("poses", obj.poses.numpy()),
                                ("bboxes", obj.bboxes.numpy())):
                _save_durably(tmp / f"{name}.npy", array)
            write_json_atomic(tmp / "meta.json", meta)
            if replace and (self._meta(record) or {}).get("fingerprint") == fingerprint:
                shutil.rmtree(tmp, ignore_errors=True)  # another process wrote these very views since ensure looked
                return False
            if replace and final.exists():
                held = {p.name for p in final.iterdir()}
                if not held <= STORE_FILES:
                    shutil.rmtree(tmp, ignore_errors=True)
                    raise DepthnerfError(f"{final}: not a view store object (it holds {', '.join(sorted(held))}); "
                                         "refusing to replace it")
                old = final.with_name(f".{final.name}.old-{uuid.uuid4().hex}")
                final.rename(old)
                shutil.rmtree(old, ignore_errors=True)
        except OSError as err:
            raise DepthnerfError(f"{final}: cannot write the view store object ({err})") from None
        try:
            tmp.rename(final)
        except OSError:  # another process wrote the same object first: theirs is as good
            shutil.rmtree(tmp, ignore_errors=True)
            if self._meta(record) is None:
                raise DepthnerfError(f"{final}: cannot write the view store object (the folder exists and is not "
                                     "one); delete it") from None
            return False
        return True

    def ensure(self, records: Sequence[ObjectRecord], *, rank: int = 0, world: int = 1,
               progress: bool = False) -> dict[str, int]:
        """Build the objects of ``records[rank::world]`` that are missing or stale (their fingerprints compared);
        returns counts ``built`` / ``rebuilt`` / ``reused`` (an object another process wrote first is reused)."""
        for split_folder in sorted({Path(record.path).parent for record in records}):
            if self.root.resolve().is_relative_to(split_folder.resolve()):
                raise DepthnerfError(f"{self.root}: inside the split folder {split_folder}, where the store would be "
                                     "read as an object of the dataset; name a folder outside it for "
                                     "--data.view_store")
        self._check_manifest()
        counts = {"built": 0, "rebuilt": 0, "reused": 0}
        share = list(records)[rank::world]
        self._sweep({self.object_dir(record).parent for record in share})
        t0, last = time.perf_counter(), time.perf_counter()
        for n, record in enumerate(share):
            meta = self._meta(record)
            fingerprint = store_fingerprint(record)
            self.expected[str(self.object_dir(record))] = fingerprint
            if meta is not None and meta.get("fingerprint") == fingerprint:
                counts["reused"] += 1
                continue
            ours = self.write(record, fingerprint, replace=meta is not None or self.object_dir(record).exists())
            counts["reused" if not ours else "rebuilt" if meta is not None else "built"] += 1
            if progress and time.perf_counter() - last > 10:
                last = time.perf_counter()
                print(f"view store {self.root}: {n + 1}/{len(share)} objects ({last - t0:.0f} s)", file=sys.stderr,
                      flush=True)
        return counts

    def _sweep(self, folders: set[Path]) -> None:
        """Remove what killed builds left in ``folders`` (temporary object folders older than
        :data:`LEFTOVER_AGE_S`)."""
        cutoff = time.time() - LEFTOVER_AGE_S
        for folder in folders:
            if not folder.is_dir():
                continue
            for left in [*folder.glob(".*.tmp-*"), *folder.glob(".*.old-*")]:
                try:
                    if left.is_dir() and left.stat().st_mtime < cutoff:
                        shutil.rmtree(left, ignore_errors=True)
                except OSError:
                    pass  # another process removed it first

    def open(self, record: ObjectRecord) -> StoredObject:
        """One object's arrays, memory-mapped (a missing, unreadable or changed object is one line naming it)."""
        folder = self.object_dir(record)
        meta = self._read_meta(record)
        if meta is None:
            raise DepthnerfError(f"{folder}: missing from the view store (it is built when training starts; is "
                                 "another run rebuilding it?)")
        expected = self.expected.get(str(folder))
        if expected is not None and meta.get("fingerprint") != expected:
            raise DepthnerfError(f"{folder}: rebuilt from other files since this run started (does a run on other "
                                 "data share this --data.view_store?); give each dataset its own store")
        try:
            arrays = {n: np.load(folder / f"{n}.npy", mmap_mode="r", allow_pickle=False)
                      for n in ("images", "masks", "poses", "bboxes")}
            intrinsics = Intrinsics(**meta["intrinsics"])
        except (OSError, ValueError, KeyError, TypeError) as err:
            raise DepthnerfError(f"{folder}: unreadable view store object ({err}); delete the folder to rebuild it"
                                 ) from None
        if arrays["images"].shape[0] != record.num_views or meta.get("views") != record.num_views:
            raise DepthnerfError(f"{folder}: holds {arrays['images'].shape[0]} views, the dataset has "
                                 f"{record.num_views}; delete the folder to rebuild it")
        return StoredObject(images=arrays["images"], masks=arrays["masks"],
                            poses=torch.from_numpy(np.array(arrays["poses"])),
                            bboxes=torch.from_numpy(np.array(arrays["bboxes"])), intrinsics=intrinsics)
