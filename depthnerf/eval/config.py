"""What ``depthnerf eval`` runs: :class:`ProtocolConfig`, and the :class:`ProtocolChoices` that move published
numbers, each selectable and recorded in ``summary.json`` (``protocol_choices``). The defaults are pixelNeRF's.

SSIM (``--ssim``, :data:`~depthnerf.eval.metrics.SSIM_WINDOWS`)
    ``uniform7`` (default): pixelNeRF's ``skimage.measure.compare_ssim(..., multichannel=True, data_range=1)``,
    i.e. a 7x7 uniform window with sample covariance. ``gaussian11``: an 11x11 Gaussian window, sigma 1.5,
    population covariance, border left out (Wang et al. 2004; scikit-image ``gaussian_weights=True, sigma=1.5,
    use_sample_covariance=False``). ``gaussian11-zeropad``: the same window over the zero-padded image, every
    pixel averaged: the ``ssim()`` that Splatter Image's ``eval.py`` imports from 3D Gaussian Splatting. The two
    Gaussian spellings differ only through the 5-pixel border.

Scored precision (``--scored``; ``--quantize`` is ``--scored png8``)
    ``png8`` (default): the render as the 8-bit PNG pixelNeRF's ``eval/eval.py`` writes, ``(x * 255)
    .astype(uint8)`` of the clamped render (truncation). pixelNeRF's README: eval.py "computes PSNR and SSIM
    without quantization. The final metrics we report in the paper use the rendered images saved to disk"
    (``eval/calc_metrics.py``). ``float``: the clamped float render, as eval.py prints (and Splatter Image scores).
    The ground truth is the dataset image as read either way: 8-bit values at the dataset's own resolution, the
    area-resized float image at another ``--resolution``.

Objects (``--objects``)
    ``pixelnerf`` (default): leave out the objects pixelNeRF's evaluation cannot load
    (:data:`PIXELNERF_UNLOADABLE`). The SRN cars test object ``876d92ce6a0e4bf399588eee976baae`` shows no car
    (white images); pixelNeRF's ``src/data/SRNDataset.py`` raises ``RuntimeError("ERROR: Bad image at", ...)``
    on a view without a pixel that is non-white in all three channels (for this object at ``rgb/000001.png``),
    so its ``eval.py`` stops there and numbers made with its code exclude the object. ``all``: score every
    object (Splatter Image's SRN loader has no such check and keeps it). The object is left out by its id,
    whatever its images; the summary lists the ids actually left out (``skipped_objects``).

``depthnerf compare`` refuses summaries whose choices differ (:func:`protocol_mismatch`); a summary written before
the choices were recorded scored with ``uniform7`` (the only SSIM then), at the precision its ``metrics_path``
names, and left no object out.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path

from depthnerf.data.protocol import check_input_views
from depthnerf.errors import DepthnerfError
from depthnerf.eval.geometry_metrics import GeometryConfig
from depthnerf.eval.metrics import SSIM_WINDOW_SIDE, SSIM_WINDOWS, LpipsConfig
from depthnerf.render.mesh import check_mesh_resolution
from depthnerf.render.mesh_level import AUTO_LEVEL

SCORED = {"png8": "8-bit PNG renders, truncated as pixelNeRF's eval.py writes them (its paper numbers, "
                  "calc_metrics.py)",
          "float": "float renders clamped to [0, 1] (the numbers pixelNeRF's eval.py prints)"}
"""Precision the renders are scored at (``--scored``)."""
OBJECTS = {"pixelnerf": "objects pixelNeRF's evaluation cannot load are left out",
           "all": "every object of the split is scored"}
"""Which objects are scored (``--objects``)."""
PIXELNERF_UNLOADABLE = {
    "876d92ce6a0e4bf399588eee976baae": "SRN cars test object without a car in its images; pixelNeRF's "
                                        "SRNDataset raises 'Bad image' on it",
}
"""Objects pixelNeRF's evaluation cannot load (id -> why), left out under ``--objects pixelnerf``."""
METRICS_PATH = {"png8": "quantized 8-bit renders (calc_metrics.py)", "float": "float renders (eval.py)"}
"""``summary.json`` ``metrics_path`` text of each scored precision."""
LEGACY_METRICS_PATH = {text: scored for scored, text in METRICS_PATH.items()}
"""``summary.json`` ``metrics_path`` text -> scored precision (summaries without ``protocol_choices``)."""


@dataclass(frozen=True)
class ProtocolChoices:
    """The evaluation choices that move published numbers (module docstring); defaults are pixelNeRF's."""

    ssim: str = "uniform7"
    """SSIM variant, a key of :data:`~depthnerf.eval.metrics.SSIM_WINDOWS`."""
    scored: str = "png8"
    """Precision of the scored renders, a key of :data:`SCORED`."""
    objects: str = "pixelnerf"
    """Which objects are scored, a key of :data:`OBJECTS`."""

    def check(self) -> ProtocolChoices:
        """Self, or a one-line :class:`DepthnerfError` naming the flag with an unknown value."""
        for flag, value, known in (("--ssim", self.ssim, SSIM_WINDOWS), ("--scored", self.scored, SCORED),
                                   ("--objects", self.objects, OBJECTS)):
            if value not in known:
                raise DepthnerfError(f"{flag} {value!r}: choose one of {', '.join(known)}")
        return self

    @property
    def is_pixelnerf(self) -> bool:
        """True when every choice is pixelNeRF's."""
        return self == ProtocolChoices()

    def skips(self, object_id: str) -> bool:
        """Whether the object is left out under these choices."""
        return self.objects == "pixelnerf" and object_id in PIXELNERF_UNLOADABLE

    def record(self, skipped: Sequence[str]) -> dict:
        """``summary.json`` ``protocol_choices``: the choices, what they mean, and the ids actually left out."""
        return {"ssim": self.ssim, "ssim_window": SSIM_WINDOWS[self.ssim], "scored": self.scored,
                "scored_detail": SCORED[self.scored], "objects": self.objects,
                "objects_detail": OBJECTS[self.objects],
                "skipped_objects": list(skipped),
                "skipped_reasons": {i: PIXELNERF_UNLOADABLE[i] for i in skipped if i in PIXELNERF_UNLOADABLE},
                "pixelnerf_defaults": self.is_pixelnerf}


@dataclass(frozen=True)
class ProtocolConfig:
    """What ``depthnerf eval`` evaluates and how (how the checkpoint runs, its prior, pixel centre, device policy,
    chunk and guided sampling, is the session's: :class:`~depthnerf.infer.session.SessionOptions`)."""

    split: str = "test"
    """Split folder suffix (``<category>_<split>``)."""
    category: str | None = None
    """Category folder prefix; None = the checkpoint's training category."""
    views_stride: int = 1
    """Score every K-th target view (1 = all 250)."""
    input_views: tuple[int, ...] | None = None
    """The views each object is conditioned on, the first the primary one (``--input-views 64 104``: pixelNeRF's
    two-view protocol); every other view is a target. None: the SRN protocol's single view 64 (view 0 for objects
    with at most 64 views)."""
    max_objects: int | None = None
    """Evaluate only the first N objects (sorted by id, after the ones ``choices`` leave out); None = all."""
    resolution: int | None = None
    """Render/score resolution; None = the checkpoint's training resolution (:mod:`depthnerf.eval.protocol`)."""
    mesh: bool = True
    """Extract a mesh per object and score it against ``mesh.ply`` when the object has one."""
    mesh_resolution: int = 128
    """Marching-cubes samples along the longest side of the frustum box."""
    mesh_threshold: float | str = AUTO_LEVEL
    """Density level of the extracted surface, or ``"auto"`` (per object, see :mod:`depthnerf.render.mesh`)."""
    geometry: GeometryConfig = field(default_factory=GeometryConfig)
    """Chamfer / F-score settings."""
    save_renders: bool = False
    """Write rendered PNGs, predicted meshes and ``renders.csv``."""
    choices: ProtocolChoices = field(default_factory=ProtocolChoices)
    """SSIM variant, scored precision and left-out objects (module docstring; defaults are pixelNeRF's)."""
    method: str | None = None
    """Row label for ``depthnerf compare``; None = from the depth prior."""
    lpips: LpipsConfig = field(default_factory=LpipsConfig)
    """Where LPIPS weights are looked for (never downloaded)."""
    progress: bool = True
    """Progress bar over objects (stderr)."""
    overwrite: bool = False
    """Discard the finished objects of an earlier evaluation in the output folder instead of resuming it (an
    evaluation with other settings there is refused without it)."""

    def __post_init__(self) -> None:
        """One line naming the ``depthnerf eval`` flag when a value cannot work (checked before anything loads)."""
        for flag, value, least in (("--views-stride", self.views_stride, 1), ("--max-objects", self.max_objects, 1)):
            if value is not None and value < least:
                raise DepthnerfError(f"{flag} must be >= {least}, got {value}")
        check_mesh_resolution(self.mesh_resolution, none_allowed=False)
        if self.input_views is not None:
            object.__setattr__(self, "input_views", check_input_views(self.input_views))
        if self.resolution is not None:
            side = max(8, SSIM_WINDOW_SIDE.get(self.choices.ssim, 8))
            if self.resolution < side:
                raise DepthnerfError(f"--resolution must be >= {side} (SSIM {self.choices.ssim}), got "
                                     f"{self.resolution}")


@dataclass(frozen=True)
class RecordedChoices:
    """The protocol choices a ``summary.json`` was made with (None = not recorded), for ``depthnerf compare``."""

    path: Path
    """The summary file."""
    category: str
    """Its category."""
    ssim: str | None
    """SSIM variant."""
    scored: str | None
    """Scored precision."""
    skipped: tuple[str, ...]
    """Object ids it left out."""
    scored_ids: frozenset[str] | None
    """Object ids it scored (its ``per_object`` list), None when not listed."""


def recorded_choices(path: Path, data: dict) -> RecordedChoices:
    """The choices of a loaded ``summary.json`` (module docstring for summaries without ``protocol_choices``)."""
    rec = data.get("protocol_choices")
    per_object = data.get("per_object")
    ids = None
    if isinstance(per_object, list):
        ids = frozenset(str(o.get("object_id")) for o in per_object if isinstance(o, dict))
    category = str(data.get("category", "")).strip().lower()
    if isinstance(rec, dict):
        skipped = rec.get("skipped_objects") or []
        if not isinstance(skipped, list):
            raise DepthnerfError(f"{path}: 'protocol_choices.skipped_objects' must be a list, got {skipped!r}")
        return RecordedChoices(path, category, rec.get("ssim"), rec.get("scored"), tuple(map(str, skipped)), ids)
    scored = LEGACY_METRICS_PATH.get(data.get("metrics_path"))
    return RecordedChoices(path, category, "uniform7" if scored else None, scored, (), ids)


def protocol_mismatch(summaries: Sequence[RecordedChoices]) -> str | None:
    """One line saying how two of the summaries were scored differently, or None when they agree (choices a
    summary does not record are not compared; a left-out object matters only where another summary scored it)."""
    for key, flag in (("ssim", "--ssim"), ("scored", "--scored")):
        known = [s for s in summaries if getattr(s, key) is not None]
        for s in known[1:]:
            if getattr(s, key) != getattr(known[0], key):
                return (f"{s.path} was scored with {flag} {getattr(s, key)} but {known[0].path} with {flag} "
                        f"{getattr(known[0], key)}")
    for a in summaries:
        for b in summaries:
            both = set(a.skipped) & (b.scored_ids or frozenset())
            if a.category == b.category and both:
                return (f"{a.path} left out object {sorted(both)[0]} (--objects pixelnerf) but {b.path} scored it "
                        "(--objects all)")
    return None
