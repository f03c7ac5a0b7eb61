"""The memory a training step needs: settings whose step cannot fit the device are refused before training starts,
and an allocation that fails during training is one line naming the settings that size a step.

A step renders, per rank, ``B x R`` rays of ``S`` samples each in one pass (no chunking, :mod:`depthnerf.train.step`):
``B`` objects (``schedule.objects_phase1`` / ``objects_phase2`` split over the ranks; one at a time with
``schedule.step_shape per-object``), ``R = schedule.rays_per_object`` and ``S = n_coarse + n_importance + n_gaussian``
samples per ray in the fine pass (``render.sampler``). Its sample points alone, ``B x R x S x 3`` float32, are one
tensor; the field's features and activations are many times larger. :func:`check_step_fits` refuses settings whose
points alone exceed the device's whole memory (a GPU's, or the host's RAM plus swap), which no step can ever hold.
Target rays are drawn with replacement (:func:`depthnerf.train.batching.sample_pixels`) and objects through
epoch-wise permutations, so the data bounds neither ``R`` nor ``B``. Below that bound, :func:`one_line_out_of_memory`
turns the allocation that fails into one line; nothing is written on the way out, so the run keeps its last complete
checkpoint.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Callable, Iterator
from pathlib import Path

import torch

from depthnerf.distributed import DistInfo
from depthnerf.errors import DepthnerfError
from depthnerf.train.config import TrainConfig

POINT_BYTES = 3 * 4
"""Bytes of one sample point (x, y, z in float32)."""
_TRIED = re.compile(r"[Tt]ried to allocate (\d+) bytes|[Tt]ried to allocate ([\d.]+ ?[KMGTPE]?i?B)\b")


def readable_bytes(count: float) -> str:
    """``count`` bytes in binary units (``1.5 GiB``)."""
    for unit in ("B", "KiB", "MiB", "GiB", "TiB", "PiB"):
        if count < 1024 or unit == "PiB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def samples_per_ray(cfg: TrainConfig) -> int:
    """Samples per ray of the fine pass, the larger one (it re-evaluates the coarse samples)."""
    sampler = cfg.render.sampler
    return sampler.n_coarse + sampler.n_importance + sampler.n_gaussian


def step_sizes(cfg: TrainConfig, world: int, phase: int) -> str:
    """The settings that size a step of schedule phase ``phase`` (1: bounding-box phase), with their values."""
    s, sampler = cfg.schedule, cfg.render.sampler
    objects = s.objects_phase1 if phase == 1 else s.objects_phase2
    notes = ([f"{objects // world} per rank"] if world > 1 else []) + (
        ["one at a time: --schedule.step_shape per-object"] if s.step_shape == "per-object" else [])
    how = f" ({'; '.join(notes)})" if notes else ""
    most = max(cfg.data.source_views)  # each source view is encoded, and each sample gathers a feature from each
    views = (f", each object on up to {most} source views (--data.source_views "
             f"{','.join(map(str, cfg.data.source_views))})" if most > 1 else "")
    return (f"--schedule.objects_phase{phase} {objects} objects{how} x --schedule.rays_per_object "
            f"{s.rays_per_object} rays x {samples_per_ray(cfg)} samples per ray (--render.sampler.n_coarse "
            f"{sampler.n_coarse} + n_importance {sampler.n_importance} + n_gaussian {sampler.n_gaussian}){views}, at "
            f"--data.resolution {cfg.data.resolution}")


def device_memory(device: torch.device) -> int | None:
    """All the memory of ``device`` in bytes: a CUDA GPU's, or the host's RAM plus swap for the CPU (Linux's
    ``/proc/meminfo``, else RAM alone); None where it is not known."""
    if device.type == "cuda":
        return torch.cuda.get_device_properties(device).total_memory
    if device.type != "cpu":
        return None
    try:
        fields = dict(line.split(":", 1) for line in Path("/proc/meminfo").read_text().splitlines() if ":" in line)
        return sum(int(fields[k].split()[0]) * 1024 for k in ("MemTotal", "SwapTotal") if k in fields) or None
    except (OSError, ValueError):
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (AttributeError, OSError, ValueError):
        return None


def check_step_fits(cfg: TrainConfig, info: DistInfo) -> None:
    """Refuse, in one line naming the settings, a run whose step's sample points alone (module docstring) exceed
    all the memory of this rank's device: no step of it could ever run."""
    s = cfg.schedule
    phases = ([1] if s.bbox_steps > 0 else []) + ([2] if s.max_steps > s.bbox_steps else [])
    if not phases:
        return
    objects = {1: s.objects_phase1, 2: s.objects_phase2}
    phase = max(phases, key=lambda p: objects[p])
    at_once = 1 if s.step_shape == "per-object" else max(1, objects[phase] // info.world)
    need = at_once * s.rays_per_object * samples_per_ray(cfg) * POINT_BYTES
    have = device_memory(info.device)
    if have is not None and need > have:
        raise DepthnerfError(f"{step_sizes(cfg, info.world, phase)}: a step's sample points alone would take "
                             f"{readable_bytes(need)}, more than all the memory of {info.device} "
                             f"({readable_bytes(have)}); lower them")


def is_out_of_memory(err: BaseException) -> bool:
    """Whether ``err`` is an allocation that failed: ``torch.OutOfMemoryError``, the CPU allocator's
    ``RuntimeError``, a ``MemoryError``, or one of them re-raised from a DataLoader worker (its text kept)."""
    if isinstance(err, torch.OutOfMemoryError | MemoryError):
        return True
    text = str(err)
    return isinstance(err, RuntimeError) and ("DefaultCPUAllocator: can't allocate memory" in text
                                              or "out of memory" in text)


def failed_allocation(err: BaseException) -> str:
    """The allocation that failed, where torch's message names it (``could not allocate 2.0 GiB``), else the
    exception's type."""
    found = _TRIED.search(str(err))
    if found is None:
        return f"{type(err).__name__}"
    return f"could not allocate {readable_bytes(int(found[1])) if found[1] else found[2]}"


def resumable(checkpoint: Path | None) -> str:
    """What becomes of the run after it stopped for memory: its last checkpoint and how to go on."""
    if checkpoint is None:
        return "the run has no checkpoint yet: start it again with smaller settings (without --resume)"
    return (f"the run keeps its last checkpoint {checkpoint.name}: --resume continues it on a device with more "
            "memory; smaller settings need a new run (another --out)")


@contextlib.contextmanager
def one_line_out_of_memory(info: DistInfo, doing: Callable[[], str]) -> Iterator[None]:
    """An allocation that fails inside the block (:func:`is_out_of_memory`) becomes one :class:`DepthnerfError`:
    this rank (where there are several; it is this rank's failure), ``out of memory``, the device, the allocation
    torch names and ``doing()`` (called then: what ran, the settings that size it with their values, how to go on).
    Anything else passes through."""
    try:
        yield
    except (RuntimeError, MemoryError) as err:
        if not is_out_of_memory(err):
            raise
        rank = f"rank {info.rank} of {info.world}: " if info.world > 1 else ""
        raise DepthnerfError(f"{rank}out of memory on {info.device} ({failed_allocation(err)}) {doing()}") from None


def in_training_step(cfg: TrainConfig, world: int, step: int, checkpoint: Path | None) -> str:
    """:func:`one_line_out_of_memory`'s ``doing`` for training step ``step``."""
    phase = 1 if step < cfg.schedule.bbox_steps else 2
    return f"at training step {step}: a step renders {step_sizes(cfg, world, phase)}; {resumable(checkpoint)}"


def in_validation(cfg: TrainConfig, step: int, checkpoint: Path | None) -> str:
    """:func:`one_line_out_of_memory`'s ``doing`` for the validation of step ``step``."""
    return (f"validating at step {step}: it renders --log.render_chunk {cfg.log.render_chunk} rays per chunk x "
            f"{samples_per_ray(cfg)} samples per ray, at --data.resolution {cfg.data.resolution}; "
            f"{resumable(checkpoint)}")
