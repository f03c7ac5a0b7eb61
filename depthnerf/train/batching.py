"""Training batches as a pure function of ``(seed, step)``: exact resume and rank sharding for free.

Schedule (pixelNeRF / the paper): each step draws ``objects_per_batch`` objects; for each object one random source
view (or the step's number of them, :meth:`BatchPlan.sources`) and ``rays_per_object`` target rays from its *other*
views. During the bounding-box phase target rays are drawn inside the object's 2D box in the target view
(pixelNeRF's ``bbox`` sampling), afterwards from the whole image.

Determinism: object order is an epoch-wise permutation drawn from ``seed + epoch``; a step's number of source
views (where several counts are allowed) from a generator seeded by ``hash(seed, s, -2)``; the source views, target
views and pixels of item ``k`` at step ``s`` from a generator seeded by ``hash(seed, s, k)``. Nothing depends on
DataLoader workers, on how many ranks share the batch, or on where a run was resumed.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import TypeVar

import torch
from jaxtyping import Bool, Float, Int
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import SourceViews

_MIX = 0x9E3779B97F4A7C15
T = TypeVar("T")


def item_seed(seed: int, step: int, k: int) -> int:
    """A 63-bit seed for item ``k`` of step ``step`` (splitmix-style mixing, stable across Python versions)."""
    x = (seed * 1_000_003 + step) * 1_000_033 + k
    x = (x + _MIX) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 30)) * 0xBF58476D1CE4E5B9) & 0xFFFFFFFFFFFFFFFF
    x = ((x ^ (x >> 27)) * 0x94D049BB133111EB) & 0xFFFFFFFFFFFFFFFF
    return (x ^ (x >> 31)) & 0x7FFFFFFFFFFFFFFF


@dataclass(frozen=True)
class BatchPlan:
    """Which objects step ``s`` trains on, from the schedule alone."""

    num_objects: int
    """Number of training objects."""
    seed: int
    """Run seed."""
    bbox_steps: int
    """Steps of the bounding-box phase (phase 1)."""
    objects_phase1: int
    """Objects per batch in phase 1."""
    objects_phase2: int
    """Objects per batch in phase 2."""
    source_views: tuple[int, ...] = (1,)
    """The source-view counts a step draws from (``DataConfig.source_views``)."""

    def sources(self, step: int) -> int:
        """Source views per object at ``step``: one of :attr:`source_views`, uniformly (no draw, so no change to
        any other draw, when there is only one)."""
        if len(self.source_views) == 1:
            return self.source_views[0]
        g = torch.Generator().manual_seed(item_seed(self.seed, step, -2))
        return self.source_views[int(torch.randint(len(self.source_views), (), generator=g))]

    def batch_size(self, step: int) -> int:
        return self.objects_phase1 if step < self.bbox_steps else self.objects_phase2

    def consumed(self, step: int) -> int:
        """Objects consumed by steps ``0 .. step-1``."""
        p1 = min(step, self.bbox_steps)
        return p1 * self.objects_phase1 + max(0, step - self.bbox_steps) * self.objects_phase2

    def epoch(self, step: int) -> float:
        """Fractional epoch at the start of ``step`` (objects consumed / objects in the set)."""
        return self.consumed(step) / self.num_objects

    def _perm(self, epoch: int) -> Tensor:
        g = torch.Generator().manual_seed(item_seed(self.seed, -1, epoch))
        return torch.randperm(self.num_objects, generator=g)

    def objects(self, step: int) -> list[int]:
        """Indices of the objects of ``step``, drawn without replacement through epoch-wise permutations."""
        start, n = self.consumed(step), self.batch_size(step)
        out = []
        for pos in range(start, start + n):
            epoch, off = divmod(pos, self.num_objects)
            out.append(int(self._perm(epoch)[off]))
        return out


def check_world_split(bbox_steps: int, objects_phase1: int, objects_phase2: int, max_steps: int, world: int,
                      start: int = 0) -> None:
    """Refuse, in one line, a world size that a global batch the run will still use does not divide (every rank
    takes an equal share of each step's objects, so the result does not depend on how the batch is split); ``start``:
    the step the run starts or resumes at (a phase that ends before it has no steps left to split)."""
    used = ([("objects_phase1", objects_phase1)] if start < bbox_steps else []) + \
        ([("objects_phase2", objects_phase2)] if max_steps > max(bbox_steps, start) else [])
    for name, size in used:
        if size % world:
            sizes = sorted({n for _, n in used})
            fits = [k for k in range(1, min(sizes) + 1) if all(n % k == 0 for n in sizes)]
            raise DepthnerfError(
                f"--schedule.{name} {size}: a global batch of {size} objects does not split over {world} ranks; "
                f"launch {', '.join(map(str, fits))} processes, or raise the batch sizes (--schedule.objects_phase1 / "
                f"--schedule.objects_phase2: a departure from the preset)")


def shard(items: Sequence[T], rank: int, world: int) -> list[T]:
    """The contiguous slice of a global batch that ``rank`` of ``world`` processes (sizes must divide)."""
    if len(items) % world:
        raise ValueError(f"global batch of {len(items)} objects does not split over {world} ranks")
    per = len(items) // world
    return list(items[rank * per:(rank + 1) * per])


@dataclass(frozen=True)
class ItemKey:
    """Everything a worker needs to build one training item deterministically."""

    object_index: int
    """Index into the training split's object list."""
    seed: int
    """Seed of this item's generator (from :func:`item_seed`)."""
    use_bbox: bool
    """Draw target pixels inside the target view's bounding box."""
    sources: int = 1
    """Source views the item is conditioned on (:meth:`BatchPlan.sources` of its step)."""


def pick_views(num_views: int, num_targets: int, gen: torch.Generator, sources: int = 1
               ) -> tuple[list[int], list[int]]:
    """``sources`` distinct source views and ``num_targets`` distinct target views among the others (all others
    if fewer): the first ``sources`` of one random permutation, then the rest (so one source draws as before)."""
    perm = torch.randperm(num_views, generator=gen).tolist()
    src, others = perm[:sources], perm[sources:]
    return src, others[:num_targets] if num_targets > 0 else others


def sample_pixels(num_rays: int, masks_shape: tuple[int, int, int], bboxes: Int[Tensor, "V 4"] | None,
                  gen: torch.Generator) -> tuple[Int[Tensor, " R"], Int[Tensor, " R"], Int[Tensor, " R"]]:
    """``num_rays`` (view, row, col) triples, uniform over the views' pixels or inside their boxes.

    Boxes are ``x0, y0, x1, y1`` inclusive (pixelNeRF). Sampling is with replacement, as pixelNeRF's.
    """
    v_count, height, width = masks_shape
    view = torch.randint(v_count, (num_rays,), generator=gen)
    if bboxes is None:
        row = torch.randint(height, (num_rays,), generator=gen)
        col = torch.randint(width, (num_rays,), generator=gen)
    else:
        box = bboxes[view].to(torch.float64)
        u = torch.rand(num_rays, 2, generator=gen, dtype=torch.float64)
        col = (box[:, 0] + u[:, 0] * (box[:, 2] - box[:, 0] + 1)).floor().long().clamp(0, width - 1)
        row = (box[:, 1] + u[:, 1] * (box[:, 3] - box[:, 1] + 1)).floor().long().clamp(0, height - 1)
    return view, row, col


@dataclass
class TrainBatch(TensorBundle):
    """One collated training batch (B objects of this rank)."""

    source: SourceViews
    """The source views of each object (V: the step's count, 1 in the paper), as the conditioning stage makes it
    (:func:`depthnerf.model.conditioning.condition`): image, camera and normalised prior (None for the baseline)."""
    ray_origins: Float[Tensor, "B R 3"]
    """World ray origins of the target rays."""
    ray_dirs: Float[Tensor, "B R 3"]
    """Unit world ray directions."""
    target_rgb: Float[Tensor, "B R 3"]
    """Ground-truth colours of the target rays."""
    target_prior: Float[Tensor, "B R"] | None
    """Normalised prior disparity at the target pixels (for the optional depth loss)."""
    target_fg: Bool[Tensor, "B R"]
    """Whether each target pixel is foreground."""
    target_cos: Float[Tensor, "B R"]
    """Camera-frame z of each unit target ray direction (z-depth = ray distance * this)."""

    def item(self, k: int) -> TrainBatch:
        """Object ``k`` of the batch, as a batch of one."""
        return self.slice(k, k + 1, dim=0)

    def pin_memory(self) -> TrainBatch:
        """Page-locked copy (the DataLoader calls this with ``pin_memory=True``: asynchronous host-to-GPU copies)."""
        return self.map(lambda x: x.pin_memory())


def collate(items: list[TrainBatch]) -> TrainBatch:
    """Stack per-object items (each with B = 1) into one batch."""
    return TrainBatch.cat(items, dim=0)


PACK_ALIGN = 16
"""Byte alignment of each tensor in a :class:`PackedBatch` (so that every dtype can be viewed in place)."""


@dataclass(frozen=True)
class PackedBatch:
    """A :class:`TrainBatch` as one flat byte tensor and its layout: what a DataLoader worker sends. A batch of
    separate tensors crosses the process boundary as one shared-memory segment per tensor (measured here: ~3.4 ms
    to receive a paper-preset batch of 9 tensors, more than building it from a view store); packed, it is one
    segment, one pinned copy and one host-to-device copy. :meth:`to` gives the batch back, every tensor a view of
    the copied bytes: the same values, bit for bit."""

    flat: Tensor
    """uint8: each tensor's bytes in :meth:`TensorBundle.map` order, each starting at a multiple of
    :data:`PACK_ALIGN`."""
    skeleton: TrainBatch
    """The batch with every tensor replaced by a ``meta`` tensor of its shape and dtype (plain values kept)."""

    @classmethod
    def pack(cls, batch: TrainBatch) -> PackedBatch:
        """The packed form of ``batch`` (CPU tensors)."""
        parts: list[Tensor] = []
        skeleton = batch.map(lambda x: parts.append(x) or torch.empty(x.shape, dtype=x.dtype, device="meta"))
        sizes = [x.numel() * x.element_size() for x in parts]
        starts = [0]
        for size in sizes[:-1]:
            starts.append(starts[-1] + -(-size // PACK_ALIGN) * PACK_ALIGN)
        flat = torch.empty(starts[-1] + sizes[-1] if parts else 0, dtype=torch.uint8)
        for x, start, size in zip(parts, starts, sizes, strict=True):
            flat[start:start + size] = x.contiguous().reshape(-1).view(torch.uint8)
        return cls(flat, skeleton)

    def pin_memory(self) -> PackedBatch:
        """Page-locked copy (the DataLoader's ``pin_memory=True`` calls this)."""
        return PackedBatch(self.flat.pin_memory(), self.skeleton)

    def to(self, device: torch.device | str, non_blocking: bool = False) -> TrainBatch:
        """The batch on ``device``: one copy of the bytes, then views."""
        flat = self.flat.to(device, non_blocking=non_blocking)
        offset = 0

        def view(meta: Tensor) -> Tensor:
            nonlocal offset
            size = meta.numel() * meta.element_size()
            out = flat[offset:offset + size].view(meta.dtype).reshape(meta.shape)
            offset += -(-size // PACK_ALIGN) * PACK_ALIGN
            return out

        return self.skeleton.map(view)


def collate_packed(items: list[TrainBatch]) -> PackedBatch:
    """:func:`collate`, packed for the trip from a DataLoader worker (:class:`PackedBatch`)."""
    return PackedBatch.pack(collate(items))


def step_keys(plan: BatchPlan, step: int, rank: int = 0, world: int = 1) -> list[ItemKey]:
    """The item keys this rank builds at ``step``."""
    objs = plan.objects(step)
    sources = plan.sources(step)
    keys = [ItemKey(o, item_seed(plan.seed, step, k), step < plan.bbox_steps, sources) for k, o in enumerate(objs)]
    return shard(keys, rank, world)


@dataclass(frozen=True)
class StepSampler:
    """DataLoader batch sampler: one list of this rank's keys per step, from ``start`` (resume) to ``stop``."""

    plan: BatchPlan
    """The schedule."""
    start: int
    """First step (the resumed step)."""
    stop: int
    """One past the last step."""
    rank: int = 0
    """This process's rank."""
    world: int = 1
    """Number of processes."""

    def __iter__(self) -> Iterator[list[ItemKey]]:
        for step in range(self.start, self.stop):
            yield step_keys(self.plan, step, self.rank, self.world)

    def __len__(self) -> int:
        return max(0, self.stop - self.start)
