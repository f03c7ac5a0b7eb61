"""First-hit engines of the synthetic renderer: the torch brute force against closed forms and against Embree, and
``depthnerf synth --raycaster``."""

from __future__ import annotations

import importlib.util
import json

import numpy as np
import pytest
import torch

from depthnerf.data.synth.hits import TorchHits, first_hit_finder, resolve_engine

HAS_EMBREE = importlib.util.find_spec("embreex") is not None


def cube(half: float = 0.5) -> tuple[np.ndarray, np.ndarray]:
    """An axis-aligned cube ``[-half, half]^3`` as 12 triangles."""
    v = np.array([[x, y, z] for x in (-half, half) for y in (-half, half) for z in (-half, half)], dtype=np.float64)
    quads = [(0, 1, 3, 2), (4, 6, 7, 5), (0, 4, 5, 1), (2, 3, 7, 6), (0, 2, 6, 4), (1, 5, 7, 3)]
    faces = [f for a, b, c, d in quads for f in ((a, b, c), (a, c, d))]
    return v, np.array(faces, dtype=np.int64)


def slab_entry(origins: np.ndarray, dirs: np.ndarray, half: float) -> np.ndarray:
    """Closed form: distance to the first cube face along each ray (inf for a miss)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (-half - origins) / dirs, (half - origins) / dirs
    near = np.nanmax(np.minimum(t1, t2), axis=1)
    far = np.nanmin(np.maximum(t1, t2), axis=1)
    return np.where((far >= near) & (near > 0), near, np.inf)


def face_distance(v: np.ndarray, f: np.ndarray, face: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Ray distance to the plane of each hit face (inf for -1)."""
    t = np.full(len(face), np.inf)
    hit = face >= 0
    tri = v[f[face[hit]]]
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    t[hit] = ((tri[:, 0] - o[hit]) * n).sum(1) / (d[hit] * n).sum(1)
    return t


@pytest.mark.parametrize("shared_origin", [True, False])
def test_torch_hits_match_the_slab_closed_form_of_a_cube(shared_origin):
    rng = np.random.default_rng(0)
    v, f = cube(0.5)
    n = 2000
    if shared_origin:  # a camera: one origin, rays over a cone that covers the cube and misses around it
        o = np.tile([[1.6, -1.1, 0.9]], (n, 1))
    else:
        o = rng.normal(size=(n, 3))
        o = o / np.linalg.norm(o, axis=1, keepdims=True) * rng.uniform(1.2, 3.0, (n, 1))
    target = rng.uniform(-0.9, 0.9, (n, 3))
    d = target - o
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    expected = slab_entry(o, d, 0.5)
    # rays within float32 rounding of the silhouette may go either way: keep those that a cube 1e-4 smaller and
    # one 1e-4 larger agree on
    clear = np.isfinite(slab_entry(o, d, 0.5 - 1e-4)) == np.isfinite(slab_entry(o, d, 0.5 + 1e-4))
    face = TorchHits(v, f, device="cpu", chunk_rays=64)(o, d)
    assert (face >= 0)[clear].tolist() == np.isfinite(expected)[clear].tolist()
    both = clear & np.isfinite(expected)
    assert 200 < both.sum() < n - 200  # hits and misses both well represented
    np.testing.assert_allclose(face_distance(v, f, face, o, d)[both], expected[both], rtol=0, atol=1e-9)
    # rays pointing away from the cube miss
    assert (TorchHits(v, f, device="cpu")(o, -d)[np.isfinite(expected)] == -1).all()


def test_shared_origin_culling_equals_testing_every_triangle():
    """The culled path (one origin) gives the faces of the all-triangles path, on a real synthetic car."""
    from depthnerf.data.synth.cars import build_car, sample_car
    from depthnerf.data.synth.generate import SynthConfig, category_spec, object_poses, object_rngs
    from depthnerf.data.synth.raycast import PixelRays

    shape, views = object_rngs(0, "cars", "train", 1)
    mesh = build_car(sample_car(shape))
    rays = PixelRays(SynthConfig(category="cars", out="x", resolution=24).get_framing().render_intrinsics(24))
    hits = TorchHits(mesh.vertices, mesh.faces, device="cpu", chunk_rays=32)
    for c2w in object_poses("train", 3, category_spec("cars"), views):
        o, d = rays.world(rays.centre, np.asarray(c2w, np.float32))
        culled = hits(o, d)
        o32, d32 = torch.as_tensor(o, dtype=torch.float32), torch.as_tensor(d, dtype=torch.float32)
        every = hits._chunk(o32, d32, hits._v0, hits._e1, hits._e2).numpy()  # all rays against all triangles
        assert (culled >= 0).any() and (culled == -1).any()
        np.testing.assert_array_equal(culled, every)


@pytest.mark.skipif(not HAS_EMBREE, reason="embreex is not installed")
@pytest.mark.parametrize("category", ["cars", "chairs"])
def test_torch_and_embree_render_the_same_views(category):
    from depthnerf.data.synth.cars import build_car, sample_car
    from depthnerf.data.synth.chairs import build_chair, sample_chair
    from depthnerf.data.synth.generate import SynthConfig, category_spec, object_poses, object_rngs
    from depthnerf.data.synth.raycast import PixelRays, Raycaster, SynthRenderConfig, render_view

    spec = category_spec(category)
    shape, views = object_rngs(0, category, "test", 2)
    mesh = build_car(sample_car(shape)) if category == "cars" else build_chair(sample_chair(shape), spec.diagonal)
    rays = PixelRays(SynthConfig(category=category, out="x", resolution=32).get_framing().render_intrinsics(32))
    embree, brute = Raycaster(mesh, "embree"), Raycaster(mesh, "torch")
    assert (embree.engine, brute.engine) == ("embree", "torch")
    pixels = differing = 0
    for c2w in object_poses("test", 4, spec, views):
        a, b = render_view(embree, c2w, rays, SynthRenderConfig()), render_view(brute, c2w, rays, SynthRenderConfig())
        same = a.mask == b.mask
        pixels += a.mask.size
        differing += int((~same).sum() + (np.abs(a.rgb - b.rgb).max(-1) > 1e-6).sum())
        both = a.mask & b.mask
        np.testing.assert_allclose(a.depth[both], b.depth[both], rtol=0, atol=1e-5)
    assert differing <= pixels * 1e-3  # ties on shared edges only (none in the views measured)


def test_synth_records_the_engine_and_refuses_embree_without_embreex(tmp_path, monkeypatch, capsys):
    from depthnerf.cli import main

    out = tmp_path / "d"
    args = ["synth", "--category", "chairs", "--out", str(out), "--train-objects", "1", "--val-objects", "0",
            "--test-objects", "0", "--resolution", "16", "--views-train", "2", "--quiet"]
    assert main([*args, "--raycaster", "torch"]) == 0
    marker = json.loads(next(out.glob("chairs_train/*/.synth_done.json")).read_text())
    card = json.loads((out / "chairs_card.json").read_text())
    assert marker["raycaster"] == "torch" and card["rendering"]["raycasters"] == {"torch": 1}

    real = importlib.util.find_spec
    monkeypatch.setattr(importlib.util, "find_spec", lambda name, *a: None if name == "embreex" else real(name, *a))
    assert main([*args, "--out", str(tmp_path / "e"), "--raycaster", "embree"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == ["error: synth: --raycaster embree needs embreex (pip install embreex); --raycaster torch or auto "
                   "needs nothing more"]
    assert not (tmp_path / "e").exists()
    with pytest.warns(UserWarning, match="embreex is not installed"):
        assert resolve_engine("auto") == "torch"
    assert first_hit_finder(*cube(), engine="torch").engine == "torch"
    with pytest.raises(ValueError, match="unknown ray-casting engine 'optix'"):
        resolve_engine("optix")
