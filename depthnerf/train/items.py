"""Building one training item (one object: source view, its prior, target rays) from an :class:`ItemKey`.

Used as a map-style ``Dataset`` indexed by keys from :func:`depthnerf.train.batching.step_keys`, so DataLoader
workers produce exactly what the main process would.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch.utils.data import Dataset

from depthnerf.data.cameras import pixel_directions
from depthnerf.data.srn import ObjectRecord, load_object
from depthnerf.depth.prior import DatasetViews, PriorSource
from depthnerf.model.conditioning import prior_input
from depthnerf.train.batching import ItemKey, TrainBatch, pick_views, sample_pixels


class TrainItems(Dataset):
    """``items[key]`` -> a :class:`TrainBatch` with B = 1 for the object and draws named by ``key``."""

    def __init__(self, records: Sequence[ObjectRecord], prior: PriorSource, *, resolution: int,
                 target_views: int, rays_per_object: int, target_priors: bool, pixel_center: float = 0.0) -> None:
        self.records = list(records)
        self.prior = prior
        self.resolution = resolution
        self.target_views = target_views
        self.rays = rays_per_object
        self.target_priors = target_priors
        self.pixel_center = pixel_center

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, key: ItemKey) -> TrainBatch:
        record = self.records[key.object_index]
        gen = torch.Generator().manual_seed(key.seed)
        src, targets = pick_views(record.num_views, self.target_views, gen)
        obj = load_object(record, [src, *targets], resolution=self.resolution, pixel_center=self.pixel_center)
        tgt = slice(1, None)
        view, row, col = sample_pixels(self.rays, (len(targets), *obj.masks.shape[1:]),
                                       obj.bboxes[tgt] if key.use_bbox else None, gen)
        dirs_cam = pixel_directions(obj.intrinsics)[row, col]  # [R 3]
        rot = obj.poses[tgt][view, :3, :3]  # [R 3 3]
        dirs = torch.einsum("rij,rj->ri", rot, dirs_cam)
        origins = obj.poses[tgt][view, :3, 3]
        src_prior = target_prior = None
        if self.prior.prior.enabled:
            views = [src, *targets] if self.target_priors else [src]
            disparity = self.prior.disparity(obj.images[: len(views)], where=DatasetViews(record, tuple(views)))
            prior = prior_input(disparity, obj.masks[: len(views)])  # [V 1 H W], as the conditioning stage makes it
            src_prior = prior[None, :1]  # [1 1 1 H W]
            if self.target_priors:
                target_prior = prior[tgt, 0][view, row, col][None]
        intr = obj.intrinsics
        return TrainBatch(
            src_images=obj.images[:1, None], src_poses=obj.poses[:1, None], src_prior=src_prior,
            focal=torch.tensor([intr.focal]), principal=torch.tensor([[intr.cx, intr.cy]]),
            ray_origins=origins[None], ray_dirs=dirs[None],
            target_rgb=obj.images[tgt][view, :, row, col][None], target_prior=target_prior,
            target_fg=obj.masks[tgt][view, row, col][None], target_cos=dirs_cam[:, 2][None],
        )
