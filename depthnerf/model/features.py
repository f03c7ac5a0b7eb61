"""Pixel-aligned features: bring world points into each source camera, project, sample the feature maps.

Conventions (see ``depthnerf.data.cameras``): ``w2c`` maps world to OpenCV camera coordinates; a camera point
projects to ``u = f x / z + cx``, ``v = f y / z + cy`` with pixel (i, j) centred at (u, v) = (j, i).

Feature-map indexing follows pixelNeRF exactly (its ``latent_scaling``): image coordinates (u, v) of an
``H x W`` image map to the grid coordinate ``g = (u, v) * 2 * (Wf, Hf) / ((Wf - 1, Hf - 1) * (W, H)) - 1`` and are
sampled bilinearly with ``align_corners=True`` and border padding; i.e. feature column ``u * Wf / W`` and row
``v * Hf / H`` (so with ``Hf = H`` a point projecting to pixel (i, j) reads feature pixel (i, j) exactly).

Determinism: under ``torch.use_deterministic_algorithms(True)`` (``depthnerf train --deterministic``) the
feature gather is written with index gathers (:func:`sample_maps_gather`, backward = sort-based
``index_put`` accumulation) instead of the fused ``embedding_bag``, and the encoder's map resizing
(:func:`resize_bilinear`) is two matrix products instead of ``interpolate``, whose CUDA backward uses atomics
(``grid_sample``'s too). Both give the same values as the fast kernels up to float rounding (tests/test_model.py).
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from jaxtyping import Float, Int
from torch import Tensor

from depthnerf.bundles import TensorBundle
from depthnerf.data.cameras import project


def to_source_frames(points: Float[Tensor, "B N 3"], w2c: Float[Tensor, "B V 4 4"]
                     ) -> tuple[Float[Tensor, "B V N 3"], Float[Tensor, "B V N 3"]]:
    """World points in every source camera: ``(R x, R x + t)`` = (rotated only, full camera coordinates).
    Always in the inputs' precision: under bf16 autocast a matmul would round the coordinates to bf16 (about
    1e-3 of the scene scale) before the positional encoding and the projection."""
    rot = w2c[:, :, :3, :3]
    with torch.autocast(points.device.type, enabled=False):
        rotated = points[:, None] @ rot.transpose(-1, -2)
    return rotated, rotated + w2c[:, :, None, :3, 3]


def project_points(cam: Float[Tensor, "B V N 3"], focal: Float[Tensor, " B"],
                   principal: Float[Tensor, "B 2"]) -> Float[Tensor, "B V N 2"]:
    """Pixel coordinates (u, v) of camera-frame points; points with z <= 0 go far outside (border features).
    :func:`depthnerf.data.cameras.project` with one camera per batch element (broadcast over its views)."""
    return project(cam, focal[:, None], principal[:, None, :])


def in_frame(cam: Float[Tensor, "B V N 3"], uv: Float[Tensor, "B V N 2"], image_size: tuple[int, int]
             ) -> Float[Tensor, "B V N"]:
    """1.0 where a camera-frame point is in front of the camera and its projection ``uv``
    (:func:`project_points`) lies inside ``0 <= u <= W``, ``0 <= v <= H``, else 0.0. With pixel centres at
    integer coordinates the image covers ``[-0.5, W - 0.5]``: this test is half a pixel off that at both ends, as
    the shipped mirror models were trained with it (a flag, not a coordinate: features are sampled by
    :func:`uv_to_grid`)."""
    h, w = image_size
    inside = (cam[..., 2] > 0) & (uv[..., 0] >= 0) & (uv[..., 0] <= w) & (uv[..., 1] >= 0) & (uv[..., 1] <= h)
    return inside.to(cam.dtype)


def uv_to_grid(uv: Float[Tensor, "*B 2"], image_size: tuple[int, int],
               feature_size: tuple[int, int]) -> Float[Tensor, "*B 2"]:
    """pixelNeRF's ``latent_scaling``: image coordinates -> ``grid_sample`` coordinates in [-1, 1]."""
    (h, w), (hf, wf) = image_size, feature_size
    scale = uv.new_tensor([2.0 * wf / (max(wf - 1, 1) * w), 2.0 * hf / (max(hf - 1, 1) * h)])
    return uv * scale - 1.0


def sample_maps(maps: Float[Tensor, "BV Hf Wf C"], grid: Float[Tensor, "BV N 2"]) -> Float[Tensor, "BV N C"]:
    """Bilinear samples of channels-last maps at grid points; ``grid_sample(align_corners=True,
    padding_mode="border")`` semantics (coordinates clamped to the map), differentiable in maps and grid.

    Implemented as one fused gather-weighted-sum (``embedding_bag`` over the 4 corner rows): with C contiguous
    channels per pixel it reads whole rows, where ``grid_sample`` on a channels-first map makes 4 strided reads
    per channel and point (measured ~4x faster forward and ~10x faster backward for C = 1536). On CUDA without
    gradients (inference) it is :func:`sample_maps_inference` instead: with ``--compile`` (compiled MLPs, this
    gather outside the compiled region) a paper-sampler view took 89 ms with it against 143-146 without (H100s
    of the same kind), eager views 230 against 226 ms on one machine (docs/speed.md). Same values either way.
    """
    bv, hf, wf, c = maps.shape
    n = grid.shape[1]
    if c == 0:  # a field without feature injection (combine_layer = 0)
        return maps.new_zeros(bv, n, 0)
    if maps.is_cuda and not (maps.requires_grad or grid.requires_grad):
        return sample_maps_inference(maps, grid)
    index, weight = _corners(grid, bv, hf, wf)
    if torch.are_deterministic_algorithms_enabled():
        return sample_maps_gather(maps, index, weight).reshape(bv, n, c)
    out = F.embedding_bag(index, maps.reshape(bv * hf * wf, c), per_sample_weights=weight, mode="sum")
    return out.reshape(bv, n, c)


def sample_maps_inference(maps: Float[Tensor, "BV Hf Wf C"], grid: Float[Tensor, "BV N 2"]
                          ) -> Float[Tensor, "BV N C"]:
    """:func:`sample_maps` by ``grid_sample`` on channels-first maps (one copy of the maps per call), for calls
    without gradients: its forward is deterministic, its backward (atomics, strided) is what the fused gather
    avoids. In float32 whatever the maps' dtype (the result has theirs); non-finite coordinates are read as in
    :func:`_corners` (NaN as 0, infinities at the border)."""
    maps_cf = maps.permute(0, 3, 1, 2).float().contiguous()
    grid = torch.nan_to_num(grid.float(), nan=0.0, posinf=1.0, neginf=-1.0)
    with torch.autocast(maps.device.type, enabled=False):
        out = F.grid_sample(maps_cf, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=True)
    return out[..., 0].transpose(1, 2).to(maps.dtype)


def _corners(grid: Float[Tensor, "BV N 2"], bv: int, hf: int, wf: int
             ) -> tuple[Int[Tensor, "BVN 4"], Float[Tensor, "BVN 4"]]:
    """Flat row indices of the 4 bilinear corners of every grid point in ``[BV*Hf*Wf]`` and their weights."""
    n = grid.shape[1]
    device = grid.device
    fx = ((torch.nan_to_num(grid[..., 0]) + 1.0) * (0.5 * (wf - 1))).clamp(0.0, wf - 1.0)
    fy = ((torch.nan_to_num(grid[..., 1]) + 1.0) * (0.5 * (hf - 1))).clamp(0.0, hf - 1.0)
    x0 = fx.detach().floor().clamp(max=max(wf - 2, 0))
    y0 = fy.detach().floor().clamp(max=max(hf - 2, 0))
    ax, ay = fx - x0, fy - y0
    dx, dy = int(wf > 1), wf * int(hf > 1)
    base = torch.arange(bv, device=device)[:, None] * (hf * wf) + y0.long() * wf + x0.long()
    index = torch.stack([base, base + dx, base + dy, base + dy + dx], dim=-1).reshape(bv * n, 4)
    weight = torch.stack([(1 - ax) * (1 - ay), ax * (1 - ay), (1 - ax) * ay, ax * ay], dim=-1).reshape(bv * n, 4)
    return index, weight


def sample_maps_gather(maps: Float[Tensor, "BV Hf Wf C"], index: Int[Tensor, "M 4"],
                       weight: Float[Tensor, "M 4"]) -> Float[Tensor, "M C"]:
    """The weighted 4-corner sum of :func:`sample_maps` with plain index gathers: deterministic backward
    (``index_put`` accumulation), at the cost of materialising the ``[M, 4, C]`` corner rows."""
    c = maps.shape[-1]
    rows = maps.reshape(-1, c)[index.reshape(-1)].reshape(*index.shape, c)
    return (rows * weight[..., None].to(rows.dtype)).sum(1)


def _interp_matrix(n_out: int, n_in: int, device: torch.device) -> Float[Tensor, "O I"]:
    """Rows of bilinear (``align_corners=True``) interpolation weights from ``n_in`` to ``n_out`` samples."""
    src = torch.arange(n_out, device=device, dtype=torch.float32) * ((n_in - 1) / max(n_out - 1, 1))
    lo = src.floor().clamp(max=max(n_in - 2, 0))
    frac = (src - lo) if n_in > 1 else torch.zeros_like(src)
    lo = lo.long()
    hi = (lo + 1).clamp(max=n_in - 1)
    eye = torch.eye(n_in, device=device)
    return (1.0 - frac)[:, None] * eye[lo] + frac[:, None] * eye[hi]


def resize_bilinear(x: Float[Tensor, "N C H W"], size: tuple[int, int] | torch.Size) -> Float[Tensor, "N C Ho Wo"]:
    """``F.interpolate(x, size, mode="bilinear", align_corners=True)``; under deterministic algorithms the same
    map as two matrix products ``A_h x A_w^T`` (deterministic forward and backward on CUDA)."""
    ho, wo = int(size[0]), int(size[1])
    if not torch.are_deterministic_algorithms_enabled():
        return F.interpolate(x, (ho, wo), mode="bilinear", align_corners=True)
    return resize_bilinear_matmul(x, (ho, wo))


def resize_bilinear_matmul(x: Float[Tensor, "N C H W"], size: tuple[int, int]) -> Float[Tensor, "N C Ho Wo"]:
    """Bilinear ``align_corners=True`` resizing as ``A_h @ x @ A_w^T`` (see :func:`resize_bilinear`)."""
    a_h = _interp_matrix(size[0], x.shape[-2], x.device).to(x.dtype)
    a_w = _interp_matrix(size[1], x.shape[-1], x.device).to(x.dtype)
    return torch.matmul(torch.matmul(a_h, x), a_w.t())


def sample_projected(maps: Float[Tensor, "B V Hf Wf C"], uv: Float[Tensor, "B V N 2"],
                     image_size: tuple[int, int]) -> Float[Tensor, "B V N C"]:
    """Features of each source view's (channels-last) map at image coordinates ``uv`` of an ``H x W`` image (the
    projections of camera-frame points, :func:`project_points`)."""
    b, v, hf, wf, c = maps.shape
    grid = uv_to_grid(uv, image_size, (hf, wf))
    out = sample_maps(maps.reshape(b * v, hf, wf, c), grid.reshape(b * v, -1, 2))
    return out.reshape(b, v, uv.shape[2], c)


@dataclass
class MapSamples(TensorBundle):
    """Channels-last maps and the points to read them at, the bilinear gather left to whoever consumes the
    features (``--gather inside``: the field MLP's forward, so that under ``--compile`` the gather is part of the
    compiled graph). :meth:`read` gives :func:`sample_maps`' values with plain index loads of whole channel rows,
    which inductor generates into its own kernel; the maps may be bf16 while the coordinates and corner weights
    stay fp32 (``grid_sample`` takes its coordinates in the map's dtype, :func:`sample_maps_inference`)."""

    maps: Float[Tensor, "BV Hf Wf C"]
    """The maps, channels-last (fp32, or bf16 for half the bytes read)."""
    grid: Float[Tensor, "BV N 2"]
    """Grid coordinates of the points in each map (:func:`uv_to_grid`), fp32."""

    def corners(self) -> tuple[Int[Tensor, "BVN 4"], Float[Tensor, "BVN 4"]]:
        """Flat row indices of every point's 4 bilinear corners in ``maps.reshape(-1, C)`` and their weights;
        computed once and passed to each :meth:`read`."""
        bv, hf, wf, _ = self.maps.shape
        return _corners(self.grid, bv, hf, wf)

    def read(self, corners: tuple[Int[Tensor, "BVN 4"], Float[Tensor, "BVN 4"]], start: int = 0,
             stop: int | None = None) -> Float[Tensor, "BVN K"]:
        """Channels ``[start, stop)`` at every point, rows in (BV, N) order: ``sum_k w_k maps[i_k, start:stop]``
        over the 4 corners, written as four terms (no ``[BVN, 4, K]`` tensor), in fp32 whatever the maps' dtype."""
        index, weight = corners
        rows = self.maps.reshape(-1, self.maps.shape[-1])[:, start:stop]
        out = weight[:, :1].float() * rows[index[:, 0]]
        for k in range(1, 4):
            out = out + weight[:, k:k + 1].float() * rows[index[:, k]]
        return out


def map_samples(maps: Float[Tensor, "B V Hf Wf C"], uv: Float[Tensor, "B V N 2"],
                image_size: tuple[int, int]) -> MapSamples:
    """:func:`sample_projected` with the gather deferred: the maps (in their dtype) and the grid coordinates of
    image coordinates ``uv``, for :meth:`MapSamples.read`."""
    b, v, hf, wf, c = maps.shape
    grid = uv_to_grid(uv.float(), image_size, (hf, wf))
    return MapSamples(maps=maps.reshape(b * v, hf, wf, c), grid=grid.reshape(b * v, -1, 2))


def rotate_dirs(dirs: Float[Tensor, "B N 3"], w2c: Float[Tensor, "B V 4 4"]) -> Float[Tensor, "B V N 3"]:
    """Direction vectors expressed in every source camera's axes (in the inputs' precision under autocast, as
    :func:`to_source_frames`)."""
    with torch.autocast(dirs.device.type, enabled=False):
        return dirs[:, None] @ w2c[:, :, :3, :3].transpose(-1, -2)

