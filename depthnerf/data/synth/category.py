"""What a synthetic category is made with: its camera distance, z-range and object size in a framing
(:class:`CategorySpec`, :func:`category_spec`), for the generator (:mod:`depthnerf.data.synth.generate`) and its
dataset card."""

from __future__ import annotations

from dataclasses import dataclass

from depthnerf.data.srn import CATEGORY_DEFAULTS
from depthnerf.data.synth.framing import DEFAULT_FRAMING, get_framing
from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class CategorySpec:
    """Per-category camera setup and normalisation (SRN values)."""

    radius: float
    """Camera distance from the origin."""
    z_near: float
    """pixelNeRF's near bound (ray distance)."""
    z_far: float
    """pixelNeRF's far bound (ray distance)."""
    diagonal: float
    """Bounding-box diagonal of the normalised objects."""
    framing: str = DEFAULT_FRAMING
    """Framing the cameras follow (``srn`` or ``legacy``)."""


def category_spec(category: str, framing: str = DEFAULT_FRAMING) -> CategorySpec:
    """Camera radius, z-range (the SRN release's, :data:`~depthnerf.data.srn.CATEGORY_DEFAULTS`) and object size
    of ``cars`` or ``chairs`` in ``framing``."""
    fr = get_framing(framing)
    if category not in ("cars", "chairs"):
        raise DepthnerfError(f"synth: unknown category {category!r} (expected cars or chairs)")
    srn = CATEGORY_DEFAULTS[category]
    return CategorySpec(radius=srn.camera_radius, z_near=srn.z_near, z_far=srn.z_far,
                        diagonal=1.0 if category == "cars" else fr.chair_diagonal, framing=fr.name)
