"""End-to-end learning check: a tiny pixelNeRF overfits one analytic object through the real renderer.

Two 32x32 views of a textured two-sphere object (ground truth volume-rendered from the analytic scene with many
samples); the model is conditioned on view 0 and trained on random rays of both views with the paper's loss
(coarse + fine L2). PSNR of the final (fine) render of both training views, in eval mode, must pass 25 dB.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import Tensor

from depthnerf.data.cameras import Intrinsics, look_at
from depthnerf.model import EncoderConfig, FieldConfig, PixelNeRF, PixelNeRFConfig, SourceViews
from depthnerf.render import (
    RayBundle,
    RenderConfig,
    SamplerConfig,
    rays_from_camera,
    render_image,
    render_rays,
)
from depthnerf.render.analytic import Sphere, SphereScene

SIZE, NEAR, FAR = 32, 0.8, 1.8


def training_views() -> tuple[Tensor, RayBundle, SourceViews]:
    intr = Intrinsics(focal=SIZE * 131.25 / 128, cx=(SIZE - 1) / 2, cy=(SIZE - 1) / 2, height=SIZE, width=SIZE)
    scene = SphereScene((Sphere((0.0, 0.0, 0.0), 0.42), Sphere((0.18, -0.1, 0.28), 0.14)), beta=0.01,
                        pattern_frequency=4.0)
    az, el = torch.tensor([0.0, 0.7]), 0.35
    eye = torch.stack([1.3 * math.cos(el) * torch.cos(az), 1.3 * math.cos(el) * torch.sin(az),
                       torch.full_like(az, 1.3 * math.sin(el))], dim=-1)
    poses = look_at(eye)
    rays = rays_from_camera(poses, intr, NEAR, FAR)  # [2, 1024]
    gt_cfg = RenderConfig(sampler=SamplerConfig(n_coarse=128, n_importance=64, n_gaussian=0))
    gt = render_image(scene, scene, rays, gt_cfg, chunk=4096).final.rgb  # [2, 1024, 3]
    src = SourceViews(images=gt[0].reshape(SIZE, SIZE, 3).permute(2, 0, 1)[None, None], poses=poses[None, :1],
                      focal=torch.tensor([intr.focal]), principal=torch.tensor([[intr.cx, intr.cy]]))
    flat = RayBundle(rays.origins.reshape(1, -1, 3), rays.directions.reshape(1, -1, 3),
                     rays.near.reshape(1, -1), rays.far.reshape(1, -1))
    return gt.reshape(1, -1, 3), flat, src


@pytest.mark.slow
def test_tiny_model_overfits_one_object():
    threads = torch.get_num_threads()
    torch.set_num_threads(1)  # tiny ops: one thread is as fast and immune to a busy shared machine
    try:
        torch.manual_seed(0)
        gt, rays, src = training_views()
        assert 0.3 < (gt > 0.99).all(-1).float().mean() < 0.6  # object and white background both present
        field = FieldConfig(d_hidden=64, density_bias_init=0.5)
        model = PixelNeRF(PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18", num_layers=2),
                                          coarse=field, fine=field), depth_aware=False)
        cfg = RenderConfig(sampler=SamplerConfig(n_coarse=32, n_importance=16, n_gaussian=8))
        opt = torch.optim.Adam(model.parameters(), lr=1e-3)
        gen = torch.Generator().manual_seed(0)

        def psnr() -> float:
            model.eval()
            with torch.no_grad():
                enc = model.encode(src)
                out = render_image(model.field(enc, "coarse"), model.field(enc, "fine"), rays, cfg, chunk=4096)
            model.train()
            return -10 * math.log10(float((out.final.rgb - gt).square().mean()))

        history = [psnr()]
        assert history[0] < 18
        for it in range(1, 301):
            idx = torch.randint(0, rays.num_rays, (256,), generator=gen)
            batch = RayBundle(rays.origins[:, idx], rays.directions[:, idx], rays.near[:, idx], rays.far[:, idx])
            enc = model.encode(src)
            out = render_rays(model.field(enc, "coarse"), model.field(enc, "fine"), batch, cfg, train=True,
                              generator=gen)
            target = gt[:, idx]
            loss = (out.coarse.rgb - target).square().mean() + (out.fine.rgb - target).square().mean()
            opt.zero_grad(set_to_none=True)
            loss.backward()
            opt.step()
            if it % 25 == 0:
                history.append(psnr())
                if history[-1] > 25.0:
                    break
        assert history[-1] > 25.0, f"PSNR every 25 iterations: {[round(p, 2) for p in history]}"
    finally:
        torch.set_num_threads(threads)
