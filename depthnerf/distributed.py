"""Process-group set-up for multi-GPU / multi-node jobs launched with ``torchrun`` (training and evaluation).

``torchrun`` sets ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK``; without them the job is a single process. The
backend is NCCL on CUDA (one GPU per process, ``LOCAL_RANK`` picks it) and gloo on CPU (what the CPU tests use).
Training: rank 0 alone logs, validates and checkpoints (PyTorch DDP). Evaluation: every rank scores its share of
the objects and rank 0 merges them (:func:`gather_to_main`, :func:`broadcast_from_main`). A neutral module: any
stage may use it.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist

from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class DistInfo:
    """Where this process sits in the job."""

    rank: int
    """Global rank (0 = the process that logs and checkpoints, and merges an evaluation)."""
    world: int
    """Number of processes."""
    device: torch.device
    """Device this process computes on."""

    @property
    def is_main(self) -> bool:
        return self.rank == 0


def make_deterministic() -> None:
    """Deterministic algorithms everywhere (``--deterministic``): cuBLAS's fixed workspace (set before CUDA is
    initialised), ``torch.use_deterministic_algorithms(True)`` and no cuDNN autotuning. The model then gathers
    features and resizes maps with deterministic kernels (``depthnerf.model.features``), which it checks with
    ``torch.are_deterministic_algorithms_enabled()``."""
    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    torch.use_deterministic_algorithms(True)
    torch.backends.cudnn.benchmark = False
    torch.backends.cudnn.deterministic = True


def pick_device(device: str, local_rank: int = 0) -> torch.device:
    """``auto`` (CUDA if available), ``cpu``, ``cuda`` or ``cuda:N``; a CUDA request without a GPU is a one-line
    :class:`DepthnerfError`."""
    if device not in ("auto", "cpu", "cuda") and not (device.startswith("cuda:") and device[5:].isdigit()):
        raise DepthnerfError(f"--device {device!r}: choose auto, cpu, cuda or cuda:N")
    if device == "cpu" or (device == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise DepthnerfError(f"--device {device}: no CUDA GPU is available to this process "
                             "(torch.cuda.is_available() is False); use --device cpu")
    index = int(device[5:]) if device.startswith("cuda:") else local_rank
    if index >= torch.cuda.device_count():
        raise DepthnerfError(f"--device {device}: only {torch.cuda.device_count()} CUDA device(s) are visible")
    return torch.device(f"cuda:{index}")


def setup(device: str = "auto", deterministic: bool = False, timeout: timedelta | None = None) -> DistInfo:
    """Initialise the process group if launched by torchrun, and pick this rank's device. ``timeout``: how long a
    collective may wait for the slowest rank (None: PyTorch's default)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if deterministic:
        make_deterministic()
    dev = pick_device(device, local)
    use_cuda = dev.type == "cuda"
    if use_cuda:
        torch.cuda.set_device(dev)
    if world > 1 and not dist.is_initialized():
        kwargs = {} if timeout is None else {"timeout": timeout}
        dist.init_process_group(backend="nccl" if use_cuda else "gloo", **kwargs)
    return DistInfo(rank=rank, world=world, device=dev)


def barrier(info: DistInfo) -> None:
    if info.world > 1:
        dist.barrier()


def teardown(info: DistInfo) -> None:
    if info.world > 1 and dist.is_initialized():
        dist.destroy_process_group()


def gather_to_main(obj: Any, info: DistInfo) -> list[Any] | None:
    """Every rank's picklable ``obj``, in rank order, on rank 0 (None on the other ranks); ``[obj]`` alone."""
    if info.world == 1:
        return [obj]
    out = [None] * info.world if info.is_main else None
    dist.gather_object(obj, out, dst=0)
    return out


def all_ranks(obj: Any, info: DistInfo) -> list[Any]:
    """Every rank's picklable ``obj``, in rank order, on every rank (a barrier too); ``[obj]`` alone."""
    if info.world == 1:
        return [obj]
    out: list[Any] = [None] * info.world
    dist.all_gather_object(out, obj)
    return out


def broadcast_from_main(obj: Any, info: DistInfo) -> Any:
    """Rank 0's picklable ``obj`` on every rank (what the other ranks pass is ignored)."""
    if info.world == 1:
        return obj
    box = [obj if info.is_main else None]
    dist.broadcast_object_list(box, src=0)
    return box[0]
