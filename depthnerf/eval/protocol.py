"""The SRN evaluation protocol (pixelNeRF's), as run by ``depthnerf eval``.

Protocol
    For every object of the split (sorted by id, without the objects the protocol choices leave out, the first
    ``max_objects``): view 64 (:data:`~depthnerf.data.protocol.INPUT_VIEW`) is the single input view and every other
    view is a target (250 for SRN's 251 views), optionally every ``stride``-th of them in order (``targets = [v !=
    input][::stride]``). Objects with at most 64 views (tiny fixtures) use view 0 as input, and the protocol text
    says so. ``input_views`` (``--input-views 64 104``: pixelNeRF's two-view protocol) conditions on several views
    instead, every view not among them a target; the model averages their features (``combine_layer``), the
    first (primary) view's camera bounds and levels the mesh. Each object is encoded ONCE (image features of the
    input views, and their depth prior) and those features serve every target view and the mesh. Target views are
    rendered with the checkpoint's renderer (deterministic sampling unless the checkpoint's
    ``render.sampler.eval_random``), in groups of ``max(1, chunk // (H*W))`` views and ``chunk`` rays per pass, so
    memory is bounded by ``chunk``.
    Metrics: :mod:`depthnerf.eval.metrics` (PSNR/SSIM as pixelNeRF, LPIPS only from local weights), per object the
    mean over its targets, dataset the mean over objects. Random draws of the renderer (only with
    ``render.sampler.eval_random``) are seeded per object from its id, so no result depends on what else the
    process evaluated.

Protocol choices
    The SSIM variant, the precision renders are scored at (8-bit PNG or float) and whether the objects
    pixelNeRF's evaluation cannot load are left out: :mod:`depthnerf.eval.config` (defaults are pixelNeRF's),
    recorded in ``summary.json`` ``protocol_choices``.

Scale and resume
    ``torchrun --nproc_per_node=N -m depthnerf eval ...`` shares the objects out over N processes (one GPU each, or
    gloo on CPU); every object's result is a file of its own under ``OUT_DIR/objects/``, so a killed evaluation
    restarted with the same arguments computes only the missing objects, and rank 0 merges the outputs, identical
    to a one-process run's (:mod:`depthnerf.eval.shards`). ``summary.json`` records ``world_size``.

Resolution
    ``resolution`` is the size targets are rendered and scored at; default the checkpoint's training resolution
    (``data.resolution``: 64 for the CPU presets), ``--resolution 128`` gives the SRN protocol's 128x128 metrics.
    The input view is always encoded at the training resolution, as the model saw images in training (its depth
    prior cache is therefore the one at the training resolution, for the evaluated split). The summary records
    the evaluated, input, training and dataset (native) resolutions.

3D metrics (beyond the paper)
    :func:`~depthnerf.render.mesh.source_mesh` over the input camera's frustum and the run's z-range, at the auto
    level unless fixed (``mesh_level`` per object), densities of the fine network seen along the input rays
    (:func:`~depthnerf.reconstruct.orbit.field_queries`); Chamfer-L1 / F-score against the visible surface of the depth
    maps, else ``mesh.ply`` (``geometry_gt``), in ``mesh.ply`` diagonals (:mod:`depthnerf.eval.geometry_metrics`).
    Objects without ``mesh.ply`` get empty geometry cells; the means are over objects that have one.

An all-white object (the real SRN cars test set has one; left out by default, scored with ``--objects all``) has
an empty mask: its prior is the background constant, its metrics stay finite (PSNR is capped at 100 dB), and a
non-finite dataset metric is an error, never written.

Outputs in ``OUT_DIR`` (rewritten at the end of every run): ``summary.json`` (what ``depthnerf compare`` reads, see
:mod:`depthnerf.eval.table`), ``per_object.csv``, and with ``save_renders``: ``renders/<object_id>/<view>.png``,
predicted meshes ``meshes/<object_id>.ply`` and ``renders.csv`` (``object_id,view,render_path,gt_path,psnr,ssim``;
paths relative to ``OUT_DIR`` unless absolute; ``summary.json`` ``renders_csv`` names it, null without
``save_renders``). ``gt_path`` is the dataset's own image when targets are scored at
its native resolution (read it with :func:`depthnerf.data.srn_format.read_rgb`, which composites alpha on
white), else an 8-bit copy of the resized ground truth in ``gt/`` (then recomputed metrics differ by 8-bit
quantisation of the ground truth as well as of the render). Renders are 8-bit PNGs (truncated, the image
scored, with the default ``--scored png8``; rounded with ``--scored float``), so metrics recomputed from them
match exactly (png8) or within 8-bit quantisation (float). ``objects/``: the per-object result files.
``--overwrite`` deletes exactly these outputs of an earlier evaluation first
(:func:`depthnerf.eval.shards.remove_outputs`).

Empty predicted meshes (the density never reaches the level) get worst-case geometry values
(:mod:`depthnerf.eval.geometry_metrics`); ``empty_predictions`` counts them, ``mesh_status`` says so first, and
``depthnerf eval`` / ``depthnerf compare`` mark the figures they print.
"""

from __future__ import annotations

import csv
import dataclasses
import hashlib
import io
import json
import math
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np
import torch
import trimesh

from depthnerf.data import srn_format
from depthnerf.data.card import card_path, card_pixel_center, read_dataset_card
from depthnerf.data.fingerprint import DataFingerprint
from depthnerf.data.protocol import record_views
from depthnerf.data.srn import ObjectRecord, index_split, object_dirs
from depthnerf.distributed import DistInfo, checked_together
from depthnerf.errors import DepthnerfError
from depthnerf.eval.config import METRICS_PATH, ProtocolChoices, ProtocolConfig
from depthnerf.eval.geometry_metrics import object_geometry, summarize_geometry
from depthnerf.eval.metrics import (
    SSIM_WINDOW_SIDE,
    ImageMetricsConfig,
    LpipsMetric,
    ObjectMetrics,
    load_lpips,
    lpips_status,
    object_metrics,
    summarize,
)
from depthnerf.eval.objects import ProtocolViews, prepare_object
from depthnerf.eval.shards import ObjectResult, ObjectStore, evaluate_objects, prepare_output_folder
from depthnerf.eval.summary_lines import input_views_record, mesh_status, protocol_text
from depthnerf.files import write_text_atomic
from depthnerf.infer.session import InferenceSession
from depthnerf.render.mesh import MeshConfig
from depthnerf.render.mesh_level import levels_text
from depthnerf.render.source_guide import guided_record

__all__ = ["ProtocolChoices", "ProtocolConfig", "ObjectResult", "EvalOutputs", "evaluate_protocol", "method_label",
           "PER_OBJECT_COLUMNS"]


@dataclass
class EvalOutputs:
    """What :func:`evaluate_protocol` wrote."""

    summary: dict
    """The content of ``summary.json``."""
    summary_path: Path
    """``OUT_DIR/summary.json``."""
    per_object_path: Path
    """``OUT_DIR/per_object.csv``."""
    renders_path: Path | None
    """``OUT_DIR/renders.csv`` (with ``save_renders``)."""


def method_label(estimator: str) -> str:
    """The default ``depthnerf compare`` row label of a depth prior."""
    return "pixelNeRF (baseline)" if estimator == "none" else f"depth-aware ({estimator})"


class _Evaluator:
    """Per-object evaluation with the state shared across objects (the session, LPIPS, settings)."""

    def __init__(self, session: InferenceSession, cfg: ProtocolConfig, lpips: LpipsMetric | None, eval_res: int,
                 out_dir: Path, category: str, views_of: Callable[[ObjectRecord], ProtocolViews]) -> None:
        self.session, self.cfg, self.lpips, self.eval_res, self.out_dir = session, cfg, lpips, eval_res, out_dir
        self.views_of = views_of
        """Each object's input and target views (:func:`_views_of`)."""
        self.symmetry_plane, self.symmetry_from = session.dataset_symmetry(category)
        self.png8 = cfg.choices.scored == "png8"
        self.metrics_cfg = ImageMetricsConfig(quantize_pred=self.png8, ssim_window=cfg.choices.ssim)

    @torch.no_grad()
    def __call__(self, record: ObjectRecord) -> ObjectResult:
        session, cfg = self.session, self.cfg
        views = self.views_of(record)
        torch.manual_seed(object_seed(record.object_id))  # eval_random draws: the same in any process
        t0 = time.perf_counter()
        obj = prepare_object(session, record, views, self.eval_res, self.symmetry_plane)
        tgt = obj.targets
        preds = session.render(obj.encoded, tgt.poses, tgt.intrinsics).rgb.numpy()
        gts = tgt.images.permute(0, 2, 3, 1).numpy()
        t1 = time.perf_counter()
        metrics = object_metrics(record.object_id, preds, gts, self.metrics_cfg, self.lpips)
        t2 = time.perf_counter()
        geometry, mesh, level = None, None, None
        if cfg.mesh and record.mesh_path is not None:
            mesh, level = session.mesh(obj.encoded, MeshConfig(cfg.mesh_resolution, cfg.mesh_threshold),
                                       colored=False)
            geometry = object_geometry(mesh, record, cfg.geometry)
        t3 = time.perf_counter()
        rows = self._save(record, views, preds, gts, metrics, mesh) if cfg.save_renders else []
        return ObjectResult(record=record, views=views, metrics=metrics, geometry=geometry, mesh_level=level,
                            seconds={"render": t1 - t0, "metrics": t2 - t1, "mesh": t3 - t2}, renders=rows)

    def _save(self, record: ObjectRecord, views: ProtocolViews, preds: np.ndarray, gts: np.ndarray,
              metrics: ObjectMetrics, mesh: trimesh.Trimesh | None) -> list[dict]:
        native = (record.intrinsics.height, record.intrinsics.width) == gts.shape[1:3]
        rows = []
        for k, view in enumerate(views.targets):
            name = f"{record.view_names[view]}.png"
            render_rel = Path("renders") / record.object_id / name
            (self.out_dir / render_rel).parent.mkdir(parents=True, exist_ok=True)
            pred = np.floor(np.clip(preds[k], 0, 1) * 255).astype(np.uint8) if self.png8 else preds[k]
            srn_format.write_rgb(self.out_dir / render_rel, pred)  # 8-bit PNG: the scored image with png8
            if native:
                gt_path = str(record.rgb_path(view).resolve())
            else:
                gt_rel = Path("gt") / record.object_id / name
                (self.out_dir / gt_rel).parent.mkdir(parents=True, exist_ok=True)
                srn_format.write_rgb(self.out_dir / gt_rel, gts[k])
                gt_path = gt_rel.as_posix()
            rows.append({"object_id": record.object_id, "view": view, "render_path": render_rel.as_posix(),
                         "gt_path": gt_path, "psnr": repr(metrics.views[k].psnr),
                         "ssim": repr(metrics.views[k].ssim)})
        if mesh is not None:
            (self.out_dir / "meshes").mkdir(exist_ok=True)
            mesh.export(self.out_dir / "meshes" / f"{record.object_id}.ply")
        return rows


def object_seed(object_id: str) -> int:
    """The seed of an object's random render draws (from its id alone)."""
    return int(hashlib.sha256(object_id.encode()).hexdigest()[:15], 16)


def _fmt(value: float | None) -> str:
    return "" if value is None else repr(float(value))


def _write_csv(path: Path, columns: Sequence[str], rows: Sequence[dict]) -> None:
    text = io.StringIO(newline="")
    writer = csv.DictWriter(text, fieldnames=list(columns))
    writer.writeheader()
    writer.writerows(rows)
    write_text_atomic(path, text.getvalue())


PER_OBJECT_COLUMNS = ("object_id", "input_view", "input_views", "views", "psnr", "ssim", "lpips", "chamfer_l1",
                      "fscore", "floater_fraction", "accuracy", "completeness", "precision", "recall", "empty_mesh",
                      "mesh_level", "seconds")
"""Columns of ``per_object.csv`` (empty cell = not measured; ``input_view``: the primary input view,
``input_views``: every input view, space-separated)."""


def _per_object_row(r: ObjectResult) -> dict:
    g = r.geometry
    return {"object_id": r.record.object_id, "input_view": r.views.input_view,
            "input_views": " ".join(map(str, r.views.input_views)), "views": len(r.views.targets),
            "psnr": _fmt(r.metrics.psnr), "ssim": _fmt(r.metrics.ssim), "lpips": _fmt(r.metrics.lpips),
            **{k: _fmt(getattr(g, k)) if g is not None else ""
               for k in ("chamfer_l1", "fscore", "floater_fraction", "accuracy", "completeness", "precision",
                         "recall")},
            "empty_mesh": "" if g is None else int(g.empty_prediction), "seconds": f"{sum(r.seconds.values()):.3f}",
            "mesh_level": _fmt(r.mesh_level.level if r.mesh_level else None)}


def _data_card(root: Path, category: str, card: dict | None) -> dict:
    path = card_path(root, category)
    return {"root": str(root.resolve()), "card_path": str(path.resolve()) if card else None, "card": card}


def _settings(session: InferenceSession, cfg: ProtocolConfig, data_root: Path, category: str, eval_res: int,
              lpips_ok: bool) -> dict:
    """What every per-object result depends on (the resume check of
    :class:`~depthnerf.eval.shards.ObjectStore`)."""
    pre, spec, guided = session.pretrained, session.spec, session.guided
    return {"checkpoint_sha256": pre.sha256, "data_root": str(data_root.resolve()), "category": category,
            "split": cfg.split, "views_stride": cfg.views_stride, "resolution": eval_res,
            **({"input_views": list(cfg.input_views)} if cfg.input_views is not None else {}),
            "input_resolution": spec.resolution, "chunk": session.chunk, "mesh": cfg.mesh,
            "mesh_resolution": cfg.mesh_resolution, "mesh_threshold": cfg.mesh_threshold,
            "geometry": dataclasses.asdict(cfg.geometry), "save_renders": cfg.save_renders,
            "choices": dataclasses.asdict(cfg.choices), "prior": session.prior_source.provenance,
            "guided": None if guided is None else guided_record(guided), "lpips": lpips_ok,
            "lpips_net": cfg.lpips.net, "pixel_center": spec.pixel_center, "device": session.device.type,
            "autocast": str(session.policy.autocast), "point_chunk": session.policy.point_chunk,
            **({"residual": str(session.policy.residual)} if session.policy.residual is not None else {}),
            **({"encoder_norm": session.options.encoder_norm} if session.options.encoder_norm != "running" else {}),
            **({"samples": list(session.options.samples)} if session.options.samples is not None else {}),
            **({"symmetry_plane": None if session.options.symmetry_plane is None
                else list(session.options.symmetry_plane), "symmetry": session.options.symmetry}
               if session.model.cfg.mirror else {})}


def _views_of(cfg: ProtocolConfig) -> Callable[[ObjectRecord], ProtocolViews]:
    """Each object's views under ``cfg``; every one is checked first (an object lacking an asked-for input view
    is one line naming it, before anything is rendered)."""
    def views_of(record: ObjectRecord) -> ProtocolViews:
        return record_views(record, cfg.views_stride, cfg.input_views)
    return views_of


def evaluate_protocol(session: InferenceSession, out_dir: Path, cfg: ProtocolConfig | None = None,
                      info: DistInfo | None = None) -> EvalOutputs | None:
    """Run the protocol on the session's dataset and write ``out_dir`` (see the module docstring). The session
    (``SessionOptions(inputs="dataset", data_root=...)``: the checkpoint with the caller's overrides, the
    dataset's prior cache, the device policy) is how the model runs. With ``info`` (a ``torchrun`` job) this rank
    scores its share of the objects; rank 0 merges and returns the outputs, the other ranks return None."""
    t_start = time.perf_counter()
    if session.options.inputs != "dataset":
        raise DepthnerfError("evaluate_protocol needs a session on a dataset's prior cache "
                             "(SessionOptions(inputs='dataset', data_root=...))")
    device = session.device
    info = info or DistInfo(rank=0, world=1, device=device)
    cfg = cfg or ProtocolConfig()
    choices = cfg.choices.check()
    pre, spec = session.pretrained, session.spec
    data_root, out_dir = Path(session.options.data_root), Path(out_dir)
    category = cfg.category or spec.category
    with checked_together(info, "checking the data and the output folder"):  # agreed by the ranks: one line
        ids = [p.name for p in object_dirs(data_root, category, cfg.split)]
        card = read_dataset_card(data_root, category)
        # depth maps are back-projected with the dataset's own pixel centres (its card), whatever the model assumes
        cfg = replace(cfg, geometry=replace(cfg.geometry, depth_pixel_center=card_pixel_center(card)))
        skipped = [i for i in ids if choices.skips(i)]
        kept = [i for i in ids if not choices.skips(i)]
        if not kept:
            raise DepthnerfError(f"{data_root}: every object of {category}_{cfg.split} is left out by --objects "
                                 f"{choices.objects}")
        chosen = set(kept[: cfg.max_objects] if cfg.max_objects else kept)
        # every file of these checked; mesh.ply whole only when geometry is scored (else its header, as training)
        records = index_split(data_root, category, cfg.split, only=chosen, mesh_body=cfg.mesh).objects
        views_of = _views_of(cfg)
        for record in records:
            views_of(record)
        input_res, eval_res = spec.resolution, spec.resolution if cfg.resolution is None else cfg.resolution
        side = max(8, SSIM_WINDOW_SIDE[choices.ssim])
        if eval_res < side:
            raise DepthnerfError(f"--resolution must be >= {side} (SSIM {choices.ssim}), got {eval_res}")
        session.prior_source.check(records)
        estimator, guided = spec.prior.estimator, session.guided
        lpips = load_lpips(cfg.lpips, device)
        lp_reason = "ok" if lpips is not None else lpips_status(cfg.lpips).reason
        prepare_output_folder(out_dir)
        evaluator = _Evaluator(session, cfg, lpips, eval_res, out_dir, category, views_of)
        store = ObjectStore(out_dir, _settings(session, cfg, data_root, category, eval_res, lpips is not None),
                            DataFingerprint(data_root, category))
    results, counts = evaluate_objects(records, evaluator, store, info, views_of, overwrite=cfg.overwrite,
                                       progress=cfg.progress)
    if results is None:
        return None

    summary = summarize([r.metrics for r in results], lp_reason)
    geo = [r.geometry for r in results if r.geometry is not None]
    if geo:
        summary.update(summarize_geometry(geo, cfg.geometry))
        summary["geometry_objects"] = len(geo)
        summary["mesh_status"] = mesh_status(summary["empty_predictions"], len(geo), len(results)) + levels_text(
            [r.mesh_level for r in results if r.mesh_level], cfg.mesh_resolution)
    else:
        summary.update({"chamfer_l1": None, "fscore": None, "fscore_tau": None, "floater_fraction": None,
                        "geometry_objects": 0})
        summary["mesh_status"] = ("skipped (--no-mesh)" if not cfg.mesh
                                  else f"skipped: none of the {len(results)} objects has mesh.ply")
    native = sorted({(r.record.intrinsics.height, r.record.intrinsics.width) for r in results})
    deterministic = not spec.render.sampler.eval_random
    total = time.perf_counter() - t_start
    summary.update({
        "protocol": protocol_text(results, len(ids), cfg.split, category, cfg.views_stride, eval_res,
                                  input_res, deterministic, skipped, chosen=cfg.input_views is not None),
        "protocol_choices": choices.record(skipped),
        "method": cfg.method or method_label(estimator) + (
            " + mirror symmetry" if evaluator.symmetry_plane is not None else "") + (
            " + prior at each point" if spec.model.prior_at_point else "") + (
            " + colour at each point" if spec.model.rgb_at_point else "") + (
            " + global features" if spec.model.global_features else "") + (
            f" + encoder at {spec.model.encoder.image_scale:g}x input" if spec.model.encoder.image_scale != 1.0
            else "") + (
            " + encoder without first pool" if not spec.model.encoder.use_first_pool else "") + (
            f" + guided sampling ({guided.budget}/ray)" if guided is not None else "") + (
            f" + {'+'.join(map(str, session.options.samples))} samples/ray" if session.options.samples is not None
            else "") + (
            f", {len(cfg.input_views)} input views" if cfg.input_views is not None and len(cfg.input_views) > 1
            else ""),
        "guided_sampling": None if guided is None else guided_record(guided),
        "sampler_counts": list(spec.render.sampler.counts),
        "category": category, "split": cfg.split, "preset": spec.preset,
        "depth_prior": estimator, "depth_prior_provenance": session.prior_source.provenance,
        "checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step,
        "data_card": _data_card(data_root, category, card),
        "resolution": eval_res, "input_resolution": input_res, "train_resolution": spec.resolution,
        "native_resolution": [list(s) for s in native],
        "views_stride": cfg.views_stride, "input_views": input_views_record(results), "max_objects": cfg.max_objects,
        "pixel_center": spec.pixel_center, "trained_pixel_center": pre.spec.pixel_center,
        "encoder_norm": session.options.encoder_norm,
        "symmetry_plane": None if evaluator.symmetry_plane is None else list(evaluator.symmetry_plane),
        "symmetry_plane_source": evaluator.symmetry_from,
        "dataset_pixel_center": cfg.geometry.depth_pixel_center, "z_range": list(spec.z_range),
        "metrics_path": METRICS_PATH[choices.scored],
        "world_size": info.world,
        "timing": {"total_s": total,  # per object: over those computed now (resumed ones cost nothing here)
                   "per_object_s": total / counts.computed if counts.computed else None,
                   **{f"{k}_s": float(sum(r.seconds[k] for r in results)) for k in ("render", "metrics", "mesh")},
                   "device": str(device), "torch_threads": torch.get_num_threads(),
                   "objects_computed": counts.computed, "objects_resumed": counts.resumed},
    })
    for key in ("psnr", "ssim", "lpips", "chamfer_l1", "fscore", "floater_fraction"):
        value = summary.get(key)
        if value is not None and not math.isfinite(value):
            raise DepthnerfError(f"evaluation produced a non-finite {key} ({value}); refusing to write it")
    per_object = out_dir / "per_object.csv"
    _write_csv(per_object, PER_OBJECT_COLUMNS, [_per_object_row(r) for r in results])
    renders = None
    summary["renders_csv"] = None  # no renders.csv of this evaluation (one found there is another's)
    if cfg.save_renders:
        renders = out_dir / "renders.csv"
        _write_csv(renders, ("object_id", "view", "render_path", "gt_path", "psnr", "ssim"),
                   [row for r in results for row in r.renders])
        summary["renders_csv"] = renders.name
    summary_path = out_dir / "summary.json"
    write_text_atomic(summary_path, json.dumps(summary, indent=1) + "\n")
    return EvalOutputs(summary=summary, summary_path=summary_path, per_object_path=per_object,
                       renders_path=renders)
