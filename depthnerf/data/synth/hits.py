"""First-hit ray casting for the synthetic renderer: which triangle each ray meets first.

Two engines find the same thing; :class:`~depthnerf.data.synth.raycast.Raycaster` then recomputes the distance in
float64 on the hit triangle, so the engine only decides *which* triangle is hit:

- ``embree``: Intel Embree's BVH through embreex (float32 traversal; ~2 ms per 128 x 128 view on one CPU core).
- ``torch``: brute force (Moeller-Trumbore in float32, both faces; each camera's rays only against the triangles
  whose projected boxes meet theirs), on CUDA when there is one, else on the CPU. It needs nothing beyond torch
  (the lent GPU machines carry no embreex, and its wheel is too large to send there). About 0.5 s per 64 x 64 view
  of a 9k-triangle car on one CPU core, against Embree's 3 ms (``benchmarks/bench_synth.py --raycaster``).
- ``auto``: ``embree`` where embreex imports, else ``torch`` with a warning.

Both engines agree on every ray up to ties: a ray through an edge or a vertex shared by two triangles may be given
either one, and a ray grazing a silhouette within float32 rounding may hit in one and miss in the other
(``tests/test_synth_hits.py`` bounds how often on synthetic cars and chairs).
"""

from __future__ import annotations

import importlib.util
import math
import warnings
from typing import Protocol

import numpy as np
import torch
from jaxtyping import Float, Int

ENGINES = ("auto", "embree", "torch")
"""Names accepted by :func:`first_hit_finder` (and ``depthnerf synth --raycaster``)."""


class FirstHits(Protocol):
    """Index of the first triangle each ray hits, -1 for a miss."""

    engine: str

    def __call__(self, origins: Float[np.ndarray, "R 3"], dirs: Float[np.ndarray, "R 3"]) -> Int[np.ndarray, " R"]:
        ...


def available_engine() -> str:
    """``embree`` where embreex imports, else ``torch`` (what ``auto`` resolves to, without its warning: for callers
    whose casts are few enough that the engine does not matter)."""
    return "embree" if importlib.util.find_spec("embreex") is not None else "torch"


def resolve_engine(engine: str) -> str:
    """``embree`` or ``torch`` for ``engine`` (``auto``: :func:`available_engine`, with a warning when it is
    torch)."""
    if engine not in ENGINES:
        raise ValueError(f"unknown ray-casting engine {engine!r} (expected one of {', '.join(ENGINES)})")
    if engine != "auto":
        return engine
    if available_engine() == "embree":
        return "embree"
    warnings.warn("embreex is not installed: the synthetic renderer casts rays by brute force in torch (the same "
                  "hits up to ties on shared edges; slower on a CPU). `pip install embreex` for Embree.",
                  stacklevel=2)
    return "torch"


def first_hit_finder(vertices: Float[np.ndarray, "P 3"], faces: Int[np.ndarray, "F 3"], engine: str = "auto"
                     ) -> FirstHits:
    """A first-hit function over one triangle mesh with ``engine`` (see the module docstring)."""
    resolved = resolve_engine(engine)
    if resolved == "embree":
        return EmbreeHits(vertices, faces)
    return TorchHits(vertices, faces)


class EmbreeHits:
    """Embree's first hits (the scene ``trimesh.ray.ray_pyembree`` builds, used directly: without its per-call
    rescaling, which costs more than the traversal for these unit-sized objects)."""

    engine = "embree"

    def __init__(self, vertices: Float[np.ndarray, "P 3"], faces: Int[np.ndarray, "F 3"]) -> None:
        try:
            from embreex import mesh_construction, rtcore_scene
        except ImportError as e:  # asked for by name: say how to get it
            raise ImportError("the embree ray caster needs embreex (pip install embreex), or use --raycaster "
                              "torch") from e
        self._scene = rtcore_scene.EmbreeScene()
        mesh_construction.TriangleMesh(self._scene, np.ascontiguousarray(vertices, dtype=np.float32),
                                       np.ascontiguousarray(faces, dtype=np.int32))

    def __call__(self, origins: Float[np.ndarray, "R 3"], dirs: Float[np.ndarray, "R 3"]) -> Int[np.ndarray, " R"]:
        return np.asarray(self._scene.run(origins.astype(np.float32), dirs.astype(np.float32)), dtype=np.int64)


class TorchHits:
    """Brute-force first hits: for rays ``o + t d`` and triangles ``(v0, v0 + e1, v0 + e2)``, Moeller-Trumbore

    ``p = d x e2``, ``det = e1 . p``, ``s = o - v0``, ``u = (s . p) / det``, ``q = s x e1``,
    ``v = (d . q) / det``, ``t = (e2 . q) / det``;

    a hit where ``|det| > eps``, ``u >= 0``, ``v >= 0``, ``u + v <= 1`` and ``t > 0``, and the first hit is the
    smallest such ``t`` (an exact tie may go to either triangle). Each pair's terms are ``[rays, triangles]``
    tensors (no ``[rays, triangles, 3]`` temporaries).

    Rays from one shared origin (a camera's rays) are culled: with ``f`` the rays' mean direction and ``a, b`` an
    orthonormal basis of its normal plane, a point ``w`` (relative to the origin, ``w . f > 0``) projects to
    ``(w . a, w . b) / (w . f)``. A triangle in front of the origin contains a ray only if its projected bounding
    box contains the ray's projection, so each chunk of ``chunk_rays`` rays (a square tile of the projected rays)
    is tested only against the triangles whose boxes meet the chunk's box (triangles not wholly in front are
    always tested). Other rays go in chunks of about ``elements`` ray-triangle pairs against every triangle.
    """

    engine = "torch"

    def __init__(self, vertices: Float[np.ndarray, "P 3"], faces: Int[np.ndarray, "F 3"],
                 device: torch.device | str | None = None, elements: int | None = None,
                 chunk_rays: int | None = None) -> None:
        self.device = torch.device(device) if device is not None else torch.device(
            "cuda" if torch.cuda.is_available() else "cpu")
        cuda = self.device.type == "cuda"
        self.elements = elements or (1 << 26 if cuda else 1 << 22)
        self.chunk_rays = chunk_rays or (4096 if cuda else 256)
        tri = torch.as_tensor(np.asarray(vertices, dtype=np.float64)[np.asarray(faces)], dtype=torch.float32)
        tri = tri.to(self.device)
        self._v0 = tri[:, 0].T.contiguous()              # [3, F]: one row per coordinate
        self._e1 = (tri[:, 1] - tri[:, 0]).T.contiguous()
        self._e2 = (tri[:, 2] - tri[:, 0]).T.contiguous()

    @torch.no_grad()
    def __call__(self, origins: Float[np.ndarray, "R 3"], dirs: Float[np.ndarray, "R 3"]) -> Int[np.ndarray, " R"]:
        n_rays, n_faces = len(origins), self._v0.shape[1]
        out = np.full(n_rays, -1, dtype=np.int64)
        if n_rays == 0 or n_faces == 0:
            return out
        o_all = torch.as_tensor(np.asarray(origins, dtype=np.float32), device=self.device)
        d_all = torch.as_tensor(np.asarray(dirs, dtype=np.float32), device=self.device)
        if bool((o_all == o_all[:1]).all()):
            return self._shared_origin(o_all, d_all)
        chunk = max(1, self.elements // n_faces)
        for start in range(0, n_rays, chunk):
            o, d = o_all[start:start + chunk], d_all[start:start + chunk]
            out[start:start + len(o)] = self._chunk(o, d, self._v0, self._e1, self._e2).cpu().numpy()
        return out

    def _shared_origin(self, o_all: Float[torch.Tensor, "R 3"], d_all: Float[torch.Tensor, "R 3"]
                       ) -> Int[np.ndarray, " R"]:
        """First hits of rays from one origin, each chunk against the triangles its projected box meets."""
        origin = o_all[0]
        f = d_all.mean(0)
        f = f / f.norm().clamp_min(1e-12)
        a = torch.linalg.cross(f, torch.tensor([1.0, 0.0, 0.0], device=self.device)
                               if abs(float(f[0])) < 0.9 else torch.tensor([0.0, 1.0, 0.0], device=self.device))
        a = a / a.norm()
        b = torch.linalg.cross(f, a)
        basis = torch.stack([a, b, f], 1)                             # [3, 3]: columns a, b, f
        corners = torch.stack([self._v0, self._v0 + self._e1, self._v0 + self._e2], 0)   # [3 corners, 3, F]
        w = torch.einsum("kcf,cj->kfj", corners - origin[None, :, None], basis)          # [3, F, (a, b, f)]
        front = (w[..., 2] > 1e-6).all(0)                                                  # [F]
        uv = w[..., :2] / w[..., 2:].clamp_min(1e-6)                                       # [3, F, 2]
        lo, hi = uv.amin(0), uv.amax(0)                                                    # [F, 2]
        ray_uv = (d_all @ basis)                                                           # [R, 3]
        ray_front = ray_uv[:, 2] > 1e-6
        ray_uv = ray_uv[:, :2] / ray_uv[:, 2:].clamp_min(1e-6)
        # chunks are square tiles of the rays' projections (~chunk_rays rays each), not runs of the input order
        n = len(d_all)
        g = max(1, math.ceil(math.sqrt(n / self.chunk_rays)))
        q_lo, q_hi = ray_uv.amin(0), ray_uv.amax(0)
        cell = ((ray_uv - q_lo) / (q_hi - q_lo).clamp_min(1e-12) * g).long().clamp(0, g - 1)
        order = torch.argsort(cell[:, 1] * g + cell[:, 0], stable=True)
        out = torch.full((n,), -1, dtype=torch.int64, device=self.device)
        margin = 1e-5
        for start in range(0, n, self.chunk_rays):
            sl = order[start:start + self.chunk_rays]
            d, q, q_front = d_all[sl], ray_uv[sl], ray_front[sl]
            if bool(q_front.all()):
                qlo, qhi = q.amin(0) - margin, q.amax(0) + margin
                keep = ~front | ((lo <= qhi).all(1) & (hi >= qlo).all(1))
            else:  # a ray pointing away from f: no projection, test everything
                keep = torch.ones_like(front)
            idx = keep.nonzero()[:, 0]
            if len(idx) == 0:
                continue
            face = self._chunk(o_all[sl], d, self._v0[:, idx], self._e1[:, idx], self._e2[:, idx])
            out[sl] = torch.where(face >= 0, idx[face.clamp_min(0)], face)
        return out.cpu().numpy()

    @staticmethod
    def _chunk(o: Float[torch.Tensor, "r 3"], d: Float[torch.Tensor, "r 3"], v0: Float[torch.Tensor, "3 F"],
               e1: Float[torch.Tensor, "3 F"], e2: Float[torch.Tensor, "3 F"]) -> Int[torch.Tensor, " r"]:
        """First hit among the given triangles (index into them), -1 for none."""
        (v0x, v0y, v0z), (e1x, e1y, e1z), (e2x, e2y, e2z) = v0, e1, e2
        dx, dy, dz = (d[:, i:i + 1] for i in range(3))
        px, py, pz = dy * e2z - dz * e2y, dz * e2x - dx * e2z, dx * e2y - dy * e2x
        det = e1x * px + e1y * py + e1z * pz
        inv = 1.0 / torch.where(det.abs() > 1e-12, det, torch.ones_like(det))
        sx, sy, sz = o[:, 0:1] - v0x, o[:, 1:2] - v0y, o[:, 2:3] - v0z
        u = (sx * px + sy * py + sz * pz) * inv
        del px, py, pz
        qx, qy, qz = sy * e1z - sz * e1y, sz * e1x - sx * e1z, sx * e1y - sy * e1x
        del sx, sy, sz
        v = (dx * qx + dy * qy + dz * qz) * inv
        t = (e2x * qx + e2y * qy + e2z * qz) * inv
        hit = (det.abs() > 1e-12) & (u >= 0) & (v >= 0) & (u + v <= 1) & (t > 0)
        t = torch.where(hit, t, torch.full_like(t, float("inf")))
        t_min, face = t.min(dim=1)
        return torch.where(torch.isfinite(t_min), face, torch.full_like(face, -1))
