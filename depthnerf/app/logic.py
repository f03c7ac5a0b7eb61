"""What ``depthnerf app`` does, as plain functions (no Gradio here: the page in :mod:`depthnerf.app.page` only
wires these to widgets, and tests call them without a browser).

One request = one :class:`RunRequest` -> :meth:`AppSession.run` -> one :class:`RunOutputs`:

1. the upload is checked (:func:`check_upload`: a PNG, JPEG or WebP file, the rule of
   :func:`depthnerf.reconstruct.photo.check_photo_format`; everything else
   :func:`depthnerf.reconstruct.photo.prepare_photo` checks: unreadable/truncated files, sides < 16 px, no
   foreground, a cluttered background);
2. the checkpoint is loaded once per (checkpoint, depth prior) into an inference session (the device's policy
   included, as for every user of :class:`~depthnerf.infer.session.InferenceSession`) and kept
   (:class:`ModelCache`); the page's depth prior applies to depth-aware checkpoints (a baseline one has none);
3. :meth:`Reconstructor.reconstruct <depthnerf.reconstruct.reconstructor.Reconstructor.reconstruct>` runs with
   the page's settings and :meth:`~depthnerf.reconstruct.reconstructor.Reconstructor.save` writes its outputs
   (the same code path as ``depthnerf reconstruct``; the app adds nothing to the pipeline);
4. the written paths are collected: prepared input, depth prior, MP4 + GIF orbit, GLB for the viewer, and the
   GLB, PLY mesh and PLY point cloud for download.

Any :class:`~depthnerf.errors.DepthnerfError` becomes ``RunOutputs.message`` = ``error: <one line>`` (the upload's
temporary path replaced by its file name, the command-line flags a message suggests replaced by the page's
fields: :data:`PAGE_WORDS`); any other exception becomes ``internal error (<type>): <message>`` with the
traceback on the server's stderr. The server keeps serving either way.

Background removal
    The page's "Remove background" box is ``ReconstructConfig.background_removal`` ``auto`` (ticked) or ``off``;
    it starts ticked when the ``[bg]`` extra (rembg, onnxruntime) is installed (:func:`background_installed`).
    The model is the page's "Background model" field, else ``AppConfig.background_model``, else rembg's
    ``u2net`` (:mod:`depthnerf.reconstruct.background`).

Foreground ratio
    The page's "foreground ratio" is TripoSR's quantity: the object's longer bounding-box side over the side of
    the square frame. It is exactly ``ReconstructConfig.fill`` (``framing="auto"``), so it is passed unchanged.
    TripoSR's default 0.85 is the framing of TripoSR's own training renders; each checkpoint was trained at the
    fill of its training data's framing (:attr:`~depthnerf.reconstruct.reconstructor.Reconstructor.default_fill`),
    which is therefore the page's default for each model (:meth:`AppSession.training_fill`).
"""

from __future__ import annotations

import importlib.util
import shutil
import socket
import sys
import tempfile
import threading
import time
import traceback
from collections import OrderedDict
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from depthnerf.app.messages import (
    as_number,
    check_local_paths,
    check_ratio,
    check_upload,
    check_views,
    display_name,
    one_line,
)
from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.recommended import RECOMMENDED

EXAMPLES_DIR = Path(__file__).resolve().parent / "examples"
"""Bundled example photos (``scripts/make_app_examples.py``)."""
DEPTH_PRIORS = ("trained", "bundled", "depth-anything-v2")
"""Depth priors the page offers; ``trained``: the one the checkpoint was trained with (``bundled`` for the shipped
models), as ``depthnerf reconstruct`` without ``--depth``."""
SHIPPED_MODELS = {"car": RECOMMENDED["cars"], "chair": RECOMMENDED["chairs"]}
"""Page label -> the best shipped checkpoint per category (:data:`~depthnerf.pretrained.recommended.RECOMMENDED`)."""
ProgressFn = Callable[[float, str], None]


@dataclass(frozen=True)
class AppConfig:
    """How ``depthnerf app`` serves the page."""

    host: str = "127.0.0.1"
    """Interface to bind (127.0.0.1: this machine only)."""
    port: int = 7860
    """TCP port."""
    checkpoints: tuple[str, ...] = tuple(SHIPPED_MODELS.values())
    """Checkpoints offered in the model menu (shipped names or local paths)."""
    share: bool = False
    """Ask Gradio for a public share link (off unless ``--share``)."""
    views: int = 8
    """Default number of orbit views (the slider's start value)."""
    max_views: int = 36
    """Largest number of orbit views the slider allows."""
    mesh_resolution: int = 64
    """Marching-cubes samples along the longest side of the mesh box (``ReconstructConfig.mesh_resolution``)."""
    device: str = "cpu"
    """Torch device of the models."""
    work_dir: Path | None = None
    """Where runs are written (None: a fresh temporary folder)."""
    keep_runs: int = 16
    """Run folders kept on disk; older ones are deleted."""
    max_cached_models: int = 3
    """Loaded (checkpoint, depth prior) pairs kept in memory."""
    allow_checkpoint_paths: bool = True
    """Offer the free "local checkpoint path" and "background model" fields and accept local paths in the
    requests (off when sharing publicly: then a request naming a local file or folder is refused,
    :func:`~depthnerf.app.messages.check_local_paths`, whichever way it comes, the page or its HTTP API)."""
    background_model: str | None = None
    """Background model when the page's field is empty (rembg name or ONNX file; None: rembg's u2net)."""


@dataclass(frozen=True)
class RunRequest:
    """One reconstruction as the page asks for it."""

    image: str | Path | None
    """Path of the uploaded (or example) image; None = nothing uploaded."""
    model: str
    """A model-menu entry (shipped name or path; a page label of :data:`SHIPPED_MODELS` also works)."""
    checkpoint_path: str = ""
    """A local checkpoint path that overrides ``model`` when not empty."""
    depth_prior: str = "trained"
    """One of :data:`DEPTH_PRIORS` (ignored by checkpoints without a depth prior)."""
    depth_checkpoint: str = ""
    """Weights of a Depth Anything V2 prior: a hub id or local directory ("" = its default, or with ``trained``
    the checkpoint's own); ignored for the bundled prior."""
    foreground_ratio: float | None = None
    """Object's longer side / frame side (``ReconstructConfig.fill``); None = the checkpoint's training fill."""
    elevation: float = 20.0
    """Input camera (and orbit) elevation, degrees."""
    views: int = 8
    """Orbit views."""
    facing: float | str | None = 90.0
    """Which way the object's front points (``ReconstructConfig.facing``; models with mirror-symmetric
    conditioning only); ``"auto"`` = estimated from the photo; None = no symmetry plane."""
    remove_background: bool = True
    """Remove the background of a photo without alpha with a background model when one is installed."""
    background_model: str = ""
    """rembg model name or ONNX file ("" = ``AppConfig.background_model``, else rembg's u2net)."""
    mesh_level: str = "local"
    """The mesh's level rule, one of :data:`~depthnerf.render.mesh_level.LEVEL_RULES` (the page offers ``local``,
    the default, which keeps thin parts in a looser surface, and ``auto``, one tight piece)."""
    mesh_colors: str = "photo"
    """The mesh's vertex colour rule, one of :data:`~depthnerf.render.mesh_colors.MESH_COLOR_RULES` (``photo``, the
    default: the photo's own colours where it sees the surface, spread into the rest; ``normal-ray``: the field's
    colour seen along each vertex normal)."""
    guided: bool = True
    """Render the orbit with depth-guided sampling at its default budget (``ReconstructConfig.guided``): on the
    shipped app models within 0.04 dB of their own sampler and about twice as fast (docs/RESULTS.md, "Depth-guided
    sampling on the shipped checkpoints"); False: the checkpoint's own sampler."""


@dataclass
class RunOutputs:
    """What one request produced (paths of files written by ``Reconstructor.save``)."""

    ok: bool
    """True when the reconstruction ran."""
    message: str
    """One line for the status box (``error: ...`` on failure)."""
    input_image: Path | None = None
    """The prepared input: masked, recentred, on white, at the model's resolution."""
    input_mask: Path | None = None
    """Its mask."""
    depth_prior: Path | None = None
    """The normalised depth prior the encoder saw (None for a model without a prior)."""
    video: Path | None = None
    """Orbit as MP4 (None when imageio-ffmpeg is missing)."""
    gif: Path | None = None
    """Orbit as GIF."""
    viewer_glb: Path | None = None
    """Mesh for the 3D viewer (mesh.glb, written +y up; None when the mesh is empty)."""
    downloads: list[Path] = field(default_factory=list)
    """mesh.glb, mesh.ply, points.ply."""
    seconds: float = 0.0
    """Wall time of the request."""
    details: str = ""
    """Markdown: preprocessing notes, settings and timings."""


def background_installed() -> bool:
    """Whether the ``[bg]`` extra (rembg and onnxruntime) is installed."""
    return all(importlib.util.find_spec(m) is not None for m in ("rembg", "onnxruntime"))


def check_port(host: str, port: int) -> None:
    """One line when ``host:port`` cannot be bound (in use, or ``host`` is no address of this machine), checked
    before the page loads anything."""
    try:
        family, kind, proto, _, address = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM,
                                                             flags=socket.AI_PASSIVE)[0]
    except (socket.gaierror, UnicodeError) as err:
        raise DepthnerfError(f"--host {host}: not an address of this machine ({err})") from None
    with socket.socket(family, kind, proto) as probe:
        probe.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)  # as the server binds: TIME_WAIT is no conflict
        try:
            probe.bind(address)
        except OSError as err:
            raise DepthnerfError(f"cannot serve on {host}:{port} ({err.strerror or err}); pass another --port") from None


def examples() -> list[Path]:
    """The bundled example photos."""
    return sorted(EXAMPLES_DIR.glob("*.png"))


def resolve_model(request: RunRequest) -> str:
    """Checkpoint of a request: the path field if filled in, else the menu entry (labels mapped)."""
    checkpoint = request.checkpoint_path.strip() or request.model
    return SHIPPED_MODELS.get(checkpoint, checkpoint)


class ModelCache:
    """Loaded :class:`~depthnerf.reconstruct.reconstructor.Reconstructor` per (checkpoint, prior, prior weights),
    least recently used first out."""

    def __init__(self, device: str = "cpu", capacity: int = 3) -> None:
        self.device = device
        self.capacity = max(1, capacity)
        self._models: OrderedDict[tuple[str, str, str], Any] = OrderedDict()
        self._lock = threading.Lock()

    def get(self, checkpoint: str, depth_prior: str = "trained", depth_checkpoint: str = ""):
        """The Reconstructor (loaded on first use)."""
        from depthnerf import Reconstructor
        from depthnerf.pretrained.load import load_pretrained

        if depth_prior not in DEPTH_PRIORS:
            raise DepthnerfError(f"depth prior must be one of {', '.join(DEPTH_PRIORS)}, got {depth_prior!r}")
        key = (checkpoint, depth_prior, depth_checkpoint.strip())
        with self._lock:
            if key in self._models:
                self._models.move_to_end(key)
                return self._models[key]
            pretrained = load_pretrained(checkpoint, self.device)
            depth_aware = pretrained.spec.depth_aware  # the page's prior menu is for depth-aware models
            estimator = pretrained.spec.prior.estimator if depth_prior == "trained" else depth_prior
            weights = (key[2] or None) if depth_aware and estimator == "depth-anything-v2" else None
            rec = Reconstructor.from_pretrained(pretrained, self.device, depth_checkpoint=weights,
                                                depth_estimator=estimator if depth_aware else None)
            self._models[key] = rec
            while len(self._models) > self.capacity:
                self._models.popitem(last=False)
            return rec


def run_folders(work_dir: Path) -> dict[int, Path]:
    """The run folders (``run-NNNNNN``) in ``work_dir`` by number."""
    return {int(d.name[4:]): d for d in work_dir.glob("run-*") if d.name[4:].isdigit()}


def model_resolution(rec) -> int:
    """Training (input) resolution of a loaded Reconstructor."""
    return rec.session.spec.resolution


class AppSession:
    """The app's state: its config, the model cache and the run folders."""

    def __init__(self, config: AppConfig) -> None:
        self.config = config
        self.models = ModelCache(config.device, config.max_cached_models)
        if config.work_dir is None:
            self.work_dir = Path(tempfile.mkdtemp(prefix="depthnerf-app-"))
        else:
            self.work_dir = Path(config.work_dir)
            self.work_dir.mkdir(parents=True, exist_ok=True)
        self._runs = max(run_folders(self.work_dir), default=0)  # a reused --work-dir continues its numbering
        self._lock = threading.Lock()

    def model_defaults(self, model: str, checkpoint_path: str = "") -> tuple[float, bool]:
        """The page's defaults for a model, from one load: the fill (foreground ratio) it was trained at (see the
        module docstring) and whether it carries a facing head (the page then ticks "Estimate the facing from the
        photo")."""
        request = RunRequest(None, model, checkpoint_path)
        self.check_paths(request)
        loaded = self.models.get(resolve_model(request))
        return loaded.default_fill, loaded.has_facing_head

    def training_fill(self, model: str, checkpoint_path: str = "") -> float:
        """The fill (foreground ratio) the model was trained at: :meth:`model_defaults`' first value."""
        return self.model_defaults(model, checkpoint_path)[0]

    def check_paths(self, request: RunRequest) -> None:
        """One line when ``request`` names a local file or folder, or a model outside the menu, and
        ``AppConfig.allow_checkpoint_paths`` is off."""
        if not self.config.allow_checkpoint_paths:
            check_local_paths(request.checkpoint_path, request.background_model, request.depth_checkpoint)
            if resolve_model(request) not in self.config.checkpoints:
                raise DepthnerfError(f"model {request.model!r} is not in this page's menu")

    def preview(self, request: RunRequest) -> tuple[np.ndarray | None, str]:
        """The preprocessing alone (mask, recentre, white background, resize): ``(image or None, message)``."""
        from depthnerf import prepare_photo
        from depthnerf.reconstruct.exports import to_u8

        try:
            path = check_upload(request.image)
            self.check_paths(request)
            check_ratio(request.foreground_ratio)
            rec = self.models.get(resolve_model(request))
            fill = rec.default_fill if request.foreground_ratio is None else request.foreground_ratio
            prep = prepare_photo(path, None, model_resolution(rec), "auto", fill,
                                 rec.background_remover(*self.background(request)))
        except Exception as err:  # noqa: BLE001 - every failure is one line on the page
            if not isinstance(err, DepthnerfError):
                traceback.print_exc(file=sys.stderr)
            return None, one_line(err, request.image)
        return (to_u8(prep.image),
                f"ready: {display_name(request.image)}, " + "; ".join(prep.notes))

    def background(self, request: RunRequest) -> tuple[str, str | None]:
        """``(ReconstructConfig.background_removal, background_model)`` of a request."""
        model = request.background_model.strip() or self.config.background_model
        return ("auto" if request.remove_background else "off"), model or None

    def _new_run_dir(self) -> Path:
        """A fresh run folder, created here (so it is this request's alone, also when another app process shares
        the ``--work-dir``: its number follows every run folder there, and a name taken meanwhile is skipped); the
        oldest beyond ``keep_runs`` are deleted."""
        with self._lock:
            while True:
                self._runs = max([self._runs, *run_folders(self.work_dir)]) + 1
                run = self.work_dir / f"run-{self._runs:06d}"
                try:
                    run.mkdir(parents=True)
                    break
                except FileExistsError:  # another process took this number: take the next one
                    continue
            runs = [folder for _, folder in sorted(run_folders(self.work_dir).items())]
        for stale in runs[: max(0, len(runs) - max(1, self.config.keep_runs))]:
            shutil.rmtree(stale, ignore_errors=True)
        return run

    def run(self, request: RunRequest, progress: ProgressFn | None = None) -> RunOutputs:
        """Reconstruct one upload; never raises (failures are :attr:`RunOutputs.message`)."""
        t0 = time.perf_counter()
        try:
            out = self._run(request, progress or (lambda frac, text: None))
        except Exception as err:  # noqa: BLE001 - every failure is one line on the page
            if not isinstance(err, DepthnerfError):
                traceback.print_exc(file=sys.stderr)
            return RunOutputs(ok=False, message=one_line(err, request.image), seconds=time.perf_counter() - t0)
        out.seconds = time.perf_counter() - t0
        out.message = f"done in {out.seconds:.1f} s: {out.message}"
        return out

    def _run(self, request: RunRequest, progress: ProgressFn) -> RunOutputs:
        from depthnerf import ReconstructConfig
        from depthnerf.render.mesh_colors import MESH_COLOR_RULES
        from depthnerf.render.mesh_level import LEVEL_RULES

        path = check_upload(request.image)
        self.check_paths(request)
        check_views(request.views, self.config.max_views)
        check_ratio(request.foreground_ratio)
        if request.mesh_level not in LEVEL_RULES:
            raise DepthnerfError(f"mesh level must be one of {', '.join(LEVEL_RULES)}, got {request.mesh_level!r}")
        if request.mesh_colors not in MESH_COLOR_RULES:
            raise DepthnerfError(f"mesh colours must be one of {', '.join(MESH_COLOR_RULES)}, got "
                                 f"{request.mesh_colors!r}")
        checkpoint = resolve_model(request)
        progress(0.0, f"loading {checkpoint}")
        rec = self.models.get(checkpoint, request.depth_prior, request.depth_checkpoint)
        progress(0.05, "reconstructing")
        mode, background_model = self.background(request)
        from depthnerf.infer.facing import AUTO

        facing = request.facing if request.facing in (None, AUTO) else as_number(request.facing, "the object facing")
        cfg = ReconstructConfig(views=int(request.views), elevation=as_number(request.elevation, "the elevation"),
                                fill=request.foreground_ratio, mesh_resolution=self.config.mesh_resolution,
                                mesh_threshold=request.mesh_level, mesh_colors=request.mesh_colors,
                                progress=True, background_removal=mode, background_model=background_model,
                                facing=facing,
                                guided=bool(request.guided))
        result = rec.reconstruct(path, config=cfg)
        progress(0.95, "writing outputs")
        run_dir = self._new_run_dir()
        manifest = rec.save(result, run_dir)
        return collect_outputs(run_dir, manifest, display_name(path))


def collect_outputs(run_dir: Path, manifest: dict[str, Any], name: str) -> RunOutputs:
    """The page's outputs from a folder written by ``Reconstructor.save`` and its manifest."""
    files = manifest["files"]

    def at(key: str) -> Path | None:
        return run_dir / files[key] if files.get(key) else None

    glb = at("mesh_glb")
    viewer = None if manifest["mesh"]["empty"] else glb  # mesh.glb is +y up, as glTF viewers expect
    settings = manifest["settings"]
    timings = ", ".join(f"{k.removesuffix('_s')} {v:.1f} s" for k, v in manifest["timings"].items())
    prior = settings["depth_estimator"]
    details = "\n".join("- " + line for line in [
        f"**Input** {name}: " + "; ".join(manifest["input"]["notes"]),
        f"**Model** {Path(manifest['checkpoint']).name} (category {settings['category']}, "
        f"{settings['resolution']} px), depth prior **{prior}**"
        + (f" ({settings['depth_checkpoint']})" if prior != "none" and settings.get("depth_checkpoint") else ""),
        "**Background** " + (f"removed by the {settings['background_model']} model "
                             f"({settings['background_model_licence']})" if settings.get("background_model")
                             else "the alpha channel or the border colour decided (no background model ran)"),
        f"**Camera** elevation {settings['elevation']:g} deg, radius {settings['radius']:g}, "
        f"fill {settings['fill']:.2f}, {settings['views']} orbit views, "
        + (f"depth-guided sampling ({settings['guided_sampling']} samples per ray)" if settings.get("guided_sampling")
           else "the model's own sampler"),
        f"**Symmetry** {settings.get('symmetry', 'off: the model has no mirror-symmetric conditioning')}",
        ("**Mesh** none (--mesh-resolution 0)" if not manifest["mesh"].get("made", True) else
         f"**Mesh** {manifest['mesh']['faces']} faces" + (" (empty: nothing dense enough)" if viewer is None else "")
         + f", {settings['mesh_color_rule']} colours")
        + f", {manifest['point_cloud']['points']} points",
        f"**Timings** {timings}",
        *([] if files.get("turntable_mp4") else [f"**MP4** {manifest['turntable_mp4_status']}"]),
    ])
    summary = (f"{settings['views']} views, mesh {manifest['mesh']['faces']} faces, "
               f"{manifest['point_cloud']['points']} points, depth prior {prior}")
    return RunOutputs(ok=True, message=summary, input_image=at("input"), input_mask=at("input_mask"),
                      depth_prior=at("depth_prior"), video=at("turntable_mp4"), gif=at("turntable_gif"),
                      viewer_glb=viewer, downloads=[p for p in (glb, at("mesh_ply"), at("point_cloud")) if p],
                      details=details)
