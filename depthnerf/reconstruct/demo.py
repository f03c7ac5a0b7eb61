"""``depthnerf demo``: synthesise one unseen car and one unseen chair, reconstruct each from one view, score it.

Objects
    Per category, test object 0 of ``depthnerf synth --category C --seed S --test-objects 1`` (default seed
    :data:`DEMO_SEED`; the training data of the shipped checkpoints and the bundled depth network use seed 0 and
    its evaluation seed 1234, and an object's shapes depend on (seed, category, split, index) only, so the demo
    objects were never seen in training), rendered at the checkpoint's training resolution with the SRN test
    protocol's 251 spiral views into ``OUT/data`` (SRN layout, with depth, masks and the true mesh).
Reconstruction and scores
    Exactly the SRN protocol of ``depthnerf eval`` (:mod:`depthnerf.eval.protocol`): view 64 is the input, the
    targets are every ``views_stride``-th of the other 250 views (:func:`~depthnerf.eval.protocol.protocol_views`;
    stride 25 = 10 views), rendered at the training resolution and scored with :mod:`depthnerf.eval.metrics`
    (float renders, per-object mean PSNR/SSIM). The depth prior is the checkpoint's own estimator run on the input
    view (as ``depthnerf depth`` computes the cache, stored as float16 there and here); an ``oracle`` checkpoint
    gets the synthetic ground-truth depth of the input view, which only synthetic data has (reported in notes).
Outputs per category in ``OUT/<category>/``
    Everything :func:`depthnerf.reconstruct.exports.save_reconstruction` writes (``input.png``, ``depth_prior.png``, the
    turntable frames in ``views/`` and ``turntable.gif``, ``depths/``, ``mesh.ply``/``mesh.glb`` of marching cubes
    over the input camera's frustum, ``points.ply``, ``manifest.json``); the turntable orbits the object at the
    input camera's distance and elevation, starting at the input camera. Plus ``novel_views/pred_NNNNNN.png`` and
    ``novel_views/true_NNNNNN.png`` (NNNNNN = the SRN view index) and ``novel_views.png``, a strip with the
    predictions on top and the true views below. ``OUT/demo.json`` gathers metrics, checkpoints and files.
"""

from __future__ import annotations

import json
import math
import shutil
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
import trimesh
from PIL import Image
from tqdm import tqdm

from depthnerf.data import srn_format
from depthnerf.data.srn import ObjectViews, index_split
from depthnerf.data.synth.framing import DEFAULT_FRAMING, checkpoint_framing
from depthnerf.data.synth.generate import ObjectJob, SynthConfig, generate, job_status
from depthnerf.depth.estimators import CACHED_ESTIMATORS, make_estimator
from depthnerf.depth.precompute import predict_views
from depthnerf.errors import DepthnerfError
from depthnerf.eval.metrics import object_metrics
from depthnerf.eval.objects import ProtocolViews, prepare_object, protocol_views
from depthnerf.eval.pretrained import Pretrained, load_pretrained, resolve_checkpoint, shipped_checkpoints
from depthnerf.model.pixelnerf import EncodedViews
from depthnerf.reconstruct.exports import save_reconstruction
from depthnerf.reconstruct.orbit import orbit_points, orbit_poses
from depthnerf.reconstruct.photo import PreparedImage
from depthnerf.reconstruct.reconstructor import POINT_OPACITY, Reconstruction
from depthnerf.render.mesh import AUTO_LEVEL, MeshConfig, input_camera_mesh
from depthnerf.render.views import render_poses
from depthnerf.train.config import z_range

DEMO_SEED = 2718
"""``depthnerf synth --seed`` of the demo objects (training data: seed 0; bundled-depth evaluation: 1234)."""
CATEGORIES = ("cars", "chairs")
"""Categories the demo knows, in order."""
DEFAULT_CHECKPOINTS = {"cars": "cpu-cars-depth", "chairs": "cpu-chairs-depth"}
"""Shipped depth-aware checkpoint per category."""


@dataclass(frozen=True)
class DemoConfig:
    """What ``depthnerf demo`` does."""

    out: Path = Path("demo_out")
    """Output folder (``data/``, one folder per category, ``demo.json``)."""
    seed: int = DEMO_SEED
    """Synthesis seed of the demo objects."""
    categories: tuple[str, ...] = CATEGORIES
    """Categories to run, in order."""
    checkpoints: dict[str, str] = field(default_factory=lambda: dict(DEFAULT_CHECKPOINTS))
    """Checkpoint spec per category (shipped name, weights file, checkpoint or run folder)."""
    views_stride: int = 25
    """Score every K-th of the 250 target views (25: 10 views)."""
    turntable_views: int = 16
    """Frames of the turntable orbit (each costs as much as a scored view)."""
    mesh: bool = True
    """Extract the mesh (marching cubes over the input frustum)."""
    mesh_resolution: int = 96
    """Marching-cubes samples along the frustum box's longest side."""
    chunk: int = 4096
    """Rays per render pass."""
    progress: bool = True
    """Progress bar per category (stderr)."""


@dataclass
class CategoryResult:
    """The demo of one category."""

    category: str
    """``cars`` or ``chairs``."""
    pretrained: Pretrained
    """The checkpoint used."""
    checkpoint_spec: str
    """How it was named on the command line."""
    object_id: str
    """The synthesised object."""
    views: ProtocolViews
    """Input and scored target views."""
    psnr: float
    """Mean PSNR over the target views (dB)."""
    ssim: float
    """Mean SSIM over the target views."""
    per_view: list[dict[str, float]]
    """``view``, ``psnr``, ``ssim`` of each target."""
    notes: list[str]
    """Depth prior and other remarks."""
    seconds: dict[str, float]
    """Wall time per stage."""
    files: dict[str, Any]
    """Written files, relative to the demo output folder."""
    mesh_faces: int | None
    """Faces of the extracted mesh (None with ``mesh=False``)."""


def _u8(x: np.ndarray) -> np.ndarray:
    return np.round(np.clip(x, 0.0, 1.0) * 255.0).astype(np.uint8)


def load_checkpoint_for(category: str, spec: str) -> Pretrained:
    """Load the checkpoint given for ``category``; a missing one is a one-line error saying how to get it."""
    try:
        resolve_checkpoint(spec)
    except DepthnerfError:
        if spec in DEFAULT_CHECKPOINTS.values() or not Path(spec).exists():
            shipped = ", ".join(shipped_checkpoints()) or "none"
            raise DepthnerfError(f"checkpoint '{spec}' for {category} is not installed (shipped: {shipped}); "
                                 "'depthnerf checkpoints' lists the shipped ones, or pass "
                                 f"--{category}-checkpoint RUN_DIR_OR_FILE from 'depthnerf train'") from None
        raise
    pre = load_pretrained(spec)
    if pre.config.data.category != category:
        raise DepthnerfError(f"{pre.path}: trained on {pre.config.data.category}, given as the {category} checkpoint")
    return pre


def synthesize(category: str, root: Path, seed: int, resolution: int, framing: str = DEFAULT_FRAMING) -> ObjectJob:
    """Test object 0 of ``seed`` at ``resolution`` with 251 views in ``root`` (reused when already there), framed
    as ``framing`` (that of the checkpoint's training data: :func:`checkpoint_framing`)."""
    cfg = SynthConfig(category=category, out=root, train_objects=0, val_objects=0, test_objects=1,
                      resolution=resolution, seed=seed, progress=False, framing=framing)
    job = ObjectJob(cfg, "test", 0)
    try:
        job_status(job)
    except DepthnerfError:  # an earlier demo with another seed or resolution: regenerate
        shutil.rmtree(job.folder)
    generate(cfg)
    return job


def depth_prior(pre: Pretrained, src: ObjectViews, notes: list[str]) -> torch.Tensor | None:
    """Raw disparity of the input view from the checkpoint's estimator (None for a baseline)."""
    cfg = pre.config
    if not cfg.model.encoder.use_depth:
        notes.append("baseline checkpoint: no depth prior")
        return None
    name = cfg.prior.estimator
    estimator = make_estimator(name, cfg.prior.checkpoint)
    disp = predict_views(estimator, src.images, src.depths, 1)
    if name == "oracle":
        notes.append("oracle checkpoint: the prior is the synthetic input view's ground-truth depth (1/z), "
                     "which a real photo would not have")
    elif name in CACHED_ESTIMATORS:
        disp = disp.half().float()  # as stored in the depth-prior cache that 'depthnerf eval' reads
        notes.append(f"depth prior: {name} estimator on the input view")
    return disp


def _strip(preds: np.ndarray, gts: np.ndarray, gap: int = 2) -> np.ndarray:
    """Predictions on top, truths below, grey gaps between tiles."""
    n, h, w, _ = preds.shape
    out = np.full((2 * h + gap, n * w + (n - 1) * gap, 3), 160, np.uint8)
    for k in range(n):
        x = k * (w + gap)
        out[:h, x:x + w] = _u8(preds[k])
        out[h + gap:, x:x + w] = _u8(gts[k])
    return out


def _save_novel_views(out: Path, root: Path, names: Sequence[str], preds: np.ndarray, gts: np.ndarray) -> dict:
    (out / "novel_views").mkdir(parents=True, exist_ok=True)
    files: dict[str, Any] = {"pred": [], "true": []}
    for name, pred, gt in zip(names, preds, gts, strict=True):
        for kind, img in (("pred", pred), ("true", gt)):
            path = out / "novel_views" / f"{kind}_{name}.png"
            srn_format.write_rgb(path, img)
            files[kind].append(path.relative_to(root).as_posix())
    Image.fromarray(_strip(preds, gts)).save(out / "novel_views.png")
    files["strip"] = (out / "novel_views.png").relative_to(root).as_posix()
    return files


def turntable_and_mesh(pre: Pretrained, src: ObjectViews, disp: torch.Tensor | None, prior: torch.Tensor | None,
                       enc: EncodedViews, cfg: DemoConfig, notes: list[str], device: torch.device,
                       on_stage: Callable[[int], Any]) -> Reconstruction:
    """The turntable (an orbit at the input camera's distance and elevation, from the input camera on), its
    depths and point cloud, and the mesh, as a :class:`Reconstruction` that :func:`save_reconstruction` writes."""
    train, model = pre.config, pre.model
    res, (near, far) = train.data.resolution, z_range(train)
    t = time.perf_counter()
    eye = src.poses[0, :3, 3]
    radius = float(eye.norm())
    elevation = math.degrees(math.asin(float(eye[2]) / radius))
    azimuth = math.degrees(math.atan2(float(eye[1]), float(eye[0])))
    poses = orbit_poses(radius, elevation, cfg.turntable_views, azimuth)
    orbit = render_poses(model, enc, poses, src.intrinsics, near, far, train.render, cfg.chunk, device)
    times = {"turntable_s": time.perf_counter() - t}
    on_stage(1)
    t = time.perf_counter()
    mesh, level = trimesh.Trimesh(), None
    if cfg.mesh:
        mesh, level = input_camera_mesh(model, enc, src.poses[0], src.intrinsics, near, far,
                                        MeshConfig(cfg.mesh_resolution, AUTO_LEVEL), device)
    times["mesh_s"] = time.perf_counter() - t
    on_stage(1)
    points, point_colors = orbit_points(orbit, poses, src.intrinsics, POINT_OPACITY, max_points=None)
    prepared = PreparedImage(image=src.images[0].permute(1, 2, 0).numpy(), mask=src.masks[0].numpy(),
                             notes=notes, source_size=(res, res))
    settings = {"radius": radius, "elevation": elevation, "azimuth": azimuth, "resolution": res,
                "render_resolution": res, "views": cfg.turntable_views, "z_range": [near, far],
                "category": train.data.category,
                "depth_estimator": train.prior.estimator if disp is not None else "none",
                "mesh_resolution": cfg.mesh_resolution if cfg.mesh else 0, "point_opacity": POINT_OPACITY,
                "mesh_level": level and level.level, "mesh_level_rule": level and level.describe()}
    return Reconstruction(
        input=prepared, depth_prior=None if disp is None else disp[0].numpy(),
        prior_normalized=None if prior is None else prior[0, 0, 0].cpu().numpy(),
        poses=poses.numpy(), intrinsics=src.intrinsics, views=orbit.rgb.numpy(), depths=orbit.depth.numpy(),
        opacity=orbit.opacity.numpy(), mesh=mesh, points=points,
        point_colors=point_colors, settings=settings, timings=times)


@torch.no_grad()
def run_category(category: str, pre: Pretrained, spec: str, cfg: DemoConfig, device: torch.device
                 ) -> CategoryResult:
    """Synthesise, reconstruct, score and save one category with a loaded checkpoint (module docstring)."""
    times: dict[str, float] = {}
    train, model = pre.config, pre.model.to(device)
    res = train.data.resolution
    bar = tqdm(total=4, desc=f"demo {category}", unit="stage", file=sys.stderr, disable=not cfg.progress)
    t = time.perf_counter()
    framing, framing_source = checkpoint_framing(pre.path, train.data.root, category)
    job = synthesize(category, cfg.out / "data", cfg.seed, res, framing)
    record = next(r for r in index_split(cfg.out / "data", category, "test").objects if r.object_id == job.object_id)
    times["synth_s"] = time.perf_counter() - t
    bar.update(1)
    t = time.perf_counter()
    views = protocol_views(record.num_views, cfg.views_stride)
    notes: list[str] = [f"object {record.object_id}: depthnerf synth --category {category} --seed {cfg.seed} "
                        f"--test-objects 1 --resolution {res} --framing {framing} (test split, never used for "
                        f"training; framing from {framing_source})"]
    obj = prepare_object(model, record, views, lambda views_: depth_prior(pre, views_, notes), res, res, device,
                         source_depth=train.prior.estimator == "oracle", pixel_center=train.data.pixel_center)
    src, tgt, disp, enc = obj.source, obj.targets, obj.prior, obj.enc
    if not cfg.mesh:
        notes.append("--no-mesh: no mesh extracted (mesh.ply and mesh.glb are empty)")
    near, far = z_range(train)
    preds = render_poses(model, enc, tgt.poses, tgt.intrinsics, near, far, train.render, cfg.chunk, device).rgb.numpy()
    gts = tgt.images.permute(0, 2, 3, 1).numpy()
    metrics = object_metrics(record.object_id, preds, gts)
    times["reconstruct_s"] = time.perf_counter() - t
    bar.update(1)
    result = turntable_and_mesh(pre, src, disp, obj.inputs.prior, enc, cfg, notes, device, bar.update)
    bar.close()
    result.timings = {**times, **result.timings}
    t = time.perf_counter()
    out = cfg.out / category
    provenance = {"checkpoint": str(pre.path.resolve()), "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step,
                  "preset": train.preset}
    manifest = save_reconstruction(result, out, provenance)
    files = {k: (None if v is None else [f"{category}/{x}" for x in v] if isinstance(v, list) else f"{category}/{v}")
             for k, v in manifest["files"].items() if k != "views" and k != "depths"}
    files.update({"turntable_frames": f"{category}/views", "manifest": f"{category}/manifest.json"})
    files["novel_views"] = _save_novel_views(out, cfg.out, [record.view_names[v] for v in views.targets], preds, gts)
    times.update(result.timings)
    times["save_s"] = time.perf_counter() - t
    per_view = [{"view": v, "psnr": m.psnr, "ssim": m.ssim} for v, m in zip(views.targets, metrics.views, strict=True)]
    return CategoryResult(category=category, pretrained=pre, checkpoint_spec=spec, object_id=record.object_id,
                          views=views, psnr=metrics.psnr, ssim=metrics.ssim, per_view=per_view, notes=notes,
                          seconds=times, files=files,
                          mesh_faces=manifest["mesh"]["faces"] if cfg.mesh else None)


def _category_json(r: CategoryResult) -> dict:
    pre = r.pretrained
    return {"checkpoint": r.checkpoint_spec, "checkpoint_path": str(pre.path.resolve()),
            "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step, "preset": pre.config.preset,
            "depth_prior": pre.config.prior.estimator, "object_id": r.object_id, "input_view": r.views.input_view,
            "target_views": list(r.views.targets), "psnr": r.psnr, "ssim": r.ssim, "per_view": r.per_view,
            "notes": r.notes, "mesh_faces": r.mesh_faces,
            "seconds": {**r.seconds, "total_s": sum(r.seconds.values())}, "files": r.files}


def run_demo(cfg: DemoConfig, device: torch.device | str = "cpu") -> dict:
    """Run every category of ``cfg`` and write ``cfg.out/demo.json``; returns its content."""
    t0 = time.perf_counter()
    unknown = [c for c in cfg.categories if c not in CATEGORIES]
    if unknown or not cfg.categories:
        raise DepthnerfError(f"--categories: choose from {', '.join(CATEGORIES)} (got {', '.join(unknown) or 'none'})")
    if cfg.views_stride < 1 or cfg.turntable_views < 1 or cfg.mesh_resolution < 2:
        raise DepthnerfError("--views-stride and --turntable-views must be >= 1, --mesh-resolution >= 2")
    specs = {c: cfg.checkpoints.get(c, DEFAULT_CHECKPOINTS[c]) for c in cfg.categories}
    loaded = {}
    for category, spec in specs.items():  # every checkpoint loads before any work starts
        t = time.perf_counter()
        loaded[category] = (load_checkpoint_for(category, spec), time.perf_counter() - t)
    try:
        cfg.out.mkdir(parents=True, exist_ok=True)
    except OSError as err:
        raise DepthnerfError(f"{cfg.out}: cannot create the output folder ({err.strerror or err})") from None
    results = []
    for category, (pre, load_s) in loaded.items():
        results.append(run_category(category, pre, specs[category], cfg, torch.device(device)))
        results[-1].seconds = {"load_s": load_s, **results[-1].seconds}
    total = time.perf_counter() - t0
    demo = {"seed": cfg.seed, "data": "data", "views_stride": cfg.views_stride,
            "protocol": (f"SRN protocol as 'depthnerf eval': input view {results[0].views.input_view}, every "
                         f"{cfg.views_stride}-th of the other {results[0].views.others} views, training resolution, "
                         "PSNR/SSIM from depthnerf.eval.metrics on float renders"),
            "categories": {r.category: _category_json(r) for r in results},
            "seconds": total, "device": str(device), "torch_threads": torch.get_num_threads()}
    (cfg.out / "demo.json").write_text(json.dumps(demo, indent=1) + "\n")
    return demo
