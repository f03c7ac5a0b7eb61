"""Building one training item (one object: its conditioned source views, target rays) from an :class:`ItemKey`,
and the run's store of decoded views the items read (:func:`ready_view_store`).

Used as a map-style ``Dataset`` indexed by keys from :func:`depthnerf.train.batching.step_keys`, so DataLoader
workers produce exactly what the main process would.
"""

from __future__ import annotations

import math
import sys
import time
from collections.abc import Sequence

import torch
from torch.utils.data import Dataset

from depthnerf.data.cameras import pixel_directions
from depthnerf.data.srn import ObjectRecord, load_object
from depthnerf.data.view_store import StoredObject, ViewStore
from depthnerf.depth.prior import DatasetViews, PriorSource
from depthnerf.distributed import DistInfo, checked_together
from depthnerf.model.conditioning import condition
from depthnerf.train.batching import ItemKey, TrainBatch, pick_views, sample_pixels
from depthnerf.train.config import DataConfig


class TrainItems(Dataset):
    """``items[key]`` -> a :class:`TrainBatch` with B = 1 for the object and draws named by ``key``."""

    def __init__(self, records: Sequence[ObjectRecord], prior_source: PriorSource, *, resolution: int,
                 target_views: int, rays_per_object: int, target_priors: bool, pixel_center: float = 0.0,
                 symmetry_plane: tuple[float, float, float, float] | None = None, mirror_dropout: float = 0.0,
                 mirror_jitter: float = 0.0, view_store: ViewStore | None = None, channel_permute: float = 0.0) -> None:
        self.records = list(records)
        self.prior_source = prior_source
        self.resolution = resolution
        self.target_views = target_views
        self.rays = rays_per_object
        self.target_priors = target_priors
        self.pixel_center = pixel_center
        self.symmetry_plane = symmetry_plane
        """The objects' plane (mirror models; None: sources carry none)."""
        self.mirror_dropout = mirror_dropout
        """Fraction of items conditioned with the zero ("no plane") plane instead."""
        self.mirror_jitter = mirror_jitter
        """Largest angle (degrees) by which an item's plane is turned (:func:`jittered_plane`; 0: never)."""
        self.view_store = view_store
        """Decoded views to read instead of the PNG files (the same items, to the bit); None: decode the files."""
        self.channel_permute = channel_permute
        """Fraction of items whose colour channels are permuted (``DataConfig.channel_permute``)."""

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, key: ItemKey) -> TrainBatch:
        record = self.records[key.object_index]
        gen = torch.Generator().manual_seed(key.seed)
        src, targets = pick_views(record.num_views, self.target_views, gen, key.sources)
        n_src = len(src)
        # pos: where the sources and the targets sit in obj's arrays
        if self.view_store is not None:  # every view, at the record's view indices
            obj, pos = self.view_store.open(record), [*src, *targets]
        else:  # only these views are decoded, in this order
            obj = StoredObject.from_views(load_object(record, [*src, *targets], resolution=self.resolution,
                                                      pixel_center=self.pixel_center))
            pos = list(range(n_src + len(targets)))
        tgt = torch.tensor(pos[n_src:])
        view, row, col = sample_pixels(self.rays, (len(targets), *obj.masks.shape[1:]),
                                       obj.bboxes[tgt] if key.use_bbox else None, gen)
        dirs_cam = pixel_directions(obj.intrinsics)[row, col]  # [R 3]
        rot = obj.poses[tgt][view, :3, :3]  # [R 3 3]
        dirs = torch.einsum("rij,rj->ri", rot, dirs_cam)
        origins = obj.poses[tgt][view, :3, 3]
        target_rgb, target_fg = obj.pixels(tgt[view], row, col)
        # the conditioning stage's own bundle (B = 1, V = key.sources); the target views' prior, made by the same
        # stage, feeds the optional depth loss
        plane = None
        if self.symmetry_plane is not None:  # drawn last, so the views and rays are a plain model's
            dropped = bool(torch.rand((), generator=gen) < self.mirror_dropout)
            plane = (0.0, 0.0, 0.0, 0.0) if dropped else self.symmetry_plane
            if self.mirror_jitter > 0:  # two more draws, only then: runs without jitter keep their items
                plane = plane if dropped else jittered_plane(plane, self.mirror_jitter, gen)
        src_image, src_mask = obj.views(pos[:n_src])
        if self.channel_permute > 0:  # drawn after everything else, so the views, rays and plane are as without
            order = permuted_channels(gen, self.channel_permute)
            src_image, target_rgb = src_image[:, order], target_rgb[:, order]
        source = condition(self.prior_source, src_image, src_mask, obj.poses[pos[:n_src]], obj.intrinsics,
                           where=DatasetViews(record, tuple(src)), symmetry_plane=plane).inputs
        target_prior = None
        if self.target_priors and source.disparity is not None:
            tgt_images, tgt_masks = obj.views(pos[n_src:])
            targets_in = condition(self.prior_source, tgt_images, tgt_masks, obj.poses[tgt], obj.intrinsics,
                                   where=DatasetViews(record, tuple(targets))).inputs
            target_prior = targets_in.disparity[0, :, 0][view, row, col][None]
        return TrainBatch(
            source=source, ray_origins=origins[None], ray_dirs=dirs[None],
            target_rgb=target_rgb[None], target_prior=target_prior, target_fg=target_fg[None],
            target_cos=dirs_cam[:, 2][None],
        )


def jittered_plane(plane: tuple[float, float, float, float], max_deg: float, gen: torch.Generator
                   ) -> tuple[float, float, float, float]:
    """``plane`` (``n . x = d``, unit ``n``) turned by an angle drawn uniformly from [-max_deg, max_deg] degrees
    about an axis ``a`` through its point ``d n``, ``a`` drawn uniformly among the unit vectors in the plane:
    ``n' = n cos t + (a x n) sin t``, ``d' = d cos t`` (two draws from ``gen``)."""
    angle = math.radians(max_deg) * (2.0 * float(torch.rand((), generator=gen)) - 1.0)
    turn = 2.0 * math.pi * float(torch.rand((), generator=gen))
    n = torch.tensor(plane[:3], dtype=torch.float64)
    helper = torch.eye(3, dtype=torch.float64)[int(torch.argmin(n.abs()))]
    u = torch.linalg.cross(n, helper)
    u = u / u.norm()
    axis = u * math.cos(turn) + torch.linalg.cross(n, u) * math.sin(turn)
    turned = n * math.cos(angle) + torch.linalg.cross(axis, n) * math.sin(angle)
    return (*(float(v) for v in turned), float(plane[3]) * math.cos(angle))


CHANNEL_ORDERS = ((0, 2, 1), (1, 0, 2), (1, 2, 0), (2, 0, 1), (2, 1, 0))
"""The five non-identity orders of the RGB channels."""


def permuted_channels(gen: torch.Generator, fraction: float) -> list[int]:
    """An order of the RGB channels for one item: with probability ``fraction`` one of :data:`CHANNEL_ORDERS`,
    uniformly, else ``[0, 1, 2]`` (two draws from ``gen`` either way)."""
    permute = bool(torch.rand((), generator=gen) < fraction)
    which = int(torch.randint(len(CHANNEL_ORDERS), (), generator=gen))
    return list(CHANNEL_ORDERS[which]) if permute else [0, 1, 2]


def ready_view_store(data: DataConfig, records: Sequence[ObjectRecord], info: DistInfo) -> ViewStore | None:
    """The run's view store, brought up to date (None without ``data.view_store``, with a hint on CUDA). Each rank
    builds or checks its share of the objects; once every rank has reported (a rank that failed stops them all with
    its message), every rank checks the other ranks' shares too and builds what it still lacks there (where the
    ranks do not share a disk)."""
    if not data.view_store:
        if info.device.type == "cuda" and info.is_main:
            print("data: each item decodes its object's views from PNG, which can hold a GPU back; "
                  "--data.view_store DIR decodes them once (docs/training.md, \"Decoded views\")", file=sys.stderr,
                  flush=True)
        return None
    t0 = time.perf_counter()
    store = ViewStore(data.view_store, data.resolution, data.pixel_center)
    with checked_together(info, "building the view store"):  # every rank stops with a rank's failure
        counts = store.ensure(records, rank=info.rank, world=info.world, progress=info.is_main)
    others = [record for i, record in enumerate(records) if i % info.world != info.rank]  # the others' shares
    store.ensure(others)  # fingerprints only, where the ranks share a disk; built here, where not
    if info.is_main:
        share = f" (rank 0's share of {len(records)})" if info.world > 1 else ""
        print(f"view store {store.root}: {counts['built']} objects decoded, {counts['rebuilt']} changed since and "
              f"decoded again, {counts['reused']} reused{share}, {time.perf_counter() - t0:.1f} s",
              file=sys.stderr, flush=True)
    return store
