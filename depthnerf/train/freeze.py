"""Parameters held fixed in training (``--schedule.freeze``).

A prefix names parameters by their qualified names in :class:`~depthnerf.model.pixelnerf.PixelNeRF` at a dot
boundary: ``encoder`` holds ``encoder.trunk.*`` and ``encoder.depth.*`` (pixelNeRF's ``--freeze_enc``),
``fine.lin_out`` the fine network's output layer, ``encoder.trunk.layer3.0.bn1.weight`` one tensor. A frozen
parameter gets no gradient and is not in the optimizer. A module whose parameters are all frozen also runs in
evaluation mode, so a frozen BatchNorm layer normalises with its running statistics and never updates them: a
frozen encoder gives training exactly the features evaluation gives, and its weights and statistics leave the run
as they came in.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import nn

from depthnerf.errors import DepthnerfError


def _under(name: str, prefix: str) -> bool:
    return name == prefix or name.startswith(prefix + ".")


def freeze_parameters(model: nn.Module, prefixes: Sequence[str]) -> list[str]:
    """Set ``requires_grad`` False on every parameter of ``model`` under one of ``prefixes``; the frozen names.

    One line (:class:`DepthnerfError`) for a prefix under which no parameter lies, or when no parameter is left
    to train, before any parameter is changed."""
    names = [name for name, _ in model.named_parameters()]
    for prefix in prefixes:
        if not any(_under(name, prefix) for name in names):
            tops = sorted({name.split(".")[0] for name in names})
            raise DepthnerfError(f"--schedule.freeze: {prefix!r} names no parameter of this model (names start with "
                                 f"{', '.join(tops)}; e.g. encoder, fine.lin_out)")
    frozen = [name for name in names if any(_under(name, prefix) for prefix in prefixes)]
    if frozen and len(frozen) == len(names):
        raise DepthnerfError(f"--schedule.freeze {','.join(prefixes)} freezes every parameter: nothing would train")
    held = set(frozen)
    for name, param in model.named_parameters():
        if name in held:
            param.requires_grad_(False)
    return frozen


def hold_frozen_modules(model: nn.Module) -> int:
    """Put every module of ``model`` whose parameters (its own and its children's, at least one) are all frozen in
    evaluation mode; call after each ``model.train()``. Returns how many modules it switched."""
    switched = 0
    for module in model.modules():
        params = list(module.parameters())
        if params and not any(p.requires_grad for p in params) and module.training:
            module.train(False)
            switched += 1
    return switched


def trainable_parameters(model: nn.Module) -> list[nn.Parameter]:
    """The parameters the optimizer updates, in ``model.parameters()`` order (so a resumed run with the same
    ``--schedule.freeze`` maps the saved optimizer state onto the same tensors)."""
    return [p for p in model.parameters() if p.requires_grad]
