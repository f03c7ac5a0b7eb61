"""The SRN-protocol generator behind ``depthnerf synth``: objects, views, files, resume, dataset card.

Layout written (SRN, see :mod:`depthnerf.data.srn_format`)::

    DIR/<category>_<split>/<object_id>/intrinsics.txt, rgb/NNNNNN.png, pose/NNNNNN.txt, depth/NNNNNN.npz,
                                       mask/NNNNNN.png, mesh.ply, .synth_done.json
    DIR/<category>_card.json

``split`` is train (``views_train`` = 50 random upper-hemisphere views per object), val and test (``views_test``
= 251 spiral views each; view 64 is the standard input view). Chairs' train split is flat (``chairs_train``).

Framing (``framing``, :mod:`depthnerf.data.synth.framing`): ``srn`` (default, generator ``depthnerf-synth-2``)
frames objects as SRN's renderer does (unit bounding-box diagonal, SRN's spiral with view 64 a side view, Blender
pixel centres); ``legacy`` (``depthnerf-synth-1``) reproduces the first generator exactly (the training data of
an earlier set of shipped checkpoints). Family (``family``): ``standard`` (the shape grammars' training mix) or
``heldout`` (car and chair styles the standard family never draws, for generalisation checks); the generator id
gets ``-heldout``.

Determinism: object ``k`` of ``split`` draws everything from ``SeedSequence(seed, spawn_key=(crc32(category),
split, k))``, so files do not depend on ``--workers``, on the order of work or on resuming. Object ids are
``synth_<category>_<split>_<k:06d>``. Resume: ``.synth_done.json`` is written last (atomically) and lists the
settings; objects with it are skipped, folders without it are deleted and redone, and a marker with different
settings is an error (use a fresh ``--out``). The card is rebuilt from all markers at the end.
"""

from __future__ import annotations

import importlib.util
import json
import math
import multiprocessing
import shutil
import zlib
from collections import Counter
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path

import numpy as np
from tqdm import tqdm

from depthnerf.data import srn_format
from depthnerf.data.cameras import Intrinsics
from depthnerf.data.synth.cars import (
    CAR_REVISION,
    CAR_STYLES,
    HELDOUT_CAR_STYLES,
    build_car,
    car_style_summary,
    sample_car,
)
from depthnerf.data.synth.category import CategorySpec, category_spec
from depthnerf.data.synth.chairs import (
    ARCHETYPE_WEIGHTS,
    CHAIR_ARCHETYPES,
    CHAIR_REVISION,
    HELDOUT_ARCHETYPES,
    build_chair,
    chair_style_summary,
    sample_chair,
)
from depthnerf.data.synth.framing import DEFAULT_FRAMING, Framing, get_framing
from depthnerf.data.synth.hits import ENGINES, resolve_engine
from depthnerf.data.synth.raycast import PixelRays, Raycaster, SynthRenderConfig, render_view
from depthnerf.data.synth.views import (
    ViewConfig,
    hemisphere_eyes,
    poses_from_angles,
    poses_from_eyes,
    spiral_eyes,
    srn_hemisphere_angles,
    srn_spiral_angles,
)
from depthnerf.errors import DepthnerfError
from depthnerf.files import folder_problem, make_folder, nearest_existing, write_json_atomic

FAMILIES = ("standard", "heldout")
"""Shape families: the grammars' training mix, and styles it never draws (generalisation checks)."""


def generator_version(category: str, framing: str = DEFAULT_FRAMING, family: str = "standard") -> str:
    """Generator version of the framing plus the category's shape-grammar revision (and ``-heldout`` for the
    held-out family): it changes whenever the files generated for the same settings would change, so resuming
    never mixes objects of two revisions. ``legacy``/``standard`` gives generator 1's ids unchanged."""
    revision = CAR_REVISION if category == "cars" else CHAIR_REVISION
    suffix = "" if family == "standard" else f"-{family}"
    return f"{get_framing(framing).generator}/{category}-r{revision}{suffix}"


SPLITS = ("train", "val", "test")
"""Splits in seed order."""
MARKER = ".synth_done.json"
"""Per-object completion marker (written last)."""


@dataclass(frozen=True)
class SynthConfig:
    """What ``depthnerf synth`` generates."""

    category: str
    """``cars`` or ``chairs``."""
    out: Path
    """Dataset root; split folders and the card go inside."""
    train_objects: int = 20
    """Objects in the train split."""
    val_objects: int = 5
    """Objects in the val split."""
    test_objects: int = 5
    """Objects in the test split."""
    resolution: int = 128
    """Image size (square); the focal scales like ``Intrinsics.resized``."""
    seed: int = 0
    """Master seed."""
    workers: int = 1
    """Worker processes (1: generate in this process)."""
    views_train: int = 50
    """Views per train object (SRN: 50)."""
    views_test: int = 251
    """Views per val/test object (SRN: 251)."""
    render: SynthRenderConfig = field(default_factory=SynthRenderConfig)
    """Renderer settings."""
    progress: bool = True
    """Show a tqdm progress bar."""
    framing: str = DEFAULT_FRAMING
    """``srn`` (SRN's renderer: docs/data.md) or ``legacy`` (generator 1: an earlier set of shipped checkpoints'
    data)."""
    family: str = "standard"
    """Shape family: ``standard`` or ``heldout`` (styles the standard family never draws)."""
    raycaster: str = "auto"
    """First-hit engine: ``embree`` (embreex), ``torch`` (brute force; CUDA when there is one) or ``auto``
    (embree where embreex imports, else torch). The same images up to ties on shared edges; not part of what a
    finished object must match to be reused."""

    def counts(self) -> dict[str, int]:
        return {"train": self.train_objects, "val": self.val_objects, "test": self.test_objects}

    def get_framing(self) -> Framing:
        return get_framing(self.framing)

    def intrinsics(self) -> Intrinsics:
        """The intrinsics written to ``intrinsics.txt``."""
        return self.get_framing().file_intrinsics(self.resolution)


@dataclass(frozen=True)
class ObjectJob:
    """One object to generate (picklable, sent to a worker)."""

    config: SynthConfig
    """The run's configuration."""
    split: str
    """train, val or test."""
    index: int
    """Object number within the split."""

    @property
    def object_id(self) -> str:
        return f"synth_{self.config.category}_{self.split}_{self.index:06d}"

    @property
    def folder(self) -> Path:
        return Path(self.config.out) / f"{self.config.category}_{self.split}" / self.object_id

    def settings(self) -> dict:
        """What must match for a finished object to be reused."""
        c = self.config
        views = c.views_train if self.split == "train" else c.views_test
        return {"generator": generator_version(c.category, c.framing, c.family), "seed": c.seed, "resolution": c.resolution, "views": views,
                "antialias": c.render.antialias}


def object_rngs(seed: int, category: str, split: str, index: int) -> tuple[np.random.Generator, np.random.Generator]:
    """Independent shape and camera generators of one object, from (seed, category, split, index) only."""
    ss = np.random.SeedSequence(seed, spawn_key=(zlib.crc32(category.encode()), SPLITS.index(split), index))
    shape, views = ss.spawn(2)
    return np.random.default_rng(shape), np.random.default_rng(views)


def object_poses(split: str, n_views: int, spec: CategorySpec, rng: np.random.Generator) -> np.ndarray:
    """Camera-to-world poses of one object: random hemisphere (train) or the spiral (val/test), as the
    spec's framing places them."""
    if spec.framing != "legacy":
        angles = srn_hemisphere_angles(n_views, rng) if split == "train" else srn_spiral_angles(n_views)
        return poses_from_angles(spec.radius, *angles)
    vc = ViewConfig(radius=spec.radius)
    eyes = hemisphere_eyes(n_views, vc, rng) if split == "train" else spiral_eyes(n_views, vc)
    return poses_from_eyes(eyes)


def _read_marker(path: Path) -> dict | None:
    if not path.is_file():
        return None
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError) as err:
        raise DepthnerfError(f"{path}: unreadable completion marker ({err}); delete the object folder") from None


def job_status(job: ObjectJob) -> str:
    """``done`` (valid marker), ``partial`` (folder without marker) or ``missing``."""
    marker = _read_marker(job.folder / MARKER)
    if marker is not None:
        if marker.get("settings") != job.settings():
            raise DepthnerfError(f"{job.folder / MARKER}: object was generated with different settings "
                                 f"{marker.get('settings')} (now {job.settings()}); use a fresh --out")
        return "done"
    return "partial" if job.folder.exists() else "missing"


def generate_object(job: ObjectJob) -> dict:
    """Build, render and write one object; returns its marker (also written as the object's last file)."""
    c = job.config
    spec = category_spec(c.category, c.framing)
    shape_rng, view_rng = object_rngs(c.seed, c.category, job.split, job.index)
    if c.category == "cars":
        params = sample_car(shape_rng, family=c.family)
        mesh, summary = build_car(params), car_style_summary(params)
    else:
        params = sample_chair(shape_rng, family=c.family)
        mesh, summary = build_chair(params, spec.diagonal), chair_style_summary(params)
    n_views = job.settings()["views"]
    poses = object_poses(job.split, n_views, spec, view_rng)
    folder = job.folder
    if folder.exists():
        shutil.rmtree(folder)
    for sub in ("rgb", "pose", "depth", "mask"):
        (folder / sub).mkdir(parents=True)
    intr = c.intrinsics()
    srn_format.write_intrinsics(folder / "intrinsics.txt", intr)
    mesh.to_trimesh().export(folder / "mesh.ply")
    caster, rays = Raycaster(mesh, c.raycaster), PixelRays(c.get_framing().render_intrinsics(c.resolution))
    z_min, z_max, coverage = math.inf, 0.0, []
    for v, c2w in enumerate(poses):
        view = render_view(caster, c2w, rays, c.render)
        name = f"{v:06d}"
        srn_format.write_rgb(folder / "rgb" / f"{name}.png", view.rgb)
        srn_format.write_pose(folder / "pose" / f"{name}.txt", c2w)
        srn_format.write_depth(folder / "depth" / f"{name}.npz", view.depth)
        srn_format.write_mask(folder / "mask" / f"{name}.png", view.mask)
        if view.mask.any():
            z = view.depth[view.mask]
            z_min, z_max = min(z_min, float(z.min())), max(z_max, float(z.max()))
        coverage.append(float(view.mask.mean()))
    lo, hi = mesh.vertices.min(0), mesh.vertices.max(0)
    marker = {"object_id": job.object_id, "split": job.split, "settings": job.settings(), "style": summary,
              "faces": int(len(mesh.faces)), "raycaster": caster.engine, "bbox_min": [round(float(x), 6) for x in lo],
              "bbox_max": [round(float(x), 6) for x in hi], "depth_min": round(z_min, 6), "depth_max": round(z_max, 6),
              "mask_coverage_mean": round(float(np.mean(coverage)), 6)}
    write_json_atomic(folder / MARKER, marker)
    return marker


def _init_worker() -> None:
    import torch

    torch.set_num_threads(1)


VIEW_BYTES_FLOOR = 1024
"""Bytes a view's four files take at least, besides its pixels (a 64 px view of the benchmark takes 2.3 KB)."""
PIXEL_BYTES_FLOOR = 0.25
"""Bytes a pixel takes at least over a view's compressed RGB, depth and mask files."""


def check_disk_space(out: Path, todo: list[ObjectJob]) -> None:
    """Refuse, before any object is made, work whose files cannot fit the free space under ``out``: a lower bound
    (:data:`VIEW_BYTES_FLOOR`, :data:`PIXEL_BYTES_FLOOR` a view) against ``shutil.disk_usage``. Huge view counts
    would otherwise end in a full disk or the kernel's out-of-memory kill, without a message."""
    views = sum(j.settings()["views"] for j in todo)
    if not views:
        return
    need = views * (VIEW_BYTES_FLOOR + PIXEL_BYTES_FLOOR * todo[0].config.resolution ** 2)
    free = shutil.disk_usage(nearest_existing(out)).free
    if need > free:
        objects = f"{len(todo):,} object{'s' if len(todo) > 1 else ''}"
        raise DepthnerfError(f"{out}: {objects} of {views:,} views in all need at least {need / 1e9:,.1f} GB, and "
                             f"the disk has {free / 1e9:,.1f} GB free; lower --views-train, --views-test, "
                             "--resolution or the object counts")


def _run_jobs(config: SynthConfig, jobs: list[ObjectJob], todo: list[ObjectJob]) -> None:
    """Generate ``todo`` (the unfinished ones of ``jobs``), in this process or in a pool, with a progress bar."""
    bar = tqdm(total=len(jobs), initial=len(jobs) - len(todo), desc=f"synth {config.category}", unit="obj",
               disable=not config.progress)
    if config.workers == 1 or len(todo) <= 1:
        import torch

        threads = torch.get_num_threads()
        torch.set_num_threads(1)
        try:
            for job in todo:
                generate_object(job)
                bar.update(1)
        finally:
            torch.set_num_threads(threads)
    else:
        ctx = multiprocessing.get_context("forkserver")
        ctx.set_forkserver_preload(["depthnerf.data.synth.generate"])
        with ProcessPoolExecutor(max_workers=config.workers, mp_context=ctx, initializer=_init_worker) as pool:
            futures = [pool.submit(generate_object, job) for job in todo]
            for fut in as_completed(futures):
                fut.result()
                bar.update(1)
    bar.close()


def generate(config: SynthConfig) -> dict:
    """Generate (or finish) a dataset; returns the dataset card (also written to ``<out>/<category>_card.json``)."""
    spec = category_spec(config.category, config.framing)
    if config.family not in FAMILIES:
        raise DepthnerfError(f"synth: unknown family {config.family!r} (expected one of {', '.join(FAMILIES)})")
    for name, n in config.counts().items():
        if n < 0:
            raise DepthnerfError(f"synth: --{name}-objects must be >= 0 (got {n})")
    if not any(config.counts().values()):
        raise DepthnerfError("synth: --train-objects, --val-objects and --test-objects are all 0: nothing to make")
    for flag, value, least in (("--resolution", config.resolution, 8), ("--views-train", config.views_train, 1),
                               ("--views-test", config.views_test, 1), ("--workers", config.workers, 1),
                               ("--seed", config.seed, 0)):
        if value < least:
            raise DepthnerfError(f"synth: {flag} must be >= {least} (got {value})")
    if config.raycaster not in ENGINES:
        raise DepthnerfError(f"synth: --raycaster must be one of {', '.join(ENGINES)} (got {config.raycaster!r})")
    if config.raycaster == "embree" and importlib.util.find_spec("embreex") is None:
        raise DepthnerfError("synth: --raycaster embree needs embreex (pip install embreex); --raycaster torch or "
                             "auto needs nothing more")
    config = replace(config, raycaster=resolve_engine(config.raycaster))  # once here, not in every worker
    out = Path(config.out)
    if (problem := folder_problem(out, "--out")) is not None:
        raise DepthnerfError(problem)
    jobs = [ObjectJob(config, split, k) for split in SPLITS for k in range(config.counts()[split])]
    todo = [j for j in jobs if job_status(j) != "done"]
    check_disk_space(out, todo)  # before anything is written
    make_folder(out, "--out")
    try:
        _run_jobs(config, jobs, todo)
    except OSError as err:  # disk full, permissions, ...
        raise DepthnerfError(f"{err.filename or out}: cannot write ({err.strerror or err})") from None
    card = build_card(config, spec, [_read_marker(j.folder / MARKER) for j in jobs])
    write_json_atomic(out / f"{config.category}_card.json", card)
    return card


def _grammar(config: SynthConfig) -> dict:
    """What the shape grammar draws from, for the card."""
    if config.category == "cars":
        styles = CAR_STYLES if config.family == "standard" else HELDOUT_CAR_STYLES
        return {"styles": {s: round(1 / len(styles), 4) for s in styles}}
    if config.family == "standard":
        return {"archetypes": dict(zip(CHAIR_ARCHETYPES, ARCHETYPE_WEIGHTS, strict=True))}
    return {"archetypes": {a: round(1 / len(HELDOUT_ARCHETYPES), 4) for a in HELDOUT_ARCHETYPES}}


def build_card(config: SynthConfig, spec: CategorySpec, markers: list[dict]) -> dict:
    """The dataset card: generator, seed, counts, protocol, cameras, z-range, lighting and styles used."""
    intr = config.intrinsics()
    styles: dict[str, dict[str, dict[str, int]]] = {}
    for m in markers:
        for key, value in m["style"].items():
            if key != "finish":
                styles.setdefault(m["split"], {}).setdefault(key, Counter())[value] += 1
    depth = [(m["depth_min"], m["depth_max"]) for m in markers if m["depth_max"] > 0]
    fr = config.get_framing()
    if fr.name == "legacy":
        vc = ViewConfig(radius=spec.radius)
        protocol = {
            "train_cameras": "uniform in area on the upper hemisphere (z = r*u, u ~ U(0, sin(max_elev)), "
                             "azimuth ~ U(0, 2pi))",
            "test_cameras": "Archimedean spiral, elevation 0 -> max_elev linear in the view index, azimuth step "
                            f"{vc.spiral_azimuth_span} rad over the spiral",
            "input_view": vc.input_view, "input_view_azimuth_deg": vc.input_azimuth_deg,
            "max_elevation_deg": vc.max_elevation_deg}
    else:
        protocol = {
            "train_cameras": "uniform in area on the upper hemisphere (z = r*u, u ~ U(0, 1), azimuth ~ U(0, 2pi))",
            "test_cameras": "SRN's Archimedean spiral (shapenet_renderer get_archimedean_spiral): elevation "
                            "90 deg * k/(n-1), azimuth 20 rad * k/(n-1) + 20 rad - 90 deg from +x (front) "
                            "towards +y (left)",
            "input_view": 64, "input_view_azimuth_deg": 269.27, "max_elevation_deg": 90.0}
    return {
        "generator": generator_version(config.category, config.framing, config.family), "category": config.category,
        "seed": config.seed, "framing": fr.name, "family": config.family,
        "counts": config.counts(), "resolution": config.resolution,
        "layout": f"{config.category}_<split>/<object_id>/{{intrinsics.txt,rgb,pose,depth,mask,mesh.ply}}",
        "protocol": {"train_views": config.views_train, "test_views": config.views_test, **protocol},
        "camera": {"radius": spec.radius, "focal": intr.focal, "cx": intr.cx, "cy": intr.cy,
                   "height": intr.height, "width": intr.width, "axes": "OpenCV camera-to-world, world +z up",
                   "pixel_center": fr.pixel_center,
                   "pixel_center_meaning": "pixel (i, j) of every image is centred at (j + c, i + c) in these "
                                           "intrinsics (train with --data.pixel_center c to read it exactly)"},
        "objects": {"bbox_diagonal": spec.diagonal, "centre": [0.0, 0.0, 0.0], "front": "+x", "up": "+z"},
        "z_range": {"near": spec.z_near, "far": spec.z_far, "kind": "ray distance (pixelNeRF bounds)",
                    "measured_z_depth_min": min((d[0] for d in depth), default=None),
                    "measured_z_depth_max": max((d[1] for d in depth), default=None)},
        "rendering": {"renderer": "ray casting (first hits: embreex or brute force in torch, per object's "
                                  "raycaster), exact float64 depth on the hit triangle",
                      "raycasters": dict(sorted(Counter(m.get("raycaster", "embree") for m in markers).items())),
                      "antialiasing": "adaptive: RGB of edge pixels averaged over centre + 4 RGSS sub-samples; "
                                      "depth and mask from the centre ray only" if config.render.antialias
                      else "none", "background": config.render.background,
                      "lighting": asdict(config.render.lighting)},
        "shape_grammar": _grammar(config),
        "styles": {split: {k: dict(sorted(v.items())) for k, v in per.items()} for split, per in styles.items()},
    }
