"""Random draws of the renderer from one generator, or from one generator per batch row.

Training renders B objects in one batch but draws each object's jitter and noise from that object's own generator
(seeded from ``(seed, step, item)``, see ``depthnerf.train.batching``). Row ``b`` of a draw of shape
``(B, ...)`` then holds exactly the numbers a batch of one would get from generator ``b``: the result of a step
does not depend on which other objects share its batch or its rank (DDP), and a batched step equals the
per-object one up to float rounding.
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

Generators = torch.Generator | Sequence[torch.Generator] | None
"""None (global RNG), one generator, or one generator per batch row (dimension 0 of every draw)."""


def _draw(fn, shape: tuple[int, ...], generator: Generators, dtype: torch.dtype, device: torch.device) -> Tensor:
    if generator is None or isinstance(generator, torch.Generator):
        return fn(shape, generator=generator, dtype=dtype, device=device)
    if len(shape) == 0 or shape[0] != len(generator):
        raise ValueError(f"{len(generator)} row generators for a draw of shape {tuple(shape)}")
    if len(generator) == 1:
        return fn(shape, generator=generator[0], dtype=dtype, device=device)
    return torch.stack([fn(shape[1:], generator=g, dtype=dtype, device=device) for g in generator])


def uniform(shape: tuple[int, ...], generator: Generators, *, dtype: torch.dtype, device: torch.device) -> Tensor:
    """U[0, 1) variates of ``shape``."""
    return _draw(torch.rand, tuple(shape), generator, dtype, device)


def normal(shape: tuple[int, ...], generator: Generators, *, dtype: torch.dtype, device: torch.device) -> Tensor:
    """N(0, 1) variates of ``shape``."""
    return _draw(torch.randn, tuple(shape), generator, dtype, device)
