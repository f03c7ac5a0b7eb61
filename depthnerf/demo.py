"""``depthnerf demo``: synthesise one unseen car and one unseen chair, reconstruct each from one view, score it.

An application of the inference session (:class:`~depthnerf.infer.session.InferenceSession`: the checkpoint, its
prior and the device policy resolved once), :func:`depthnerf.eval.objects.prepare_object` and
:mod:`depthnerf.eval.metrics` (the object as ``depthnerf eval`` prepares and scores it) and
:class:`~depthnerf.reconstruct.Reconstructor` (turntable, mesh and files), so it sits above those stages, beside
``commands/``.

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
    (float renders, per-object mean PSNR/SSIM). The depth prior is the checkpoint's own estimator run live on the
    input view (a session on ``views`` inputs): rounded as the cache stores it
    (:func:`depthnerf.depth.cache.as_cached`), so the model sees what ``depthnerf eval`` feeds it for the same view;
    an ``oracle`` checkpoint gets the synthetic ground-truth depth of the input view, which only synthetic data has
    (reported in notes).
Outputs per category in ``OUT/<category>/``
    Everything :func:`depthnerf.reconstruct.exports.save_reconstruction` writes (``input.png``, ``depth_prior.png``, the
    turntable frames in ``views/`` and ``turntable.gif``, ``depths/``, ``mesh.ply``/``mesh.glb`` of marching cubes
    over the input camera's frustum, ``points.ply``, ``manifest.json``); the turntable orbits the object at the
    input camera's distance and elevation, starting at the input camera. Plus ``novel_views/pred_NNNNNN.png`` and
    ``novel_views/true_NNNNNN.png`` (NNNNNN = the SRN view index) and ``novel_views.png``, a strip with the
    predictions on top and the true views below. ``OUT/demo.json`` gathers metrics, checkpoints and files.
    A rerun into the same ``OUT`` replaces these files (an earlier run's novel views with another stride or seed
    included) and leaves other files alone.
"""

from __future__ import annotations

import json
import math
import re
import shutil
import sys
import time
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch
from PIL import Image
from tqdm import tqdm

from depthnerf.data import srn_format
from depthnerf.data.protocol import ProtocolViews, protocol_views
from depthnerf.data.srn import index_split
from depthnerf.data.symmetry import dataset_plane
from depthnerf.data.synth.framing import DEFAULT_FRAMING
from depthnerf.data.synth.generate import ObjectJob, SynthConfig, generate, job_status
from depthnerf.errors import DepthnerfError
from depthnerf.eval.metrics import object_metrics
from depthnerf.eval.objects import prepare_object
from depthnerf.files import folder_problem, make_folder, write_text_atomic
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.pretrained.hub import is_hub_reference
from depthnerf.pretrained.load import resolve_checkpoint, shipped_checkpoints
from depthnerf.pretrained.recommended import RECOMMENDED
from depthnerf.reconstruct.exports import save_reconstruction, to_u8
from depthnerf.reconstruct.orbit import orbit_poses
from depthnerf.reconstruct.photo import PreparedImage
from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor
from depthnerf.render.mesh import check_mesh_resolution
from depthnerf.render.mesh_level import LOCAL_LEVEL

DEMO_SEED = 2718
"""``depthnerf synth --seed`` of the demo objects (training data: seed 0; bundled-depth evaluation: 1234)."""
CATEGORIES = ("cars", "chairs")
"""Categories the demo knows, in order."""
DEFAULT_CHECKPOINTS = {category: RECOMMENDED[category] for category in CATEGORIES}
"""Shipped checkpoint per category: the best one (:data:`~depthnerf.pretrained.recommended.RECOMMENDED`)."""
NOVEL_VIEW = re.compile(r"(pred|true)_\d+\.png")
"""Names of the files a demo writes into ``OUT/<category>/novel_views/``."""


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
    """Checkpoint per category (shipped name, weights file, checkpoint or run folder)."""
    views_stride: int = 25
    """Score every K-th of the 250 target views (25: 10 views)."""
    turntable_views: int = 16
    """Frames of the turntable orbit (each costs as much as a scored view)."""
    mesh: bool = True
    """Extract the mesh (marching cubes over the input frustum)."""
    mesh_resolution: int = 96
    """Marching-cubes samples along the frustum box's longest side."""
    chunk: int | None = None
    """Rays per render pass; None: the device policy's (4096 on the CPU, 65536 on CUDA)."""
    progress: bool = True
    """Progress bar per category (stderr)."""


@dataclass
class CategoryResult:
    """The demo of one category."""

    category: str
    """``cars`` or ``chairs``."""
    session: InferenceSession
    """The checkpoint used, with its prior and device policy."""
    checkpoint: str
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


def load_checkpoint_for(category: str, checkpoint: str, device: torch.device | str = "cpu") -> InferenceSession:
    """The session of the checkpoint given for ``category`` (its own prior run live on dataset-like views, the
    device's policy); a missing one is a one-line error saying how to get it."""
    try:
        resolve_checkpoint(checkpoint)
    except DepthnerfError:
        if checkpoint in DEFAULT_CHECKPOINTS.values() or not (is_hub_reference(checkpoint)
                                                              or Path(checkpoint).exists()):
            shipped = ", ".join(shipped_checkpoints()) or "none"
            raise DepthnerfError(f"checkpoint '{checkpoint}' for {category} is not installed (shipped: {shipped}); "
                                 "'depthnerf checkpoints' lists the shipped ones, or pass "
                                 f"--{category}-checkpoint RUN_DIR_OR_FILE from 'depthnerf train'") from None
        raise
    session = InferenceSession(checkpoint, SessionOptions(device=device, inputs="views"))
    if session.spec.category != category:
        raise DepthnerfError(f"{session.pretrained.path}: trained on {session.spec.category}, given as the "
                             f"{category} checkpoint")
    return session


def synthesize(category: str, root: Path, seed: int, resolution: int, framing: str = DEFAULT_FRAMING) -> ObjectJob:
    """Test object 0 of ``seed`` at ``resolution`` with 251 views in ``root`` (reused when already there), framed
    as ``framing`` (that of the checkpoint's training data: ``InferenceSpec.framing``)."""
    cfg = SynthConfig(category=category, out=root, train_objects=0, val_objects=0, test_objects=1,
                      resolution=resolution, seed=seed, progress=False, framing=framing)
    job = ObjectJob(cfg, "test", 0)
    try:
        job_status(job)
    except DepthnerfError:  # an earlier demo with another seed or resolution: regenerate
        shutil.rmtree(job.folder)
    generate(cfg)
    return job


def _strip(preds: np.ndarray, gts: np.ndarray, gap: int = 2) -> np.ndarray:
    """Predictions on top, truths below, grey gaps between tiles."""
    n, h, w, _ = preds.shape
    out = np.full((2 * h + gap, n * w + (n - 1) * gap, 3), 160, np.uint8)
    for k in range(n):
        x = k * (w + gap)
        out[:h, x:x + w] = to_u8(preds[k])
        out[h + gap:, x:x + w] = to_u8(gts[k])
    return out


def _save_novel_views(out: Path, root: Path, names: Sequence[str], preds: np.ndarray, gts: np.ndarray) -> dict:
    """Write ``novel_views/{pred,true}_NAME.png`` and the strip; the views of an earlier demo in ``out`` (another
    ``--views-stride`` or ``--seed``) are removed first, so the folder holds exactly this run's views."""
    folder = out / "novel_views"
    folder.mkdir(parents=True, exist_ok=True)
    for earlier in folder.iterdir():
        if NOVEL_VIEW.fullmatch(earlier.name) and earlier.is_file():
            earlier.unlink()
    files: dict[str, Any] = {"pred": [], "true": []}
    for name, pred, gt in zip(names, preds, gts, strict=True):
        for kind, img in (("pred", pred), ("true", gt)):
            path = out / "novel_views" / f"{kind}_{name}.png"
            srn_format.write_rgb(path, img)
            files[kind].append(path.relative_to(root).as_posix())
    Image.fromarray(_strip(preds, gts)).save(out / "novel_views.png")
    files["strip"] = (out / "novel_views.png").relative_to(root).as_posix()
    return files


def _prior_note(session: InferenceSession) -> str:
    name = session.spec.prior.estimator
    if name == "none":
        return "baseline checkpoint: no depth prior"
    if name == "oracle":
        return ("oracle checkpoint: the prior is the synthetic input view's ground-truth depth (1/z), which a real "
                "photo would not have")
    return f"depth prior: {name} estimator on the input view"


@torch.no_grad()
def run_category(category: str, session: InferenceSession, checkpoint: str, cfg: DemoConfig) -> CategoryResult:
    """Synthesise, reconstruct, score and save one category with a checkpoint's session (module docstring)."""
    times: dict[str, float] = {}
    res = session.spec.resolution
    rec = Reconstructor(session)
    bar = tqdm(total=4, desc=f"demo {category}", unit="stage", file=sys.stderr, disable=not cfg.progress)
    t = time.perf_counter()
    job = synthesize(category, cfg.out / "data", cfg.seed, res, session.framing)
    record = next(r for r in index_split(cfg.out / "data", category, "test").objects if r.object_id == job.object_id)
    times["synth_s"] = time.perf_counter() - t
    bar.update(1)
    t = time.perf_counter()
    views = protocol_views(record.num_views, cfg.views_stride)
    notes: list[str] = [f"object {record.object_id}: depthnerf synth --category {category} --seed {cfg.seed} "
                        f"--test-objects 1 --resolution {res} --framing {session.framing} (test split, never used "
                        f"for training; framing from {session.framing_origin})", _prior_note(session)]
    plane = None
    if session.model.cfg.mirror:  # the synthetic data's plane, from its card, as eval reads it
        plane, plane_from = dataset_plane(cfg.out / "data", category)
        notes.append(f"mirror-symmetric conditioning on the plane {list(plane)} ({plane_from})")
    obj = prepare_object(session, record, views, symmetry_plane=plane)  # exactly as depthnerf eval prepares it
    src, tgt, encoded = obj.source, obj.targets, obj.encoded
    if not cfg.mesh:
        notes.append("--no-mesh: no mesh extracted (no mesh.ply or mesh.glb written)")
    rcfg = ReconstructConfig(mesh_resolution=cfg.mesh_resolution if cfg.mesh else 0, mesh_threshold=LOCAL_LEVEL,
                             max_points=None, chunk=cfg.chunk)
    preds = rec.render(encoded, tgt.poses, tgt.intrinsics, rcfg).rgb.numpy()
    gts = tgt.images.permute(0, 2, 3, 1).numpy()
    metrics = object_metrics(record.object_id, preds, gts)
    times["reconstruct_s"] = time.perf_counter() - t
    bar.update(1)
    # the turntable: an orbit at the input camera's distance and elevation, from the input camera on
    eye = src.poses[0, :3, 3]
    radius = float(eye.norm())
    elevation = math.degrees(math.asin(float(eye[2]) / radius))
    azimuth = math.degrees(math.atan2(float(eye[1]), float(eye[0])))
    prepared = PreparedImage(image=src.images[0].permute(1, 2, 0).numpy(), mask=src.masks[0].numpy(),
                             notes=notes, source_size=(res, res))
    turntable = orbit_poses(radius, elevation, cfg.turntable_views, azimuth)
    result = rec.reconstruct_encoded(encoded, turntable, src.intrinsics, rcfg, prepared, on_stage=bar.update)
    bar.close()
    result.settings = {"radius": radius, "elevation": elevation, "azimuth": azimuth, **result.settings}
    t = time.perf_counter()
    out = cfg.out / category
    manifest = save_reconstruction(result, out, session.provenance())
    files = {k: (None if v is None else [f"{category}/{x}" for x in v] if isinstance(v, list) else f"{category}/{v}")
             for k, v in manifest["files"].items() if k != "views" and k != "depths"}
    files.update({"turntable_frames": f"{category}/views", "manifest": f"{category}/manifest.json"})
    files["novel_views"] = _save_novel_views(out, cfg.out, [record.view_names[v] for v in views.targets], preds, gts)
    times.update({"turntable_s": result.timings["render_s"], "mesh_s": result.timings["mesh_s"]})
    times["save_s"] = time.perf_counter() - t
    per_view = [{"view": v, "psnr": m.psnr, "ssim": m.ssim} for v, m in zip(views.targets, metrics.views, strict=True)]
    return CategoryResult(category=category, session=session, checkpoint=checkpoint, object_id=record.object_id,
                          views=views, psnr=metrics.psnr, ssim=metrics.ssim, per_view=per_view, notes=notes,
                          seconds=times, files=files,
                          mesh_faces=manifest["mesh"]["faces"] if cfg.mesh else None)


def _category_json(r: CategoryResult) -> dict:
    pre = r.session.pretrained
    return {"checkpoint": r.checkpoint, "checkpoint_path": str(pre.path.resolve()),
            "checkpoint_sha256": pre.sha256, "checkpoint_step": pre.step, "preset": pre.spec.preset,
            "depth_prior": r.session.spec.prior.estimator, "object_id": r.object_id, "input_view": r.views.input_view,
            "target_views": list(r.views.targets), "psnr": r.psnr, "ssim": r.ssim, "per_view": r.per_view,
            "notes": r.notes, "mesh_faces": r.mesh_faces,
            "seconds": {**r.seconds, "total_s": sum(r.seconds.values())}, "files": r.files}


def run_demo(cfg: DemoConfig, device: torch.device | str = "cpu") -> dict:
    """Run every category of ``cfg`` and write ``cfg.out/demo.json``; returns its content."""
    t0 = time.perf_counter()
    unknown = [c for c in cfg.categories if c not in CATEGORIES]
    if unknown or not cfg.categories:
        raise DepthnerfError(f"--categories: choose from {', '.join(CATEGORIES)} (got {', '.join(unknown) or 'none'})")
    for flag, value, least in (("--views-stride", cfg.views_stride, 1), ("--turntable-views", cfg.turntable_views, 1)):
        if value < least:
            raise DepthnerfError(f"{flag} must be >= {least}, got {value}")
    check_mesh_resolution(cfg.mesh_resolution, none_allowed=False)
    if cfg.seed < 0:
        raise DepthnerfError(f"--seed must be >= 0 (a synthesis seed), got {cfg.seed}")
    if (problem := folder_problem(cfg.out, "--out")) is not None:  # before the checkpoints load
        raise DepthnerfError(problem)
    checkpoints = {c: cfg.checkpoints.get(c, DEFAULT_CHECKPOINTS[c]) for c in cfg.categories}
    loaded = {}
    for category, checkpoint in checkpoints.items():  # every checkpoint loads before any work starts
        t = time.perf_counter()
        loaded[category] = (load_checkpoint_for(category, checkpoint, device), time.perf_counter() - t)
    make_folder(cfg.out, "--out")
    results = []
    for category, (session, load_s) in loaded.items():
        results.append(run_category(category, session, checkpoints[category], cfg))
        results[-1].seconds = {"load_s": load_s, **results[-1].seconds}
    total = time.perf_counter() - t0
    demo = {"seed": cfg.seed, "data": "data", "views_stride": cfg.views_stride,
            "protocol": (f"SRN protocol as 'depthnerf eval': input view {results[0].views.input_view}, every "
                         f"{cfg.views_stride}-th of the other {results[0].views.others} views, training resolution, "
                         "PSNR/SSIM from depthnerf.eval.metrics on float renders"),
            "categories": {r.category: _category_json(r) for r in results},
            "seconds": total, "device": str(device), "torch_threads": torch.get_num_threads()}
    write_text_atomic(cfg.out / "demo.json", json.dumps(demo, indent=1) + "\n")
    return demo
