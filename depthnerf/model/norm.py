"""BatchNorm with per-object statistics, so B objects can be encoded in one batch as if one at a time.

In training mode ``nn.BatchNorm2d`` normalises with the statistics of its whole input batch. pixelNeRF encodes
all objects of a step together, so each object's features depend on the other objects in its batch (and, under
DDP without SyncBatchNorm, on how the batch was split across ranks). This package normalises each object's
source views with their own statistics (for one source view: that image's per-channel mean and variance), as if
each object were encoded alone. That keeps a step's result independent of batch composition and rank count
(2 ranks x 2 objects = 1 process x 4 objects, CPU and CUDA) while the encoder still runs once per step.

:class:`ObjectBatchNorm2d` is a drop-in ``nn.BatchNorm2d`` (same parameters, buffers and state-dict keys). Its
``groups`` attribute (set by :func:`object_groups` for the duration of one encoder call) splits the batch into
``groups`` equal consecutive parts with their own statistics; the running statistics are updated as ``groups``
successive BatchNorm calls would update them (up to float rounding). Evaluation mode is plain BatchNorm.
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
        # [g*v, C, H, W] -> [v, g*C, H, W]: BatchNorm over (v, H, W) for each (object, channel)
        grouped = x.reshape(g, v, c, h, w).transpose(0, 1).reshape(v, g * c, h, w)
        track = self.track_running_stats and self.running_mean is not None
        running_mean = self.running_mean.repeat(g) if track else None
        running_var = self.running_var.repeat(g) if track else None
        momentum = self.momentum
        y = F.batch_norm(grouped, running_mean, running_var, self.weight.repeat(g) if self.affine else None,
                         self.bias.repeat(g) if self.affine else None, True, momentum, self.eps)
        if track:
            self._fold_running_stats(running_mean.reshape(g, c), running_var.reshape(g, c), momentum)
        return y.reshape(v, g, c, h, w).transpose(0, 1).reshape(n, c, h, w)

    @torch.no_grad()
    def _fold_running_stats(self, mean_slots: Tensor, var_slots: Tensor, m: float) -> None:
        """Slot ``k`` holds ``(1 - m) r0 + m s_k``; ``g`` successive updates give
        ``(1 - m)^g r0 + sum_k (1 - m)^(g - k) m s_k`` (k = 1..g)."""
        g = mean_slots.shape[0]
        decay = (1.0 - m) ** torch.arange(g - 1, -1, -1, dtype=mean_slots.dtype, device=mean_slots.device)
        for buf, slots in ((self.running_mean, mean_slots), (self.running_var, var_slots)):
            contrib = slots - (1.0 - m) * buf
            buf.mul_((1.0 - m) ** g).add_((decay[:, None] * contrib).sum(0))
        self.num_batches_tracked.add_(g)  # F.batch_norm does not count; g BatchNorm calls would add g


@contextlib.contextmanager
def object_groups(module: nn.Module, groups: int) -> Iterator[None]:
    """Within the block, every :class:`ObjectBatchNorm2d` in ``module`` normalises ``groups`` objects apart."""
    norms = [m for m in module.modules() if isinstance(m, ObjectBatchNorm2d)]
    for m in norms:
        m.groups = groups
    try:
        yield
    finally:
        for m in norms:
            m.groups = 1
