"""A cheap fingerprint of an object's files: what an evaluation's resume checks the data against
(:mod:`depthnerf.eval.shards`).

What it reads, per object: the bytes of ``intrinsics.txt`` and of every ``pose/*.txt`` (a few KB), and the sizes
of every ``rgb/`` image and, where the object has them, of its depth maps, masks and ``mesh.ply``; no image is
read. Per dataset, once: the dataset card (``<category>_card.json``) without its tallies over the splits
(:data:`CARD_TALLIES`, which change when another split is generated into the same folder).

Content, not times: a copy (``cp -r`` without ``-p``, ``rsync``) keeps the fingerprint, so a copied evaluation
still resumes. A dataset generated again in place (``depthnerf synth`` with another seed: the same object ids and,
on the test split's fixed camera spiral, the same poses, but other shapes) changes it through the image sizes
(PNG sizes follow the content) and the card's seed. An edit that keeps every file's size and every camera (a few
repainted pixels) goes unseen; the depth prior cache has its own byte-wise fingerprint
(:func:`depthnerf.depth.cache.rgb_fingerprint`).
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

from depthnerf.data.card import read_dataset_card
from depthnerf.data.records import ObjectRecord
from depthnerf.errors import DepthnerfError

SCHEME = "files-1"
"""Prefix of a fingerprint (:func:`object_fingerprint`): what it covers, so a later scheme is told apart."""
CARD_TALLIES = ("counts", "styles", "z_range")
"""Card entries left out of the fingerprint: tallies and measurements over every split (they change when
another split grows), not a description of the objects fingerprinted."""


def card_digest(root: str | Path, category: str) -> str:
    """SHA-256 of the dataset card without :data:`CARD_TALLIES` (sorted-key JSON); ``"no card"`` without one."""
    card = read_dataset_card(root, category)
    if card is None:
        return "no card"
    kept = {k: v for k, v in card.items() if k not in CARD_TALLIES}
    return hashlib.sha256(json.dumps(kept, sort_keys=True).encode()).hexdigest()


def _size(path: Path) -> int:
    try:
        return path.stat().st_size
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read it ({err.strerror or err})") from None


def _bytes(path: Path) -> bytes:
    try:
        return path.read_bytes()
    except OSError as err:
        raise DepthnerfError(f"{path}: cannot read it ({err.strerror or err})") from None


def object_fingerprint(record: ObjectRecord, card: str) -> str:
    """``files-1:<hex>``: SHA-256 of ``card`` (:func:`card_digest`), the object's ``intrinsics.txt`` and pose
    files' bytes and its images', depth maps', masks' and mesh's sizes (module docstring). A file that cannot be
    read is a one-line :class:`DepthnerfError` naming it."""
    digest = hashlib.sha256(card.encode())
    intrinsics = _bytes(record.path / "intrinsics.txt")
    digest.update(b"%d\0" % len(intrinsics) + intrinsics)
    for view, name in enumerate(record.view_names):
        pose = _bytes(record.pose_path(view))
        sizes = [_size(record.rgb_path(view))]
        sizes += [_size(record.depth_path(view))] if record.has_depth else []
        sizes += [_size(record.mask_path(view))] if record.has_mask else []
        digest.update(f"{name}\0{len(pose)}\0".encode() + pose + f"{sizes}\0".encode())
    if record.mesh_path is not None:
        digest.update(f"mesh {_size(record.mesh_path)}".encode())
    return f"{SCHEME}:{digest.hexdigest()[:32]}"


class DataFingerprint:
    """The fingerprints of one dataset's objects (:func:`object_fingerprint`; the card read once)."""

    def __init__(self, root: str | Path, category: str) -> None:
        self.card = card_digest(root, category)
        """:func:`card_digest` of the dataset."""

    def __call__(self, record: ObjectRecord) -> str:
        return object_fingerprint(record, self.card)
