"""BatchNorm with per-object statistics, so B objects can be encoded in one batch as if one at a time.

In training mode ``nn.BatchNorm2d`` normalises with the statistics of its whole input batch. pixelNeRF encodes
all objects of a step together, so each object's features depend on the other objects in its batch (and, under
DDP without SyncBatchNorm, on how the batch was split across ranks). This package normalises each object's
source views with their own statistics (for one source view: that image's per-channel mean and variance), as if
each object were encoded alone. That keeps a step's result independent of batch composition and rank count
(2 ranks x 2 objects = 1 process x 4 objects, CPU and CUDA) while the encoder still runs once per step.

:class:`ObjectBatchNorm2d` is a drop-in ``nn.BatchNorm2d`` (same parameters, buffers and state-dict keys). Its
``groups`` attribute (set by :func:`object_groups` for the duration of one encoder call) splits the batch into
``groups`` equal consecutive parts with their own statistics: one ``batch_norm`` call over the batch viewed as
``[V, groups * C, H, W]``, with the affine parameters and running statistics repeated per object. The running
statistics are updated as ``groups`` successive BatchNorm calls would update them (up to float rounding).
Evaluation mode is plain BatchNorm.

Few operators per layer (each one a kernel launch on a GPU): :func:`object_groups` repeats the affine
parameters and running statistics of ALL the layers of the block at once (a concatenation and one gather
each), and folds the per-object running statistics of all layers at the end of the block in one pass.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class ObjectBatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` whose training-mode statistics are per group of consecutive samples (per object)."""

    groups: int = 1
    """Number of objects in the current input batch (set by :func:`object_groups`)."""
    repeated: tuple[Tensor, Tensor, Tensor, Tensor] | None = None
    """Within :func:`object_groups`: weight, bias, running mean and running variance repeated per object
    (``[groups * C]`` each; the running ones are updated in place by this layer's call, then folded)."""

    def forward(self, x: Tensor) -> Tensor:
        g = self.groups
        if g <= 1 or not self.training:
            return super().forward(x)
        n, c, h, w = x.shape
        if n % g:
            raise ValueError(f"ObjectBatchNorm2d: batch of {n} does not split into {g} objects")
        v = n // g
        if self.momentum is None:  # cumulative averaging: g successive calls, exactly
            return torch.cat([super(ObjectBatchNorm2d, self).forward(part) for part in x.split(v)])
        track = self.track_running_stats and self.running_mean is not None
        repeated, self.repeated = self.repeated, None  # used: the running statistics are folded once per block
        if track and repeated is None:
            raise RuntimeError("ObjectBatchNorm2d: called twice in one object_groups block, or outside one")
        weight, bias, running_mean, running_var = repeated if repeated is not None else (None,) * 4
        if weight is None and self.affine:  # a layer outside the block's shared repeats
            weight, bias = self.weight.repeat(g), self.bias.repeat(g)
        # [g*v, C, H, W] -> [v, g*C, H, W]: BatchNorm over (v, H, W) for each (object, channel)
        if v == 1:
            grouped = x.reshape(1, g * c, h, w)
        else:
            grouped = x.reshape(g, v, c, h, w).transpose(0, 1).reshape(v, g * c, h, w)
        y = F.batch_norm(grouped, running_mean, running_var, weight, bias, True, self.momentum, self.eps)
        if v == 1:
            # y is a temporary of this call: a plain view of it would make the in-place ops that follow BatchNorm
            # (ResNet's ReLU(inplace=True), ``out += identity``) record a copy of the whole base in backward
            return torch.ops.aten._unsafe_view(y, (n, c, h, w))
        return y.reshape(v, g, c, h, w).transpose(0, 1).reshape(n, c, h, w)  # a copy: not a view of y


def _repeat_index(sizes: list[int], groups: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """For vectors of ``sizes`` concatenated into one: the gather index laying each vector out ``groups`` times
    in a row (``[groups * size]`` blocks, copy ``k`` at ``k * size``), and the index that reads such blocks back
    as ``[groups, sum(sizes)]`` (row ``k`` = copy ``k`` of every vector)."""
    out: list[int] = []
    back: list[list[int]] = [[] for _ in range(groups)]
    start = 0
    for size in sizes:
        for k in range(groups):
            back[k].extend(range(len(out), len(out) + size))
            out.extend(range(start, start + size))
        start += size
    return torch.tensor(out, device=device), torch.tensor(back, device=device)


class _SharedRepeats:
    """The repeated parameters and running statistics of the tracked layers of one block (one momentum)."""

    def __init__(self, norms: list[ObjectBatchNorm2d], groups: int, cache: dict | None) -> None:
        self.norms, self.groups = norms, groups
        device = norms[0].running_mean.device
        sizes = [m.num_features for m in norms]
        key = (tuple(sizes), groups, device)
        cache = {} if cache is None else cache
        if key not in cache:
            cache[key] = _repeat_index(sizes + sizes, groups, device)  # [means, vars] and [weights, biases]
        self.index, self.back = cache[key]
        self.sizes = [groups * s for s in sizes]
        with torch.no_grad():
            self.stats = torch.cat([m.running_mean for m in norms] + [m.running_var for m in norms])
            self.slots = self.stats[self.index]  # updated in place by the layers' calls (through the views)
        stat_slots = self.slots.split(self.sizes + self.sizes)
        params: list = [None] * (2 * len(norms))
        if all(m.affine for m in norms):
            params = torch.cat([m.weight for m in norms] + [m.bias for m in norms])[self.index].split(
                self.sizes + self.sizes)
        layers = len(norms)
        for i, m in enumerate(norms):
            m.repeated = (params[i], params[layers + i], stat_slots[i], stat_slots[layers + i])

    @torch.no_grad()
    def fold(self) -> None:
        """Fold each layer's ``groups`` running-statistic slots into its buffers: slot ``k`` holds
        ``(1 - m) r0 + m s_k``; ``g`` successive updates give ``(1 - m)^g r0 + sum_k (1 - m)^(g - k) m s_k``."""
        g, m = self.groups, self.norms[0].momentum
        ran = [n.repeated is None for n in self.norms]
        if not any(ran):
            return
        slots = self.slots[self.back]  # [g, 2 * sum(C)]
        decay = (1.0 - m) ** torch.arange(g - 1, -1, -1, dtype=slots.dtype, device=slots.device)
        contrib = slots - (1.0 - m) * self.stats
        new = (self.stats * (1.0 - m) ** g + (decay[:, None] * contrib).sum(0)).split(
            [s // g for s in self.sizes] * 2)
        layers = len(self.norms)
        buffers = [n.running_mean for n in self.norms] + [n.running_var for n in self.norms]
        keep = [i for i in range(2 * layers) if ran[i % layers]]
        torch._foreach_copy_([buffers[i] for i in keep], [new[i] for i in keep])
        torch._foreach_add_([n.num_batches_tracked for n, r in zip(self.norms, ran, strict=True) if r], g)


@contextlib.contextmanager
def object_groups(module: nn.Module, groups: int, cache: dict | None = None) -> Iterator[None]:
    """Within the block, every :class:`ObjectBatchNorm2d` in ``module`` normalises ``groups`` objects apart
    (each layer at most once per block); at its end the running statistics of the layers that ran are folded.
    ``cache`` (a dict the caller keeps) holds the gather indices between blocks."""
    norms = [m for m in module.modules() if isinstance(m, ObjectBatchNorm2d)]
    shared: list[_SharedRepeats] = []
    if groups > 1:
        tracked = [m for m in norms if m.training and m.momentum is not None and m.track_running_stats
                   and m.running_mean is not None]
        for momentum in dict.fromkeys(m.momentum for m in tracked):
            shared.append(_SharedRepeats([m for m in tracked if m.momentum == momentum], groups, cache))
    for m in norms:
        m.groups = groups
    try:
        yield
        for s in shared:
            s.fold()
    finally:
        for m in norms:
            m.groups = 1
            m.repeated = None
