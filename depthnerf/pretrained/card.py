"""The training steps a shipped checkpoint's JSON model card (``<name>.json``, written by
``scripts/export_checkpoint.py``) counts: a warm-started model's card records its source in ``init_from``, and the
steps of the whole chain in ``total_steps``."""

from __future__ import annotations

from typing import Any


def warm_start_steps(card: dict[str, Any]) -> int | None:
    """The steps behind a warm-started model's source, in all: ``init_from.total_steps``, or for a card written
    before that field the source's own ``init_from.step``; None for a model trained from scratch."""
    warm = card.get("init_from") or {}
    behind = warm.get("total_steps", warm.get("step"))
    return None if behind is None else int(behind)


def total_steps(card: dict[str, Any], own_steps: int) -> int:
    """The steps behind the weights in all: the card's ``total_steps``, else ``own_steps`` (the run's own) plus
    :func:`warm_start_steps`."""
    if card.get("total_steps") is not None:
        return int(card["total_steps"])
    return own_steps + (warm_start_steps(card) or 0)
