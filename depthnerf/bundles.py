"""The base of every typed tensor bundle, and the radiance-field callable type (both defined once, here).

A bundle is a dataclass whose fields are tensors with a shared leading layout (e.g. ``B R ...`` for rays, ``N H W``
for views), ``None`` (an absent optional tensor), nested bundles, or plain values (shared metadata such as an
image size). :class:`TensorBundle` gives every such dataclass the same four operations, written once:

- :meth:`~TensorBundle.map`: apply a function to every tensor (recursing into nested bundles; ``None`` and plain
  values are kept);
- :meth:`~TensorBundle.to`: device/dtype moves;
- :meth:`~TensorBundle.slice` / :meth:`~TensorBundle.gather`: select along one axis by a range or, per batch
  row, by an index tensor ``[B, G]`` (trailing axes follow);
- :meth:`~TensorBundle.cat`: concatenate bundles along one axis (plain values are taken from the first part).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from typing import Any, TypeVar

import torch
from jaxtyping import Float, Int
from torch import Tensor

FieldFn = Callable[[Float[Tensor, "B R S 3"], Float[Tensor, "B R 3"]],
                   tuple[Float[Tensor, "B R S 3"], Float[Tensor, "B R S"]]]
"""A radiance field: (world points, unit world view directions) -> (rgb in [0, 1], density >= 0)."""

B = TypeVar("B", bound="TensorBundle")


def _apply(value: Any, fn: Callable[[Tensor], Tensor]) -> Any:
    if isinstance(value, Tensor):
        return fn(value)
    if isinstance(value, TensorBundle):
        return value.map(fn)
    return value


class TensorBundle:
    """Mixin for dataclasses of tensors (see the module docstring)."""

    def _fields(self) -> dict[str, Any]:
        return {f.name: getattr(self, f.name) for f in dataclasses.fields(self)}  # type: ignore[arg-type]

    def map(self: B, fn: Callable[[Tensor], Tensor]) -> B:
        """A bundle of the same type with ``fn`` applied to every tensor."""
        return type(self)(**{k: _apply(v, fn) for k, v in self._fields().items()})

    def to(self: B, *args: Any, **kwargs: Any) -> B:
        """Every tensor ``.to(*args, **kwargs)`` (device and/or dtype)."""
        return self.map(lambda x: x.to(*args, **kwargs))

    def slice(self: B, start: int, stop: int, dim: int = 1) -> B:
        """Entries ``start:stop`` along ``dim`` of every tensor (default: the ray axis of ``[B, R, ...]``)."""
        return self.map(lambda x: x.narrow(dim, start, max(0, min(stop, x.shape[dim]) - start)))

    def gather(self: B, idx: Int[Tensor, "B G"]) -> B:
        """Per batch row ``b``, entries ``idx[b]`` along axis 1 of every tensor (trailing axes follow)."""
        def pick(x: Tensor) -> Tensor:
            full = idx.reshape(*idx.shape, *([1] * (x.ndim - 2))).expand(*idx.shape, *x.shape[2:])
            return torch.gather(x, 1, full)
        return self.map(pick)

    @classmethod
    def cat(cls: type[B], parts: Sequence[B], dim: int = 0) -> B:
        """Concatenate bundles along ``dim`` (``None`` fields stay ``None``; plain values from the first part)."""
        if not parts:
            raise ValueError(f"{cls.__name__}.cat needs at least one part")
        first = parts[0]._fields()
        out = {}
        for name, value in first.items():
            values = [getattr(p, name) for p in parts]
            if isinstance(value, Tensor):
                out[name] = torch.cat(values, dim=dim)
            elif isinstance(value, TensorBundle):
                out[name] = type(value).cat(values, dim=dim)
            else:
                out[name] = value
        return cls(**out)
