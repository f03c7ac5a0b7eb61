"""How ``depthnerf synth`` frames its objects: ``srn`` (SRN's renderer, the default) or ``legacy`` (generator 1).

========================= ============================================== ==========================================
                          ``srn`` (``depthnerf-synth-2``)                ``legacy`` (``depthnerf-synth-1``)
========================= ============================================== ==========================================
object size               unit bounding-box diagonal (cars and chairs)    cars 1.0, chairs 1.35
cameras                   SRN's spiral and upper hemisphere               spiral with view 64 at 65 deg from the front
                          (view 64: the right side, 23 deg up)            (three-quarter), elevation capped at 89 deg
``intrinsics.txt``        ``f = 131.25 R / 128``, ``c = R / 2`` (what    SRN's 128 px intrinsics resized as
                          SRN's Blender renderer writes at ``R`` px)      integer-centred pixels (``c = 64.5 R/128 - 0.5``)
ground-truth pixel (i, j) traced through ``(j + 0.5, i + 0.5)``         through ``(j, i)``
fill (median, train views) cars 0.66, chairs 0.43                        cars 0.67, chairs 0.59
========================= ============================================== ==========================================

Facts and sources: docs/data.md ("Synthetic benchmark framing"). The fill (the longer side of the object's box
over the image side) is what a photo is framed to for a model trained on this data
(:func:`depthnerf.data.photo_framing.category_fill`). A checkpoint's inference spec states the framing of its
training data (``InferenceSpec.framing``); for checkpoints written before that field (the shipped ``cpu-*`` ones,
trained on ``srn`` data), :func:`checkpoint_framing` derives it once, at load, from what they carry.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

from depthnerf.data.cameras import Intrinsics
from depthnerf.data.card import card_path, read_dataset_card
from depthnerf.data.srn import SRN_FOCAL, SRN_IMAGE_SIZE
from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class Framing:
    """One framing of the synthetic benchmark."""

    name: str
    """``srn`` or ``legacy``."""
    generator: str
    """Generator version written into dataset cards and completion markers."""
    chair_diagonal: float
    """Bounding-box diagonal of a normalised chair (cars: always 1.0)."""
    pixel_center: float
    """Ground-truth pixel (row i, column j) is traced through ``(j + c, i + c)`` in the written intrinsics."""
    fills: tuple[tuple[str, float], ...] = ()
    """``(category, fill)``: the fraction of the frame the object's longer mask bounding-box side takes in the
    train images, median over 300 masks of 6 train objects at 128 px (``python scripts/measure_fill.py``)."""

    def fill(self, category: str, default: float) -> float:
        """Training fill of ``category`` (``default`` for a category this framing has no measurement of)."""
        return dict(self.fills).get(category, default)

    def file_intrinsics(self, resolution: int) -> Intrinsics:
        """The intrinsics written to ``intrinsics.txt`` at ``resolution`` x ``resolution`` pixels."""
        if self.name == "legacy":
            return SRN_INTRINSICS.resized(resolution, resolution)
        return Intrinsics(focal=SRN_INTRINSICS.focal * resolution / SRN_INTRINSICS.width, cx=resolution / 2,
                          cy=resolution / 2, height=resolution, width=resolution)

    def render_intrinsics(self, resolution: int) -> Intrinsics:
        """Integer-centred intrinsics of the rays the renderer traces (file intrinsics shifted by the centre)."""
        return self.file_intrinsics(resolution).with_pixel_center(self.pixel_center)


SRN_INTRINSICS = Intrinsics(focal=SRN_FOCAL, cx=SRN_IMAGE_SIZE / 2, cy=SRN_IMAGE_SIZE / 2, height=SRN_IMAGE_SIZE,
                            width=SRN_IMAGE_SIZE)
"""SRN's intrinsics at 128 x 128 (as in its intrinsics files: focal 525/512 * 128, principal point 128 / 2;
:data:`depthnerf.data.srn.SRN_FOCAL`, :data:`~depthnerf.data.srn.SRN_IMAGE_SIZE`)."""
FRAMINGS = {
    "srn": Framing(name="srn", generator="depthnerf-synth-2", chair_diagonal=1.0, pixel_center=0.5,
                   fills=(("cars", 0.66), ("chairs", 0.43))),
    "legacy": Framing(name="legacy", generator="depthnerf-synth-1", chair_diagonal=1.35, pixel_center=0.0,
                      fills=(("cars", 0.67), ("chairs", 0.59))),
}
"""The framings by name."""
DEFAULT_FRAMING = "srn"
"""Framing of ``depthnerf synth`` unless ``--framing`` says otherwise."""
LEGACY_FRAMING = "legacy"
"""Framing of datasets whose card predates the ``framing`` field (generator ``depthnerf-synth-1``)."""


def get_framing(name: str, where: str = "synth") -> Framing:
    """The framing called ``name`` (an error naming ``where`` it was read and the choices otherwise)."""
    if name not in FRAMINGS:
        raise DepthnerfError(f"{where}: unknown framing {name!r} (expected one of {', '.join(FRAMINGS)})")
    return FRAMINGS[name]


def card_framing(card: dict) -> str:
    """Framing of a dataset card: its ``framing`` field, or ``legacy`` for cards written before it existed."""
    return str(card.get("framing", LEGACY_FRAMING))


def checkpoint_framing(weights: Path, data_root: str | Path | None, category: str) -> tuple[str, str]:
    """Framing of the synthetic data an older checkpoint (one whose inference spec has no ``framing``) was
    trained on, and where that was read.

    Looked up in order: the checkpoint card next to the weights (``<name>.json``, field ``framing``, as
    ``scripts/export_checkpoint.py`` writes it), then the training data's dataset card
    (:func:`~depthnerf.data.card.read_dataset_card`), else the default framing.
    """
    card = Path(weights).with_suffix(".json")
    if card.is_file():
        try:
            meta = json.loads(card.read_text())
        except (OSError, ValueError) as err:
            raise DepthnerfError(f"{card}: unreadable checkpoint card ({err})") from None
        if isinstance(meta, dict) and "framing" in meta:
            return get_framing(str(meta["framing"]), f"{card} framing").name, str(card)
    if data_root is not None:
        data_card = read_dataset_card(data_root, category)
        if data_card is not None:
            where = str(card_path(data_root, category))
            return get_framing(card_framing(data_card), f"{where} framing").name, where
    return DEFAULT_FRAMING, "default (no checkpoint card or dataset card found)"


def dataset_framing(card: dict | None, where: str = "dataset card") -> str:
    """Framing of a dataset with this card (:func:`~depthnerf.data.card.read_dataset_card`, read from ``where``,
    which an unknown framing's error names): the card's (:func:`card_framing`); a dataset without a card (a real
    SRN download) is SRN's own renders, ``srn``."""
    return DEFAULT_FRAMING if card is None else get_framing(card_framing(card), f"{where} framing").name
