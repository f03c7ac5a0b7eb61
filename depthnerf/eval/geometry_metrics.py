"""3D metrics between a predicted and a ground-truth mesh: Chamfer-L1 and F-score from surface samples.

Frame and units
    Both meshes in world coordinates (the frame of the SRN poses and of ``mesh.ply``). With
    ``GeometryConfig.normalize`` (default) every distance, and ``tau``, is in units of the ground-truth mesh's
    bounding-box **diagonal**: ShapeNet/SRN objects are normalised to a unit diagonal, so the numbers are world
    distances there, and the synthetic objects (other diagonals) stay comparable.

Sampling
    ``n_points`` area-weighted surface samples per mesh (``trimesh.sample.sample_surface``), both meshes with the same
    seed, so results are deterministic and identical meshes give exactly Chamfer 0 and F-score 1. Nearest
    neighbours by ``scipy.spatial.cKDTree``.

Ground truth of a dataset object (:func:`object_geometry`)
    The synthetic ``mesh.ply`` files contain interior faces (parts are unions of closed primitives), which no view
    sees and no image-based method can recover; sampling them inflates completeness and Chamfer. So when the
    object has depth maps (``depth/NNNNNN.npz``, camera z-depth, 0 = background), the GT samples are the
    **visible surface**: every object pixel of ALL its views back-projected (``x_cam = z * ((u - cx)/f, (v - cy)/f,
    1)``, ``x_world = R x_cam + t``, :mod:`depthnerf.data.cameras`), evenly subsampled to ``n_points``
    (:func:`visible_surface_points`). Without depth maps the samples come from ``mesh.ply``. The normalising
    diagonal is ``mesh.ply``'s either way; ``GeometryMetrics.ground_truth`` and ``summary.json`` ``geometry_gt``
    say which GT was used. The predicted side is always the marching-cubes mesh's surface samples.

Definitions (Occupancy Networks / Tatarchenko et al. 2019 conventions)
    accuracy = mean over predicted samples of the distance to the nearest GT sample;
    completeness = the same from GT samples to predicted samples;
    **Chamfer-L1 = (accuracy + completeness) / 2** (the mean, not the sum, of the two directed means);
    precision = fraction of predicted samples within ``tau`` of GT, recall = fraction of GT samples within ``tau``
    of the prediction; **F-score@tau = 2 P R / (P + R)** (0 when P + R = 0). Default ``tau = 0.01`` (1% of the
    object's diagonal, Tatarchenko et al.'s choice).

Floaters (beyond the paper): **floater fraction** = the fraction of the predicted surface (its area-weighted
samples) lying outside the ground-truth mesh's axis-aligned bounding box grown by ``floater_margin`` (in GT
diagonals; default 0.05) on every side. Density the input view never asked for (e.g. white slabs above a car,
invisible on the white background) shows up here even when Chamfer-L1 hides it behind a good completeness.

Empty prediction (no faces or zero area, e.g. a density that never reached the marching-cubes level): worst-case
values, no error: accuracy = completeness = Chamfer-L1 = one GT diagonal (1.0 when normalised), precision =
recall = F-score = 0, floater fraction 0, and ``empty_prediction = True``.
"""

from __future__ import annotations

from collections import Counter
from collections.abc import Sequence
from dataclasses import asdict, dataclass, replace

import numpy as np
import torch
import trimesh
from jaxtyping import Float
from scipy.spatial import cKDTree

from depthnerf.data import srn_format
from depthnerf.data.cameras import Intrinsics, backproject
from depthnerf.data.mesh_file import read_mesh
from depthnerf.data.srn import ObjectRecord
from depthnerf.errors import DepthnerfError


@dataclass(frozen=True)
class GeometryConfig:
    """How meshes are compared."""

    n_points: int = 100_000
    """Surface samples per mesh."""
    tau: float = 0.01
    """F-score distance threshold (in GT diagonals when ``normalize``, else world units)."""
    seed: int = 0
    """Sampling seed (the same for both meshes)."""
    normalize: bool = True
    """Express distances in units of the GT bounding-box diagonal."""
    floater_margin: float = 0.05
    """The GT bounding box is grown by this (in GT diagonals) on every side before counting floaters."""
    depth_pixel_center: float = 0.0
    """Pixel-centre convention of the dataset's depth maps (its card's ``camera.pixel_center``; 0.5 for
    ``depthnerf synth --framing srn``), used to back-project them into the visible-surface ground truth."""


@dataclass(frozen=True)
class GeometryMetrics:
    """Chamfer-L1 and F-score of one predicted mesh against its ground truth."""

    chamfer_l1: float
    """(accuracy + completeness) / 2."""
    accuracy: float
    """Mean distance from predicted samples to the GT surface samples."""
    completeness: float
    """Mean distance from GT samples to the predicted surface samples."""
    precision: float
    """Fraction of predicted samples within ``tau`` of GT."""
    recall: float
    """Fraction of GT samples within ``tau`` of the prediction."""
    fscore: float
    """Harmonic mean of precision and recall."""
    tau: float
    """The F-score threshold used (same units as the distances)."""
    scale: float
    """World length of one distance unit (the GT diagonal when normalised, else 1)."""
    empty_prediction: bool
    """True when the predicted mesh had no surface (worst-case values above)."""
    ground_truth: str = "mesh.ply"
    """Where the GT samples came from (``mesh.ply`` or ``visible surface from N depth maps``)."""
    floater_fraction: float = 0.0
    """Fraction of the predicted surface outside the GT bounding box grown by ``floater_margin``."""


def sample_surface(mesh: trimesh.Trimesh, n_points: int, seed: int) -> Float[np.ndarray, "N 3"]:
    """``n_points`` area-weighted samples of the mesh surface (deterministic for a seed)."""
    points, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    return np.asarray(points, dtype=np.float64)


def nearest_distances(src: Float[np.ndarray, "N 3"], dst: Float[np.ndarray, "M 3"]) -> Float[np.ndarray, " N"]:
    """Euclidean distance from every ``src`` point to its nearest ``dst`` point."""
    dist, _ = cKDTree(dst).query(src, k=1)
    return np.asarray(dist, dtype=np.float64)


def outside_box(points: Float[np.ndarray, "N 3"], lo: Float[np.ndarray, " 3"], hi: Float[np.ndarray, " 3"],
                margin: float) -> Float[np.ndarray, " N"]:
    """True for the points outside the box ``[lo - margin, hi + margin]`` (per axis)."""
    return np.any((points < lo - margin) | (points > hi + margin), axis=-1)


def floater_fraction(pred: trimesh.Trimesh, gt: trimesh.Trimesh, config: GeometryConfig = GeometryConfig(),
                     pred_points: Float[np.ndarray, "N 3"] | None = None) -> float:
    """Fraction of ``pred``'s surface outside ``gt``'s bounding box grown by ``config.floater_margin`` GT
    diagonals (module docstring); 0 for an empty prediction. ``pred_points``: ``pred``'s surface samples (world
    frame), when already drawn."""
    if is_empty_mesh(pred):
        return 0.0
    lo, hi, margin = floater_box(gt, config)
    points = sample_surface(pred, config.n_points, config.seed) if pred_points is None else pred_points
    return float(outside_box(points, lo, hi, margin).mean())


def floater_box(gt: trimesh.Trimesh, config: GeometryConfig) -> tuple[np.ndarray, np.ndarray, float]:
    """``(lo, hi, margin)``: ``gt``'s axis-aligned bounds and the floater margin in world units
    (``config.floater_margin`` GT bounding-box diagonals); outside means outside ``[lo - margin, hi + margin]``."""
    lo, hi = np.asarray(gt.bounds[0], np.float64), np.asarray(gt.bounds[1], np.float64)
    return lo, hi, config.floater_margin * float(np.linalg.norm(hi - lo))


def is_empty_mesh(mesh: trimesh.Trimesh) -> bool:
    """True when the mesh has no faces or no area (an empty prediction)."""
    return len(mesh.faces) == 0 or not mesh.area > 0


def geometry_metrics(pred: trimesh.Trimesh, gt: trimesh.Trimesh, config: GeometryConfig = GeometryConfig(),
                     gt_points: Float[np.ndarray, "M 3"] | None = None) -> GeometryMetrics:
    """Chamfer-L1, F-score and their parts (see the module docstring for the definitions); ``gt_points`` (world
    frame) replace the samples of ``gt``, which then only gives the normalising diagonal."""
    if is_empty_mesh(gt):
        raise DepthnerfError("ground-truth mesh has no surface (no faces or zero area)")
    if config.n_points < 1 or not config.tau > 0:
        raise DepthnerfError(f"geometry metrics: need GeometryConfig.n_points >= 1 and tau > 0 (depthnerf eval "
                             f"--mesh-points, --fscore-tau), got n_points={config.n_points}, tau={config.tau}")
    diagonal = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    scale = diagonal if config.normalize else 1.0
    if is_empty_mesh(pred):
        worst = diagonal / scale
        return GeometryMetrics(worst, worst, worst, 0.0, 0.0, 0.0, config.tau, scale, True)
    pred_world = sample_surface(pred, config.n_points, config.seed)
    floaters = floater_fraction(pred, gt, config, pred_world)
    pred_pts = pred_world / scale
    gt_pts = (sample_surface(gt, config.n_points, config.seed) if gt_points is None
              else np.asarray(gt_points, dtype=np.float64)) / scale
    to_gt, to_pred = nearest_distances(pred_pts, gt_pts), nearest_distances(gt_pts, pred_pts)
    accuracy, completeness = float(to_gt.mean()), float(to_pred.mean())
    precision, recall = float((to_gt < config.tau).mean()), float((to_pred < config.tau).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return GeometryMetrics((accuracy + completeness) / 2, accuracy, completeness, precision, recall, fscore,
                           config.tau, scale, False, floater_fraction=floaters)


def backproject_depth(depth: Float[np.ndarray, "H W"], c2w: Float[np.ndarray, "4 4"],
                      intr: Intrinsics) -> Float[np.ndarray, "P 3"]:
    """World points (float64) of the pixels of a z-depth map with depth > 0 (camera ``c2w``, OpenCV axes)."""
    z = torch.from_numpy(np.asarray(depth, dtype=np.float64))
    return backproject(z, torch.as_tensor(np.asarray(c2w), dtype=torch.float64), intr, z > 0).numpy()


def visible_surface_points(record: ObjectRecord, n_points: int,
                           pixel_center: float = 0.0) -> Float[np.ndarray, "N 3"] | None:
    """The back-projected depth maps of all views of ``record`` (pixel (i, j) at ``(j + pixel_center,
    i + pixel_center)``), evenly subsampled to at most ``n_points``; None when the object has no depth maps."""
    if not record.has_depth:
        return None
    intr = record.intrinsics.with_pixel_center(pixel_center)
    parts = []
    for view in range(record.num_views):
        depth = srn_format.read_depth(record.depth_path(view), record.depth_scale, allow_empty=True)
        if depth.shape != (intr.height, intr.width):
            raise DepthnerfError(f"{record.depth_path(view)}: depth map is {depth.shape[1]}x{depth.shape[0]} but "
                                 f"intrinsics.txt says {intr.width}x{intr.height}")
        parts.append(backproject_depth(depth, srn_format.read_pose(record.pose_path(view)), intr))
    points = np.concatenate(parts)
    if len(points) == 0:
        raise DepthnerfError(f"{record.path}: every depth map is empty (no object pixel)")
    if len(points) > n_points:
        points = points[np.linspace(0, len(points) - 1, n_points).round().astype(np.int64)]
    return points


def object_geometry(pred: trimesh.Trimesh, record: ObjectRecord,
                    config: GeometryConfig = GeometryConfig()) -> GeometryMetrics:
    """``pred`` scored against the GT of a dataset object with ``mesh.ply``: its visible surface from the depth
    maps when it has them, else ``mesh.ply`` (module docstring)."""
    if record.mesh_path is None:
        raise DepthnerfError(f"{record.path}: no mesh.ply to score against")
    gt = read_mesh(record.mesh_path)
    points = visible_surface_points(record, config.n_points, config.depth_pixel_center)
    metrics = geometry_metrics(pred, gt, config, points)
    if points is None:
        return metrics
    return replace(metrics, ground_truth=f"visible surface from {record.num_views} depth maps")


def chamfer_l1(pred: trimesh.Trimesh, gt: trimesh.Trimesh, n_points: int = 100_000, seed: int = 0,
               normalize: bool = True) -> float:
    """Chamfer-L1 = mean of the two directed mean nearest-neighbour distances."""
    return geometry_metrics(pred, gt, GeometryConfig(n_points=n_points, seed=seed, normalize=normalize)).chamfer_l1


def fscore(pred: trimesh.Trimesh, gt: trimesh.Trimesh, tau: float = 0.01, n_points: int = 100_000, seed: int = 0,
           normalize: bool = True) -> float:
    """F-score at ``tau``: harmonic mean of precision and recall."""
    config = GeometryConfig(n_points=n_points, tau=tau, seed=seed, normalize=normalize)
    return geometry_metrics(pred, gt, config).fscore


def summarize_geometry(results: Sequence[GeometryMetrics], config: GeometryConfig = GeometryConfig()) -> dict:
    """The geometry part of ``summary.json``: plain means over objects (``chamfer_l1``, ``fscore``, ...)."""
    if not results:
        raise DepthnerfError("no meshes were evaluated: nothing to summarise")
    means = {k: float(np.mean([asdict(r)[k] for r in results]))
             for k in ("chamfer_l1", "accuracy", "completeness", "precision", "recall", "fscore",
                       "floater_fraction")}
    units = "ground-truth bounding-box diagonals" if config.normalize else "world units"
    sources = Counter(r.ground_truth for r in results)
    gt = (next(iter(sources)) if len(sources) == 1
          else "; ".join(f"{name} ({n} objects)" for name, n in sorted(sources.items())))
    return {**means, "fscore_tau": config.tau, "floater_margin": config.floater_margin, "geometry_units": units,
            "geometry_points": config.n_points, "empty_predictions": sum(r.empty_prediction for r in results), "geometry_gt": gt}
