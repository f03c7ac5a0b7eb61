"""Fit a checkpoint's facing head (:mod:`depthnerf.model.facing_head`) on dataset views whose plane is known.

For each of ``objects`` objects of a split, ``views_per_object`` views drawn at random (seeded) are encoded one at a
time and paired with the relative angle of the dataset's mirror plane
(:func:`~depthnerf.data.symmetry.relative_facing`). ``inputs`` says how a view is encoded (:data:`INPUTS`): as the
evaluation encodes it (``dataset``: the dataset's framing, the prior from its cache), as ``reconstruct`` encodes a
photo of it (``photo``: recentred and scaled to the model's fill by
:func:`~depthnerf.data.photo_framing.frame_photo`, the prior computed from the framed image), or both ways
(``both``: two rows per view). A head reads the features it was fitted on best: one fitted on dataset views alone
is several degrees looser on photos (docs/RESULTS.md, "Through the photo path the head is looser"). The ridge
weight is chosen on a held-out fifth of the objects
(the smallest median angle error over :data:`LAMBDAS`), then the head is refitted on all of them. The planes must
be vertical and the cameras without roll (as in SRN and the synthetic benchmark).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from depthnerf.data.photo_framing import category_fill, frame_photo, framed_intrinsics, square_crop
from depthnerf.data.srn import ObjectViews, index_split
from depthnerf.data.symmetry import relative_facing
from depthnerf.errors import DepthnerfError
from depthnerf.infer.session import EncodedView, InferenceSession, SessionOptions
from depthnerf.model.facing_head import (
    FacingHead,
    angle_error,
    encoder_fingerprint,
    fit_ridge,
    fit_ridges,
    pool_features,
)
from depthnerf.train.memory import device_memory, readable_bytes

LAMBDAS = (10.0, 100.0, 1000.0, 10000.0)
"""Ridge weights tried on the held-out objects."""
INPUTS = ("dataset", "photo", "both")
"""How a drawn view is encoded (``FacingHeadConfig.inputs``, module docstring)."""
FIT_BYTES_PER_VALUE = 32
"""Peak host bytes per pooled feature value of a fit: the float32 rows (4), the held-out split's float32 copy
(about 3) and :func:`~depthnerf.model.facing_head.fit_ridges`'s float64 copy, centred temporary and standardised
rows (8 each); measured at 31-32 on 2000-16000 rows of 2048-16384 values."""


@dataclass(frozen=True)
class FacingHeadConfig:
    """What :func:`fit_facing_head` fits on."""

    data: Path
    """Dataset root (``<category>_<split>/`` and its prior cache)."""
    category: str
    """Category folder prefix, e.g. ``cars``."""
    split: str = "train"
    """Split to fit on (the training split: the head learns what the network was trained on)."""
    objects: int = 300
    """At most this many objects (the first of the split)."""
    views_per_object: int = 8
    """Views drawn per object (seeded)."""
    grid: int = 4
    """Pooling grid of the head (``grid x grid`` cells per feature channel)."""
    seed: int = 0
    """Seed of the view draw and of the held-out objects."""
    device: str = "cpu"
    """Torch device of the encoder."""
    inputs: str = "both"
    """How each drawn view is encoded, one of :data:`INPUTS` (module docstring); ``both`` reads photos nearly as
    closely as ``photo`` and dataset views nearly as closely as ``dataset`` (docs/RESULTS.md, "A facing head for
    photos")."""

    def __post_init__(self) -> None:
        if self.inputs not in INPUTS:
            raise DepthnerfError(f"--inputs must be one of {', '.join(INPUTS)}, got {self.inputs!r}")


@dataclass(frozen=True)
class FacingHeadFit:
    """A fitted head and how well it did."""

    head: FacingHead
    """The head refitted on every object with the chosen weight."""
    validation: dict[str, dict[str, float]]
    """Per ridge weight tried: median and 90th-percentile absolute angle error (degrees) on the held-out objects."""


def dataset_session(checkpoint: str | Path, cfg: FacingHeadConfig) -> tuple[InferenceSession, list]:
    """A session of ``checkpoint`` reading ``cfg``'s dataset (views, plane; the cached prior for ``dataset`` inputs,
    else the prior computed from each encoded image) and the split's first ``cfg.objects`` records."""
    records = index_split(cfg.data, cfg.category, cfg.split, mesh_body=False).objects[: cfg.objects]
    options = (SessionOptions(device=cfg.device, inputs="dataset", data_root=cfg.data, records=records)
               if cfg.inputs == "dataset" else SessionOptions(device=cfg.device, data_root=cfg.data))
    session = InferenceSession(checkpoint, options)
    if cfg.inputs != "dataset" and session.prior_source.needs_depths:
        raise DepthnerfError(f"{checkpoint}: its prior reads ground-truth depth, which a view framed as a photo has "
                             "not; fit with --inputs dataset")
    return session, records


def drawn_views(records, cfg: FacingHeadConfig) -> list[list[int]]:
    """The views of each record :func:`gather` encodes: ``views_per_object`` of them (all when it has fewer), drawn
    without replacement with ``cfg.seed``, in index order."""
    rng = np.random.default_rng(cfg.seed)
    return [sorted(rng.choice(r.num_views, size=min(cfg.views_per_object, r.num_views), replace=False).tolist())
            for r in records]


def gather(session: InferenceSession, cfg: FacingHeadConfig, records) -> tuple[torch.Tensor, torch.Tensor,
                                                                                 np.ndarray]:
    """``(pooled features [N, D], relative angles [N], object index [N])`` of the drawn views."""
    plane, _ = session.dataset_symmetry(cfg.category)
    if plane is None or not any(plane[:3]):
        raise DepthnerfError(f"{cfg.data}: no mirror plane for {cfg.category} (a facing head needs one)")
    fill = category_fill(session.spec.category, session.framing)
    pooled, psi, owner = [], [], []
    for i, (record, picks) in enumerate(zip(records, drawn_views(records, cfg), strict=True)):
        for view in picks:
            src = session.load_views(record, [view], session.spec.resolution,
                                     with_depth=session.prior_source.needs_depths)
            angle = relative_facing(plane, src.poses[0].double().numpy())
            for encoded in encodings(session, src, cfg.inputs, plane, fill):
                pooled.append(pool_features(encoded.enc.features[0, :1], cfg.grid).cpu())
                psi.append(angle)
                owner.append(i)
    return torch.cat(pooled), torch.tensor(psi, dtype=torch.float64), np.array(owner)


def encodings(session: InferenceSession, src: ObjectViews, inputs: str, plane: Sequence[float], fill: float
              ) -> Iterator[EncodedView]:
    """The first view of ``src`` encoded as ``inputs`` says (module docstring): as it is, and/or framed as a photo
    at ``fill``, with the framed image's own camera (:func:`~depthnerf.data.photo_framing.framed_intrinsics`), so
    that it renders the dataset's other views where they are."""
    if inputs != "photo":
        yield session.encode_views(src, symmetry_plane=plane)
    if inputs != "dataset":
        res, mask = session.spec.resolution, src.masks[0].numpy()
        image, framed_mask = frame_photo(src.images[0].permute(1, 2, 0).numpy(), None, mask, res, "auto", fill, [])
        intr = framed_intrinsics(src.intrinsics, square_crop(mask, "auto", fill), res)
        yield session.encode(torch.from_numpy(image).permute(2, 0, 1)[None].contiguous(),
                             torch.from_numpy(framed_mask)[None], src.poses[0], intr, symmetry_plane=plane)


def check_fit(session: InferenceSession, checkpoint: str | Path, cfg: FacingHeadConfig) -> None:
    """Refuse, before any view is encoded, a fit that means nothing: data of another category than the model's
    (a head learns how the model's objects look from each side), or a pooling grid finer than the encoder's feature
    maps (the cells would repeat feature values; the features grow with ``grid^2``)."""
    trained = session.spec.category
    if cfg.category != trained:
        raise DepthnerfError(f"{checkpoint}: a {trained} model, given {cfg.category} data (--category "
                             f"{cfg.category}); fit its facing head on {trained} views")
    side = session.model.cfg.encoder.feature_side(session.spec.resolution)
    if cfg.grid > side:
        raise DepthnerfError(f"--grid must be <= {side} (the encoder's feature maps are {side} x {side} at the "
                             f"model's resolution {session.spec.resolution}), got {cfg.grid}")


def fit_memory(rows: int, dim: int) -> int:
    """Peak host memory (bytes) of a fit on ``rows`` encoded views of ``dim`` pooled values each:
    :data:`FIT_BYTES_PER_VALUE` a value, plus the float64 Gram matrix and its regularised copy (the smaller of
    ``rows`` and ``dim`` squared)."""
    side = min(rows, dim)
    return rows * dim * FIT_BYTES_PER_VALUE + 2 * side * side * 8


def check_fit_memory(rows: int, dim: int, objects: int, cfg: FacingHeadConfig) -> str:
    """One line sizing the fit on ``objects`` objects (:func:`fit_memory`); refuse, before any view is encoded, a
    fit that needs more than all of the host's memory (RAM plus swap) in one line naming the settings that size
    it."""
    need = fit_memory(rows, dim)
    size = (f"{rows:,} encoded views ({objects} objects x up to {cfg.views_per_object} (--views-per-object)"
            f"{' x 2 for --inputs both' if cfg.inputs == 'both' else ''}) x {dim:,} pooled values (--grid "
            f"{cfg.grid}: {dim // (cfg.grid * cfg.grid)} channels x {cfg.grid}^2)")
    have = device_memory(torch.device("cpu"))
    if have is not None and need > have:
        raise DepthnerfError(f"{size}: the fit would need about {readable_bytes(need)}, more than all the host's "
                             f"memory ({readable_bytes(have)}); lower --grid, --objects or --views-per-object")
    return f"fitting on {size}: about {readable_bytes(need)} of memory"


def fit_facing_head(checkpoint: str | Path, cfg: FacingHeadConfig,
                    log: Callable[[str], None] = lambda line: None) -> FacingHeadFit:
    """Fit a head for ``checkpoint`` (module docstring); ``log`` receives one line sizing the fit before any view
    is encoded (:func:`check_fit_memory`)."""
    session, records = dataset_session(checkpoint, cfg)
    check_fit(session, checkpoint, cfg)
    if len(records) < 5:
        raise DepthnerfError(f"{cfg.data}/{cfg.category}_{cfg.split}: {len(records)} objects; a facing head needs "
                             "at least 5 (one fifth is held out to choose the ridge weight)")
    if not session.model.cfg.mirror:
        raise DepthnerfError(f"{checkpoint}: not a mirror model, so it has no plane for a facing head to find")
    channels = session.model.encoder.latent_size
    rows = sum(len(picks) for picks in drawn_views(records, cfg)) * (2 if cfg.inputs == "both" else 1)
    log(check_fit_memory(rows, channels * cfg.grid * cfg.grid, len(records), cfg))
    pooled, psi, owner = gather(session, cfg, records)
    held = np.random.default_rng(cfg.seed + 1).permutation(len(records))[: max(1, len(records) // 5)]
    val = torch.from_numpy(np.isin(owner, held))
    scores = {}
    for lam, head in zip(LAMBDAS, fit_ridges(pooled[~val], psi[~val], LAMBDAS, channels, cfg.grid), strict=True):
        err = angle_error(head.predict(pooled[val]).double(), psi[val]).abs()
        scores[f"{lam:g}"] = {"median_deg": float(err.median()), "p90_deg": float(torch.quantile(err, 0.9))}
    lam = min(LAMBDAS, key=lambda x: scores[f"{x:g}"]["median_deg"])
    info = {"encoder": encoder_fingerprint(session.model), "lambda": lam,
            "views": sum(len(picks) for picks in drawn_views(records, cfg)), "objects": len(records),
            "inputs": cfg.inputs, "data": f"{Path(cfg.data).name}/{cfg.category}_{cfg.split}",
            "validation_median_deg": scores[f"{lam:g}"]["median_deg"],
            "validation_p90_deg": scores[f"{lam:g}"]["p90_deg"]}
    return FacingHeadFit(head=fit_ridge(pooled, psi, lam, channels, cfg.grid, info), validation=scores)
