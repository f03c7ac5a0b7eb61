"""A dataset's card, ``<root>/<category>_card.json``: what the dataset's maker states about its data.

``depthnerf synth`` writes one per category (generator, framing, cameras, counts, ...;
:func:`depthnerf.data.synth.generate.build_card`); real SRN downloads have none. Every reader goes through
:func:`read_dataset_card`, so a card is read one way everywhere: no file is None, and a file that is not a JSON
object is an error naming it.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from depthnerf.errors import DepthnerfError
from depthnerf.files import read_json_object

INTEGER_CENTRED = 0.0
"""Pixel centre of a dataset whose card does not state one (no card, or a card older than the field): pixel
(i, j) at (j, i), as pixelNeRF reads SRN."""


def card_path(root: str | Path, category: str) -> Path:
    """Where the card of ``category`` under ``root`` lives (whether or not it exists)."""
    return Path(root) / f"{category}_card.json"


def read_dataset_card(root: str | Path, category: str) -> dict[str, Any] | None:
    """The parsed card of ``category`` under ``root``; None when there is none. A card that cannot be read, is
    not JSON or is not a JSON object is a :class:`~depthnerf.errors.DepthnerfError` naming the file, and so is
    a stated ``camera.pixel_center`` that is not a number in [0, 1]."""
    path = card_path(root, category)
    if not path.is_file():
        return None
    card = read_json_object(path, "dataset card")
    camera = card.get("camera")
    stated = camera.get("pixel_center") if isinstance(camera, dict) else None
    if stated is not None and not (isinstance(stated, (int, float)) and not isinstance(stated, bool)
                                   and 0 <= stated <= 1):  # NaN fails too
        raise DepthnerfError(f"{path}: camera.pixel_center must be a number in [0, 1] (the pixel centre of the "
                             f"dataset's images), got {stated!r}")
    return card


def card_pixel_center(card: dict[str, Any] | None) -> float:
    """The pixel-centre convention a card states (``camera.pixel_center``), else :data:`INTEGER_CENTRED`."""
    camera = (card or {}).get("camera")
    if isinstance(camera, dict) and camera.get("pixel_center") is not None:
        return float(camera["pixel_center"])
    return INTEGER_CENTRED


def dataset_pixel_center(root: str | Path, category: str) -> float:
    """The pixel-centre convention of a dataset's files as its card states it (:func:`card_pixel_center`)."""
    return card_pixel_center(read_dataset_card(root, category))
