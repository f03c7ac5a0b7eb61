"""Process-group set-up for multi-GPU / multi-node jobs launched with ``torchrun`` (training and evaluation).

``torchrun`` sets ``RANK``, ``WORLD_SIZE`` and ``LOCAL_RANK``; without them the job is a single process. The
backend is NCCL on CUDA (one GPU per process, ``LOCAL_RANK`` picks it) and gloo on CPU (what the CPU tests use).
Training: rank 0 alone logs, validates and checkpoints (PyTorch DDP). Evaluation: every rank scores its share of
the objects and rank 0 merges them (:func:`gather_to_main`, :func:`broadcast_from_main`). A neutral module: any
stage may use it.

A rank that stops (its own one-line error, a kill) breaks the other ranks' next collective; :func:`peer_failure`
turns that into one line on those ranks too, instead of a backend traceback. Checks that every rank makes before the
work starts (the data, the run folder) agree instead (:func:`checked_together`): one line for the whole job.
"""

from __future__ import annotations

import contextlib
import os
import re
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import timedelta
from typing import Any

import torch
import torch.distributed as dist
from torch import nn

from depthnerf.errors import DepthnerfError, refusal


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


def _shown(name: str) -> str:
    """A device request as a message quotes it: as given when it is one word, else its repr."""
    return name if re.fullmatch(r"[\w.:-]+", name) else repr(name)


def _visible(count: int) -> str:
    """``N visible CUDA device(s) (cuda:0, ...)``."""
    names = ", ".join(f"cuda:{i}" for i in range(count)) if count <= 3 else f"cuda:0 to cuda:{count - 1}"
    return f"{count} visible CUDA device{'' if count == 1 else 's'} ({names})"


def check_device_text(device: str | torch.device, flag: str = "--device", auto: bool = True) -> str:
    """The request as text when it names a device this package runs on: ``cpu``, ``cuda``, ``cuda:N`` (and
    ``auto`` where ``auto``); any other text (``mps``, ``meta``, ``gpu``, ...) is a one-line
    :class:`DepthnerfError` naming ``flag`` and the choices. Depends on the text alone."""
    name = str(device)
    if name in ("cpu", "cuda") or (auto and name == "auto") or re.fullmatch(r"cuda:\d+", name):
        return name
    raise DepthnerfError(f"{flag} {_shown(name)}: choose {'auto, ' if auto else ''}cpu, cuda or cuda:N")


def pick_device(device: str | torch.device, local_rank: int | None = None, *, flag: str = "--device",
                auto: bool = True) -> torch.device:
    """The one check of a device request: every ``--device`` flag (eval, train, reconstruct, demo, app, depth,
    depth-eval), :class:`~depthnerf.infer.session.SessionOptions` and
    :func:`~depthnerf.pretrained.load.load_pretrained` (a ``torch.device`` is read as its text).

    ``auto`` (allowed where ``auto``): CUDA when available, else the CPU; ``cpu``; ``cuda``; ``cuda:N``. Another
    device type (:func:`check_device_text`), CUDA without a GPU, or ``cuda:N`` past the GPUs this process sees
    is a one-line :class:`DepthnerfError` naming ``flag`` and what there is. ``local_rank`` (a torchrun rank's
    ``LOCAL_RANK``): the GPU ``cuda`` and ``auto`` mean, one per process; None: ``cuda`` as given (torch's
    current GPU)."""
    name = check_device_text(device, flag, auto)
    if name == "cpu" or (name == "auto" and not torch.cuda.is_available()):
        return torch.device("cpu")
    if not torch.cuda.is_available():
        raise DepthnerfError(f"{flag} {name}: no CUDA GPU is available to this process "
                             f"(torch.cuda.is_available() is False); use {flag} cpu")
    count = torch.cuda.device_count()
    index = int(name[5:]) if name.startswith("cuda:") else local_rank
    if index is None:
        return torch.device("cuda")
    if index < count:
        return torch.device("cuda", index)
    if name.startswith("cuda:"):
        raise DepthnerfError(f"{flag} {name}: this machine has {_visible(count)}")
    raise DepthnerfError(f"{flag} {name}: LOCAL_RANK {index} has no CUDA device of its own: this machine has "
                         f"{_visible(count)}; launch at most {count} processes per machine")


def _rank_device(device: str, rank: int, local: int, world: int) -> torch.device:
    """:func:`pick_device` for a torchrun rank, before its process group starts, a refusal printed once
    (:func:`~depthnerf.errors.refusal`): by rank 0 when the text is wrong (every rank alike), by each machine's
    ``LOCAL_RANK`` 0 when the machine lacks the device (its ranks alike), and by the first rank past the
    machine's GPUs when it runs more processes than it has GPUs. One process prints its own."""
    def teller(r: int) -> int:
        return r if world > 1 else 0

    try:
        check_device_text(device)
    except DepthnerfError as err:
        raise refusal(str(err), teller(rank)) from None
    try:
        pick_device(device)
    except DepthnerfError as err:
        raise refusal(str(err), teller(local)) from None
    try:
        return pick_device(device, local)
    except DepthnerfError as err:
        raise refusal(str(err), teller(local - torch.cuda.device_count())) from None


def setup(device: str = "auto", deterministic: bool = False, timeout: timedelta | None = None) -> DistInfo:
    """Initialise the process group if launched by torchrun, and pick this rank's device (a refusal printed
    once: :func:`_rank_device`). ``timeout``: how long a collective may wait for the slowest rank (None:
    PyTorch's default)."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    if deterministic:
        make_deterministic()
    dev = _rank_device(device, rank, local, world)
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


def _is_collective_failure(err: BaseException) -> bool:
    """Whether ``err`` is a process-group backend's failure (a peer gone, a timeout), not a bug of the caller's:
    NCCL and the store raise ``DistError`` subclasses, gloo a plain ``RuntimeError`` naming its source file."""
    return isinstance(err, dist.DistError) or (isinstance(err, RuntimeError) and "gloo" in str(err))


@contextlib.contextmanager
def peer_failure(info: DistInfo, what: str) -> Iterator[None]:
    """Turn a collective that fails because another rank stopped into one :class:`DepthnerfError` line naming
    this rank and ``what`` it was doing (the rank that stopped printed why); anything else passes through."""
    try:
        yield
    except (RuntimeError, dist.DistError) as err:
        if info.world == 1 or not _is_collective_failure(err):
            raise
        text = str(err).strip().splitlines()[0] if str(err).strip() else type(err).__name__
        said = text.split("] ", 1)[-1].split(". ", 1)[0][:160]  # gloo: "[file:line] what. Advice..."
        raise DepthnerfError(f"rank {info.rank} of {info.world}: another rank stopped while this one was {what}; "
                             f"the rank that stopped says why ({said})") from None


@contextlib.contextmanager
def checked_together(info: DistInfo, what: str) -> Iterator[None]:
    """Checks every rank makes (``what`` they are: the data, the run folder), agreed on by all ranks at the end of
    the block: when any rank refused, every rank stops with the first refusal, rank 0 printing it and the others
    raising :class:`~depthnerf.errors.RefusedOnMain` (:func:`~depthnerf.errors.refusal`), so the job prints it
    once; suffixed with the refusing rank where not every rank refused alike. A collective: every rank enters the
    block. One process: a refusal passes through as raised."""
    failed = None
    try:
        yield
    except DepthnerfError as err:
        if info.world == 1:
            raise
        failed = str(err)
    if info.world == 1:
        return
    with peer_failure(info, what):
        said = all_ranks(failed, info)
    refused = [(rank, message) for rank, message in enumerate(said) if message is not None]
    if refused:
        rank, message = refused[0]
        alike = all(other == message for other in said)
        raise refusal(message if alike else f"{message} (rank {rank})", info.rank) from None


class NormMerge:
    """Running BatchNorm statistics of a DDP step as one process training the whole batch would have them.

    DDP alone keeps rank 0's statistics, of its share of the batch only, so they (and every evaluation, which
    uses them) would depend on the number of ranks. Each step, :meth:`state` before it, :meth:`merge` after it:
    every rank started from the same state and updated it with its own share (rank ``r``'s share is the ``r``-th
    slice of the global batch); the merge sets every rank's statistics to all ranks' updates made one after
    another in rank order, up to float rounding. With momentum ``m`` and ``k`` updates per rank,
    ``a = (1 - m)^k``, rank ``r`` holds ``a * before + d_r``, so the merge is ``a^N * before + sum_r a^(N-1-r) d_r``
    and the update counts grow by ``N * k``. One all-gather of the statistics, no host synchronisation; nothing
    for one process. Layers without a momentum (cumulative averages) are left as DDP leaves them.
    """

    def __init__(self, model: nn.Module, info: DistInfo) -> None:
        self.info = info
        self.norms = [m for m in model.modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)
                      and m.track_running_stats and m.running_mean is not None and m.momentum is not None]
        """The layers merged (a fixed order)."""
        self.sizes = [m.num_features for m in self.norms] * 2
        device = self.norms[0].running_mean.device if self.norms else torch.device("cpu")
        self._repeats = torch.tensor(self.sizes, device=device)
        self._base = torch.tensor([1.0 - m.momentum for m in self.norms] * 2, device=device)
        self.active = info.world > 1 and bool(self.norms)
        """Whether there is anything to merge."""

    def _stats(self) -> list[torch.Tensor]:
        return [m.running_mean for m in self.norms] + [m.running_var for m in self.norms]

    def state(self) -> tuple[torch.Tensor, torch.Tensor] | None:
        """The running means and variances as one new flat tensor, and the update counts (None: inactive)."""
        if not self.active:
            return None
        with torch.no_grad():
            return torch.cat(self._stats()), torch.stack([m.num_batches_tracked for m in self.norms])

    def merge(self, before: tuple[torch.Tensor, torch.Tensor] | None) -> None:
        """Merge the ranks' updates since :meth:`state` returned ``before`` (class docstring)."""
        if before is None:
            return
        stats, counts = before
        mine, now = self.state()
        with torch.no_grad():
            gathered = [torch.empty_like(mine) for _ in range(self.info.world)]
            dist.all_gather(gathered, mine)
            updates = (now - counts).repeat(2)
            keep = torch.repeat_interleave(self._base.to(mine.dtype) ** updates, self._repeats,
                                           output_size=mine.numel())
            merged = stats
            for theirs in gathered:
                merged = keep * merged + (theirs - keep * stats)
            torch._foreach_copy_(self._stats(), list(merged.split(self.sizes)))
            torch._foreach_copy_([m.num_batches_tracked for m in self.norms],
                                 list((counts + self.info.world * (now - counts)).unbind()))
