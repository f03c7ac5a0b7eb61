"""The depth-prior cache: precomputed raw disparity per object, keyed by estimator, weights and resolution.

Layout (written by ``depthnerf depth``, read by :class:`PriorStore`)::

    <data>/depth_priors/<estimator>-<hash12>-<res>/manifest.json
    <data>/depth_priors/<estimator>-<hash12>-<res>/<category>_<split>/<object_id>.safetensors

``hash12`` is the first 12 hex digits of the estimator's weights hash (:class:`PriorProvenance`) and ``res`` the
image side length the priors were computed at. Each object file holds one tensor ``disparity`` ``[V, H, W]``
(float16; float32 if a value would overflow float16), the raw relative disparity of every view in the object's
``view_names`` order, and string metadata: ``fingerprint``, ``weights_hash``, ``estimator``, ``resolution``,
``views``. Files are written to a temporary name and renamed, so a crash never leaves a partial file.

Stale detection: an object's *fingerprint* is the SHA-256 of the view names and the bytes of their RGB files
(reading them costs about what the file checks of ``index_split`` already spend on them); a regenerated or edited
dataset changes it, even when every file keeps its size (uncompressed PNGs), and loading then fails instead of
silently reusing the old priors; copying the dataset does not. Caches written before this fingerprint (view names,
RGB file sizes and the first file's bytes; no ``rgb-bytes:`` prefix) are still checked the way they were made, so
they are not recomputed, and checking them reads no more than that (the byte-wise fingerprint is computed only for
``rgb-bytes:`` entries and for entries being written). A missing, partial, stale or other-estimator cache is a
:class:`~depthnerf.errors.DepthnerfError` naming the exact ``depthnerf depth ...`` command that makes it.

Damage (:func:`header_problem`, :func:`values_problem`): a file that is no safetensors file, lacks the
``disparity`` tensor, has another dtype or a shape other than ``[V, res, res * W / H]`` of the object, or holds a
non-finite value is an error naming the file and the same command, which recomputes it (``depthnerf depth`` checks
every value of an entry it would keep). Reading for training checks the header of each object once and the
values it reads. The sign is not checked: a raw relative disparity is defined up to a shift, so negative values
are valid (the ``bundled`` net's output is about half negative).

``oracle`` priors need no cache (computed from ``depth/`` on the fly) but are served through the same
:class:`PriorStore` API; ``none`` has no store (:meth:`PriorStore.open` returns None).
"""

from __future__ import annotations

import hashlib
import json
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from jaxtyping import Float
from safetensors import SafetensorError
from safetensors.torch import safe_open
from torch import Tensor

from depthnerf.data.records import ObjectRecord
from depthnerf.depth.backend import PriorProvenance, oracle_disparity
from depthnerf.depth.estimators import describe_estimator
from depthnerf.errors import DepthnerfError
from depthnerf.files import write_bytes_atomic
from depthnerf.state_dicts import safetensors_bytes

CACHE_DIRNAME = "depth_priors"
"""Folder under the dataset root that holds every cache."""

FLOAT16_MAX = 65000.0
"""Raw disparities with a larger magnitude are stored as float32 instead of float16."""


def cache_dir(data_root: Path, provenance: PriorProvenance, resolution: int) -> Path:
    """``<data>/depth_priors/<estimator>-<hash12>-<res>``."""
    return Path(data_root) / CACHE_DIRNAME / f"{provenance.estimator}-{provenance.short_hash}-{resolution}"


def object_path(root: Path, record: ObjectRecord) -> Path:
    """Cache file of one object inside a cache folder."""
    return root / f"{record.category}_{record.split}" / f"{record.object_id}.safetensors"


def depth_command(data_root: Path, estimator: str, checkpoint: str | None, resolution: int,
                  category: str | None = None, split: str | None = None) -> str:
    """The ``depthnerf depth ...`` command line that (re)makes a cache."""
    parts = ["depthnerf depth", f"--data {data_root}", f"--depth {estimator}"]
    if checkpoint:
        parts.append(f"--depth-checkpoint {checkpoint}")
    if category:
        parts.append(f"--category {category}")
    if split:
        parts.append(f"--splits {split}")
    parts.append(f"--resolution {resolution}")
    return " ".join(parts)


FINGERPRINT_SCHEME = "rgb-bytes"
"""Prefix of :func:`rgb_fingerprint`; a stored fingerprint without it is the earlier scheme
(:func:`_sizes_fingerprint`)."""


def _rgb_bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except FileNotFoundError:
        raise DepthnerfError(f"{path}: image file is missing") from None
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read image ({err.strerror or err})") from None


def rgb_fingerprint(record: ObjectRecord) -> str:
    """``rgb-bytes:`` + the SHA-256 of the view names and the bytes of their RGB files (see the module docstring)."""
    digest = hashlib.sha256()
    for index, name in enumerate(record.view_names):
        data = _rgb_bytes(Path(record.rgb_path(index)))
        digest.update(f"{name}:{len(data)}\n".encode())
        digest.update(hashlib.sha256(data).digest())
    return f"{FINGERPRINT_SCHEME}:{digest.hexdigest()}"


def _sizes_fingerprint(record: ObjectRecord) -> str:
    """The earlier fingerprint: SHA-256 of the view names, their RGB file sizes and the first RGB file's bytes."""
    digest = hashlib.sha256()
    for index, name in enumerate(record.view_names):
        path = Path(record.rgb_path(index))
        try:
            size = path.stat().st_size
        except OSError:
            raise DepthnerfError(f"{path}: image file is missing") from None
        digest.update(f"{name}:{size}\n".encode())
    if record.view_names:
        digest.update(_rgb_bytes(Path(record.rgb_path(0))))
    return digest.hexdigest()


def is_bytes_fingerprint(stored: str | None) -> bool:
    """Whether a stored fingerprint is of the :func:`rgb_fingerprint` scheme (``rgb-bytes:``), the one checking
    it needs the bytes of every RGB file for; an earlier one is checked by :func:`_sizes_fingerprint`."""
    return isinstance(stored, str) and stored.startswith(f"{FINGERPRINT_SCHEME}:")


def fingerprint_matches(stored: str | None, record: ObjectRecord, current: str | None = None) -> bool:
    """Whether a cache entry's stored fingerprint is ``record``'s now, under the scheme it was written with
    (``current``: :func:`rgb_fingerprint` of ``record`` when the caller has it already; computed here only for
    an ``rgb-bytes:`` entry)."""
    if not isinstance(stored, str):
        return False
    if is_bytes_fingerprint(stored):
        return stored == (current or rgb_fingerprint(record))
    return stored == _sizes_fingerprint(record)


def missing_depth(record: ObjectRecord) -> str:
    """Why ``record`` has no ground-truth depth, to end an error line: no ``depth/``, or the first problem that
    made its ``depth/`` unusable (the warning the indexer gave)."""
    issue = next((i for i in getattr(record, "issues", ()) if i.part == "depth" and i.disables), None)
    return "none found" if issue is None else f"its depth/ is not usable ({issue.text})"


def storage_dtype(disparity: Float[Tensor, "V H W"]) -> torch.dtype:
    """How the cache stores a disparity tensor: float16, or float32 if a value would overflow float16."""
    return torch.float16 if disparity.abs().max() <= FLOAT16_MAX else torch.float32


def as_cached(disparity: Float[Tensor, "V H W"]) -> Float[Tensor, "V H W"]:
    """``disparity`` rounded exactly as the cache stores it (:func:`storage_dtype`), back in float32.

    A live estimator's prior passed through here equals the prior ``depthnerf eval`` reads from the cache for
    the same image, so the demo and the evaluation condition the model on the same numbers.
    """
    disparity = disparity.detach().float().cpu()
    return disparity.to(storage_dtype(disparity)).float()


def write_object_priors(path: Path, disparity: Float[Tensor, "V H W"], metadata: dict[str, str]) -> None:
    """Atomically write one object's raw disparity (:func:`depthnerf.files.write_bytes_atomic`)."""
    disparity = disparity.detach().float().cpu()
    if not torch.isfinite(disparity).all():
        raise DepthnerfError(f"{path}: estimator produced non-finite disparity; refusing to cache it")
    dtype = storage_dtype(disparity)
    write_bytes_atomic(path, safetensors_bytes({"disparity": disparity.to(dtype).contiguous()}, metadata))


def read_object_metadata(path: Path) -> dict[str, str] | None:
    """Metadata of a cached object file, or None if there is no such (readable) file."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            return dict(handle.metadata() or {})
    except (SafetensorError, OSError):
        return None


STORED_DTYPES = ("F16", "F32")
"""safetensors dtype names of a cached ``disparity`` tensor (:func:`storage_dtype`)."""


def cached_shape(record: ObjectRecord, resolution: int) -> tuple[int, int, int]:
    """``[V, H, W]`` of an object's cached disparity: every view at height ``resolution``, the width scaled with it
    (as :func:`depthnerf.data.srn.load_object` resizes)."""
    height, width = record.intrinsics.height, record.intrinsics.width
    return len(record.view_names), int(resolution), int(resolution) * width // height


def header_problem(handle: Any, record: ObjectRecord, resolution: int) -> str | None:
    """What is wrong with the header of an open cache file (``safe_open`` handle) for ``record`` at ``resolution``,
    to follow ``<path>: `` in an error line; None when its ``disparity`` tensor has a stored dtype and the shape
    :func:`cached_shape`. Reads no values."""
    if "disparity" not in handle.keys():
        held = ", ".join(sorted(handle.keys())) or "none"
        return f"unreadable depth prior (no 'disparity' tensor; tensors: {held})"
    sliced = handle.get_slice("disparity")
    shape, dtype = tuple(sliced.get_shape()), sliced.get_dtype()
    want = cached_shape(record, resolution)
    if dtype not in STORED_DTYPES:
        return f"unreadable depth prior (disparity is {dtype}, not {' or '.join(STORED_DTYPES)})"
    if len(shape) == 3 and shape[0] != want[0]:
        return f"depth prior holds {shape[0]} views, the object has {want[0]}"
    if shape != want:
        return (f"depth prior is {'x'.join(map(str, shape)) or 'a scalar'}, the object's {want[0]} views at "
                f"{resolution} px are {'x'.join(map(str, want))}")
    return None


def values_problem(disparity: Float[Tensor, "V H W"], views: Sequence[int]) -> str | None:
    """What is wrong with disparity values read from a cache file (``views``: the object's view of each row), to
    follow ``<path>: `` in an error line; None when every value is finite."""
    finite = torch.isfinite(disparity).flatten(1).all(dim=1)
    if bool(finite.all()):
        return None
    return f"depth prior holds non-finite values (view {views[int((~finite).nonzero()[0])]})"


def object_file_problem(path: Path, record: ObjectRecord, resolution: int) -> str | None:
    """Everything wrong with a cache file that exists (:func:`header_problem`, then every value:
    :func:`values_problem`), to follow ``<path>: ``; None when it is sound. Metadata is not compared here."""
    try:
        with safe_open(str(path), framework="pt") as handle:
            problem = header_problem(handle, record, resolution)
            if problem is None:
                problem = values_problem(handle.get_tensor("disparity"), range(len(record.view_names)))
    except (SafetensorError, OSError) as err:
        return f"unreadable depth prior ({err})"
    return problem


class PriorStore:
    """Read access to one estimator's depth priors for a dataset (cached, or on the fly for ``oracle``).

    Use :meth:`open`; ``load`` is cheap enough to call per sample in DataLoader workers (the store pickles).
    """

    def __init__(self, data_root: Path, provenance: PriorProvenance, resolution: int) -> None:
        self.data_root = Path(data_root)
        self.resolution = int(resolution)
        self._provenance = provenance
        self._verified: set[tuple[str, str, str]] = set()

    @classmethod
    def open(cls, data_root: str | os.PathLike, estimator: str, checkpoint: str | None = None,
             resolution: int = 128) -> PriorStore | None:
        """The store for ``estimator`` at ``resolution``; None for ``none``. Cached estimators need a
        manifest made by ``depthnerf depth`` with the same weights and resolution (else a DepthnerfError)."""
        provenance = describe_estimator(estimator, checkpoint)
        if provenance is None:
            return None
        if estimator == "oracle":
            return OraclePriorStore(Path(data_root), provenance, resolution)
        return CachedPriorStore(Path(data_root), provenance, resolution, checkpoint)

    @property
    def provenance(self) -> dict[str, Any]:
        """JSON-able provenance (estimator, checkpoint, weights hash, licence, resolution, cache folder)."""
        return {**self._provenance.as_dict(), "resolution": self.resolution}

    def load(self, record: ObjectRecord, views: Sequence[int]) -> Float[Tensor, "V H W"]:
        """Raw relative disparity of the given views of one object (float32)."""
        raise NotImplementedError

    def check(self, records: Sequence[ObjectRecord]) -> None:
        """Fail early (one line naming the fix) if any of these objects has no valid prior."""
        raise NotImplementedError

    def _check_views(self, record: ObjectRecord, views: Sequence[int], where: Path) -> list[int]:
        views = [int(v) for v in views]
        n = len(record.view_names)
        bad = [v for v in views if not -n <= v < n]
        if bad:
            raise DepthnerfError(f"{where}: view index {bad[0]} out of range for {n} views")
        return [v % n for v in views]


class OraclePriorStore(PriorStore):
    """``oracle``: ``1 / z`` on the foreground (0 on the background) from the dataset's ground-truth depth."""

    def load(self, record: ObjectRecord, views: Sequence[int]) -> Float[Tensor, "V H W"]:
        from depthnerf.data.card import INTEGER_CENTRED
        from depthnerf.data.srn import load_object

        if not record.has_depth:
            raise DepthnerfError(f"{record.path}: the 'oracle' prior needs ground-truth depth/ maps, "
                                 f"{missing_depth(record)}")
        views = self._check_views(record, views, Path(record.path))
        obj = load_object(record, views, resolution=self.resolution, with_depth=True,
                          pixel_center=INTEGER_CENTRED)  # depth pixels only
        return oracle_disparity(obj.depths)

    def check(self, records: Sequence[ObjectRecord]) -> None:
        for record in records:
            if not record.has_depth:
                raise DepthnerfError(f"{record.path}: the 'oracle' prior needs ground-truth depth/ maps, "
                                     f"{missing_depth(record)}")


class CachedPriorStore(PriorStore):
    """Priors precomputed by ``depthnerf depth`` (see the module docstring)."""

    def __init__(self, data_root: Path, provenance: PriorProvenance, resolution: int,
                 checkpoint: str | None) -> None:
        super().__init__(data_root, provenance, resolution)
        self.checkpoint = checkpoint
        self.root = cache_dir(self.data_root, provenance, self.resolution)
        manifest_path = self.root / "manifest.json"
        if not manifest_path.is_file():
            raise DepthnerfError(self._missing_message())
        try:
            manifest = json.loads(manifest_path.read_text())
            stored = manifest["provenance"]
        except (OSError, ValueError, KeyError, TypeError):
            raise DepthnerfError(f"{manifest_path}: unreadable cache manifest; rerun: {self.command()}") from None
        if stored.get("weights_hash") != provenance.weights_hash or manifest.get("resolution") != self.resolution:
            raise DepthnerfError(f"{manifest_path}: cache was made by other weights or resolution; "
                                 f"rerun: {self.command()}")
        self.manifest: dict[str, Any] = manifest

    @property
    def provenance(self) -> dict[str, Any]:
        return {**super().provenance, "cache": str(self.root)}

    def command(self, category: str | None = None, split: str | None = None) -> str:
        """The command that (re)makes this cache (optionally for one category/split)."""
        return depth_command(self.data_root, self._provenance.estimator, self.checkpoint, self.resolution,
                             category, split)

    def _missing_message(self) -> str:
        prov = self._provenance
        if self.root.is_dir():  # the folder of these weights and resolution, its manifest lost
            return f"{self.root / 'manifest.json'}: cache manifest is missing; rerun: {self.command()}"
        others = sorted(p.name for p in (self.data_root / CACHE_DIRNAME).glob("*") if p.is_dir())
        found = f" (found only: {', '.join(others)})" if others else ""
        return (f"{self.root}: no '{prov.estimator}' depth priors for weights {prov.short_hash} at "
                f"{self.resolution} px{found}; run: {self.command()}")

    def _verify(self, record: ObjectRecord) -> Path:
        key = (record.category, record.split, record.object_id)
        path = object_path(self.root, record)
        if key in self._verified:
            return path
        cmd = self.command(record.category, record.split)
        if not path.exists():
            raise DepthnerfError(f"{path}: depth prior missing (cache incomplete); run: {cmd}")
        try:
            with safe_open(str(path), framework="pt") as handle:
                meta, problem = dict(handle.metadata() or {}), header_problem(handle, record, self.resolution)
        except (SafetensorError, OSError) as err:
            raise DepthnerfError(f"{path}: unreadable depth prior ({err}); run: {cmd}") from None
        if meta.get("weights_hash") != self._provenance.weights_hash or meta.get("resolution") != str(
                self.resolution):
            raise DepthnerfError(f"{path}: depth prior made by other weights or resolution; run: {cmd}")
        if not fingerprint_matches(meta.get("fingerprint"), record):
            raise DepthnerfError(f"{path}: depth prior is stale (the object's images changed since it was "
                                 f"computed); run: {cmd}")
        if problem is not None:
            raise DepthnerfError(f"{path}: {problem}; run: {cmd}")
        self._verified.add(key)
        return path

    def check(self, records: Sequence[ObjectRecord]) -> None:
        for record in records:
            self._verify(record)

    def load(self, record: ObjectRecord, views: Sequence[int]) -> Float[Tensor, "V H W"]:
        """Raw relative disparity of the given views (float32); the file's header is checked again (it may have
        changed since :meth:`check`) and the values read must be finite."""
        path = self._verify(record)
        views = self._check_views(record, views, path)
        try:
            with safe_open(str(path), framework="pt") as handle:
                problem = header_problem(handle, record, self.resolution)
                if problem is None:
                    sliced = handle.get_slice("disparity")
                    if views and views == list(range(views[0], views[0] + len(views))):
                        disparity = sliced[views[0]:views[-1] + 1]
                    else:
                        disparity = handle.get_tensor("disparity")[views]
                    problem = values_problem(disparity, views)
        except (SafetensorError, OSError) as err:
            problem = f"unreadable depth prior ({err})"
        if problem is not None:
            raise DepthnerfError(f"{path}: {problem}; run: {self.command(record.category, record.split)}")
        return disparity.float()
