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

Definitions (Occupancy Networks / Tatarchenko et al. 2019 conventions)
    accuracy = mean over predicted samples of the distance to the nearest GT sample;
    completeness = the same from GT samples to predicted samples;
    **Chamfer-L1 = (accuracy + completeness) / 2** (the mean, not the sum, of the two directed means);
    precision = fraction of predicted samples within ``tau`` of GT, recall = fraction of GT samples within ``tau``
    of the prediction; **F-score@tau = 2 P R / (P + R)** (0 when P + R = 0). Default ``tau = 0.01`` (1% of the
    object's diagonal, Tatarchenko et al.'s choice).

Empty prediction (no faces or zero area, e.g. a density that never reached the marching-cubes level): worst-case
values, no error: accuracy = completeness = Chamfer-L1 = one GT diagonal (1.0 when normalised), precision =
recall = F-score = 0, and ``empty_prediction = True``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass

import numpy as np
import trimesh
from jaxtyping import Float
from scipy.spatial import cKDTree

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


def sample_surface(mesh: trimesh.Trimesh, n_points: int, seed: int) -> Float[np.ndarray, "N 3"]:
    """``n_points`` area-weighted samples of the mesh surface (deterministic for a seed)."""
    points, _ = trimesh.sample.sample_surface(mesh, n_points, seed=seed)
    return np.asarray(points, dtype=np.float64)


def nearest_distances(src: Float[np.ndarray, "N 3"], dst: Float[np.ndarray, "M 3"]) -> Float[np.ndarray, " N"]:
    """Euclidean distance from every ``src`` point to its nearest ``dst`` point."""
    dist, _ = cKDTree(dst).query(src, k=1)
    return np.asarray(dist, dtype=np.float64)


def _is_empty(mesh: trimesh.Trimesh) -> bool:
    return len(mesh.faces) == 0 or not mesh.area > 0


def geometry_metrics(pred: trimesh.Trimesh, gt: trimesh.Trimesh,
                     config: GeometryConfig = GeometryConfig()) -> GeometryMetrics:
    """Chamfer-L1, F-score and their parts (see the module docstring for the definitions)."""
    if _is_empty(gt):
        raise DepthnerfError("ground-truth mesh has no surface (no faces or zero area)")
    if config.n_points < 1 or not config.tau > 0:
        raise DepthnerfError(f"geometry metrics: need n_points >= 1 and tau > 0, got {config.n_points}, {config.tau}")
    diagonal = float(np.linalg.norm(gt.bounds[1] - gt.bounds[0]))
    scale = diagonal if config.normalize else 1.0
    if _is_empty(pred):
        worst = diagonal / scale
        return GeometryMetrics(worst, worst, worst, 0.0, 0.0, 0.0, config.tau, scale, True)
    pred_pts = sample_surface(pred, config.n_points, config.seed) / scale
    gt_pts = sample_surface(gt, config.n_points, config.seed) / scale
    to_gt, to_pred = nearest_distances(pred_pts, gt_pts), nearest_distances(gt_pts, pred_pts)
    accuracy, completeness = float(to_gt.mean()), float(to_pred.mean())
    precision, recall = float((to_gt < config.tau).mean()), float((to_pred < config.tau).mean())
    fscore = 2 * precision * recall / (precision + recall) if precision + recall > 0 else 0.0
    return GeometryMetrics((accuracy + completeness) / 2, accuracy, completeness, precision, recall, fscore,
                           config.tau, scale, False)


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
             for k in ("chamfer_l1", "accuracy", "completeness", "precision", "recall", "fscore")}
    units = "ground-truth bounding-box diagonals" if config.normalize else "world units"
    return {**means, "fscore_tau": config.tau, "geometry_units": units, "geometry_points": config.n_points,
            "empty_predictions": sum(r.empty_prediction for r in results)}
