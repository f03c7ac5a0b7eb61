"""BatchNorm with per-object statistics, so B objects can be encoded in one batch as if one at a time.

In training mode ``nn.BatchNorm2d`` normalises with the statistics of its whole input batch. pixelNeRF encodes
all objects of a step together, so each object's features depend on the other objects in its batch (and, under
DDP without SyncBatchNorm, on how the batch was split across ranks). This package normalises each object's
source views with their own statistics (for one source view: that image's per-channel mean and variance), as if
each object were encoded alone. That keeps a step's result independent of batch composition and rank count
(2 ranks x 2 objects = 1 process x 4 objects, CPU and CUDA) while the encoder still runs once per step.

:class:`ObjectBatchNorm2d` is a drop-in ``nn.BatchNorm2d`` (same parameters, buffers and state-dict keys) whose
forward takes the grouping as an argument: an :class:`ObjectGroups` plan, built by :func:`object_groups` once per
encoder call and passed down through the encoder's forward (nothing is set on the layers). With a plan of
``count`` objects, a training-mode layer splits its batch into ``count`` equal consecutive parts with their own
statistics: one ``batch_norm`` call over the batch viewed as ``[V, count * C, H, W]``, with the affine parameters
and running statistics repeated per object. After the encoder ran, :meth:`ObjectGroups.fold` updates the running
statistics as ``count`` successive BatchNorm calls would (up to float rounding). Without a plan, with one object,
or in evaluation mode the layer is plain BatchNorm, unless the plan asks for ``image_stats``: then an
evaluation-mode layer normalises each object with its own statistics too, exactly as training did, and leaves its
running statistics alone (the inference choice ``encoder_norm="image"`` of :meth:`PixelNeRF.encode`).

Few operators per layer (each one a kernel launch on a GPU): the plan repeats the affine parameters and running
statistics of ALL its layers at once (a concatenation and one gather each), and folds the per-object running
statistics of all of them in one pass.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from torch import Tensor, nn

Repeated = tuple[Tensor | None, Tensor | None, Tensor, Tensor]
"""One layer's weight, bias, running mean and running variance repeated per object (``[count * C]`` each; the
affine ones None when a layer of its plan is not affine)."""


class ObjectBatchNorm2d(nn.BatchNorm2d):
    """``nn.BatchNorm2d`` whose training-mode statistics are per group of consecutive samples (per object)."""

    def forward(self, x: Tensor, groups: ObjectGroups | None = None) -> Tensor:
        """Normalise ``x`` (``[count * V, C, H, W]``); ``groups``: the plan of the encoder call (None: plain)."""
        if groups is not None and groups.image_stats and not self.training:
            return self._image_stats(x, groups.count)
        if groups is None or groups.count <= 1 or not self.training:
            return super().forward(x)
        g = groups.count
        n, c, h, w = x.shape
        if n % g:
            raise ValueError(f"ObjectBatchNorm2d: batch of {n} does not split into {g} objects")
        v = n // g
        if self.momentum is None:  # cumulative averaging: g successive calls, exactly
            return torch.cat([super(ObjectBatchNorm2d, self).forward(part) for part in x.split(v)])
        if self.track_running_stats and self.running_mean is not None:
            weight, bias, running_mean, running_var = groups.take(self)
        else:
            weight, bias, running_mean, running_var = None, None, None, None
        if weight is None and self.affine:  # a layer outside the plan's shared repeats
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


    def _image_stats(self, x: Tensor, g: int) -> Tensor:
        """Each object's samples normalised with their own statistics (as in training), running statistics
        neither read nor updated."""
        n, c, h, w = x.shape
        if n % g:
            raise ValueError(f"ObjectBatchNorm2d: batch of {n} does not split into {g} objects")
        v = n // g
        weight = None if self.weight is None else self.weight.repeat(g)
        bias = None if self.bias is None else self.bias.repeat(g)
        grouped = x.reshape(g, v, c, h, w).transpose(0, 1).reshape(v, g * c, h, w)
        y = F.batch_norm(grouped, None, None, weight, bias, True, 0.0, self.eps)
        return y.reshape(v, g, c, h, w).transpose(0, 1).reshape(n, c, h, w)


def _repeat_index(sizes: list[int], groups: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """For vectors of ``sizes`` concatenated into one: the gather index laying each vector out ``groups`` times
    in a row (``[groups * size]`` blocks, copy ``k`` at ``k * size``), and the index that reads such blocks back
    as ``[groups, sum(sizes)]`` (row ``k`` = copy ``k`` of every vector). Computed on the host (numpy, no
    kernel) eagerly, with :func:`_repeat_index_traced` under ``torch.compile``."""
    if torch.compiler.is_compiling():
        return _repeat_index_traced(sizes, groups, device)
    size = np.asarray(sizes, dtype=np.int64)
    start = np.cumsum(size) - size  # of each vector in the input; its copies start at groups * start
    block = np.repeat(np.arange(len(size)), groups * size)  # the vector of each output element
    offset = np.arange(groups * int(size.sum())) - groups * start[block]  # k * size + c for copy k, element c
    out = start[block] + offset % size[block]
    element = np.arange(int(size.sum())) - np.repeat(start, size)  # c, for each input element
    back = (np.repeat(groups * start, size) + element)[None] + np.arange(groups)[:, None] * np.repeat(size, size)
    return torch.from_numpy(out).to(device), torch.from_numpy(back).to(device)


def _repeat_index_traced(sizes: list[int], groups: int, device: torch.device) -> tuple[Tensor, Tensor]:
    """:func:`_repeat_index` in tensor operations of static shapes (the numpy one breaks a compiled graph into
    pieces): output position ``p`` belongs to vector ``j``, whose copies start at ``groups * start_j``, and reads
    its element ``(p - groups * start_j) mod size_j``."""
    size = torch.tensor(sizes, dtype=torch.int64, device=device)
    start = torch.cumsum(size, 0) - size
    total = sum(sizes)
    p = torch.arange(groups * total, device=device)
    j = torch.searchsorted(groups * start, p, right=True) - 1
    out = start[j] + (p - groups * start[j]) % size[j]
    c = torch.arange(total, device=device)
    jc = torch.searchsorted(start, c, right=True) - 1
    back = (groups * start[jc] + c - start[jc])[None] + torch.arange(groups, device=device)[:, None] * size[jc]
    return out, back


class SharedRepeats:
    """The repeated parameters and running statistics of the tracked layers of one plan with one momentum."""

    def __init__(self, norms: list[ObjectBatchNorm2d], groups: int) -> None:
        self.norms = norms
        """The layers (one momentum)."""
        self.groups = groups
        """Number of objects."""
        device = norms[0].running_mean.device
        sizes = [m.num_features for m in norms]
        # one index serves [means, vars] and [weights, biases]: the gather into the repeated layout, and back
        self.index, self.back = _repeat_index(sizes + sizes, groups, device)
        self.sizes = [groups * s for s in sizes]
        """Repeated length of each layer's vectors."""
        with torch.no_grad():
            self.stats = torch.cat([m.running_mean for m in norms] + [m.running_var for m in norms])
            """Every layer's running means then running variances, before the call."""
            self.slots = self.stats[self.index]
            """The repeated running statistics, updated in place by the layers' calls (through views)."""
        stat_slots = self.slots.split(self.sizes + self.sizes)
        params: list = [None] * (2 * len(norms))
        if all(m.affine for m in norms):
            params = torch.cat([m.weight for m in norms] + [m.bias for m in norms])[self.index].split(
                self.sizes + self.sizes)
        layers = len(norms)
        self.pending: dict[ObjectBatchNorm2d, Repeated] = {
            m: (params[i], params[layers + i], stat_slots[i], stat_slots[layers + i]) for i, m in enumerate(norms)}
        """Each layer's repeated tensors until the layer takes them (once)."""

    def fold(self) -> None:
        """Fold each layer's ``groups`` running-statistic slots into its buffers: slot ``k`` holds
        ``(1 - m) r0 + m s_k``; ``g`` successive updates give ``(1 - m)^g r0 + sum_k (1 - m)^(g - k) m s_k``."""
        if self.pending:
            raise RuntimeError(f"ObjectGroups: {len(self.pending)} planned layer(s) did not run before the fold")
        with torch.no_grad():  # a block, not the decorator: torch.compile traces a decorated method in pieces
            self._fold()

    def _fold(self) -> None:
        g, m = self.groups, self.norms[0].momentum
        slots = self.slots[self.back]  # [g, 2 * sum(C)]
        decay = (1.0 - m) ** torch.arange(g - 1, -1, -1, dtype=slots.dtype, device=slots.device)
        contrib = slots - (1.0 - m) * self.stats
        new = (self.stats * (1.0 - m) ** g + (decay[:, None] * contrib).sum(0)).split(
            [s // g for s in self.sizes] * 2)
        buffers = [n.running_mean for n in self.norms] + [n.running_var for n in self.norms]
        torch._foreach_copy_(buffers, list(new))
        torch._foreach_add_([n.num_batches_tracked for n in self.norms], g)


@dataclass
class ObjectGroups:
    """The per-object BatchNorm plan of one encoder call (:func:`object_groups`): given to every
    :class:`ObjectBatchNorm2d` the call runs, each of which takes its repeated tensors once; :meth:`fold` after
    the call updates the running statistics."""

    count: int
    """Objects in the batch: each is ``batch / count`` consecutive samples."""
    shared: list[SharedRepeats]
    """The repeated tensors of the plan's tracked training-mode layers, one entry per momentum value."""
    image_stats: bool = False
    """Evaluation-mode layers also normalise each object with its own statistics (module docstring)."""

    def take(self, layer: ObjectBatchNorm2d) -> Repeated:
        """``layer``'s repeated weight, bias, running mean and running variance (once per plan)."""
        for s in self.shared:
            if layer in s.pending:
                return s.pending.pop(layer)
            if any(layer is m for m in s.norms):
                raise RuntimeError("ObjectBatchNorm2d: called twice with one ObjectGroups plan")
        raise RuntimeError("ObjectBatchNorm2d: a training-mode layer outside its ObjectGroups plan")

    def fold(self) -> None:
        """Fold the per-object running statistics of the plan's layers into their buffers (every planned layer
        must have run exactly once)."""
        for s in self.shared:
            s.fold()


def object_groups(module: nn.Module, count: int, image_stats: bool = False) -> ObjectGroups:
    """The plan for one call of ``module`` on a batch of ``count`` objects: the training-mode
    :class:`ObjectBatchNorm2d` layers in ``module`` that track running statistics with a momentum share repeated
    tensors (one :class:`SharedRepeats` per momentum value); every one of them must run once in the call."""
    shared: list[SharedRepeats] = []
    if count > 1:
        tracked = [m for m in module.modules() if isinstance(m, ObjectBatchNorm2d) and m.training
                   and m.momentum is not None and m.track_running_stats and m.running_mean is not None]
        for momentum in dict.fromkeys(m.momentum for m in tracked):
            shared.append(SharedRepeats([m for m in tracked if m.momentum == momentum], count))
    return ObjectGroups(count=count, shared=shared, image_stats=image_stats)
