"""The feature gather (``depthnerf.model.features.sample_maps``) against torch's ``grid_sample``: the fused
training path, values and gradients, and the no-gradient path of compiled CUDA inference; ``in_frame`` against
its definition."""

from __future__ import annotations

import pytest
import torch


@pytest.mark.parametrize("size", [(5, 7), (1, 4)])
def test_row_gather_sampling_equals_grid_sample(size):
    """The fused gather equals torch's grid_sample (bilinear, align_corners=True, border), values and gradients."""
    import torch.nn.functional as F

    from depthnerf.model.features import sample_maps

    hf, wf = size
    gen = torch.Generator().manual_seed(0)
    maps = torch.randn(3, 6, hf, wf, generator=gen, dtype=torch.float64, requires_grad=True)
    grid = ((torch.rand(3, 40, 2, generator=gen, dtype=torch.float64) * 2 - 1) * 1.3).requires_grad_(True)
    ref = F.grid_sample(maps, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=True)
    ref = ref[..., 0].transpose(1, 2)
    out = sample_maps(maps.permute(0, 2, 3, 1), grid)
    torch.testing.assert_close(out, ref)
    up = torch.randn(ref.shape, generator=gen, dtype=torch.float64)
    g_ref = torch.autograd.grad((ref * up).sum(), (maps, grid))
    g_out = torch.autograd.grad((out * up).sum(), (maps, grid))
    torch.testing.assert_close(g_out[0], g_ref[0])
    inside = (grid.abs() < 1).all(-1, keepdim=True).expand_as(grid)  # grid_sample's gradient at the clamp edge
    torch.testing.assert_close(g_out[1][inside], g_ref[1][inside])   # is a convention; compare inside only
    assert (~inside).any() and inside.any()


def test_inference_sampling_equals_the_fused_gather():
    """The no-gradient path (grid_sample on channels-first maps; CUDA inference) equals the fused gather,
    also for coordinates outside the map and non-finite ones, and keeps the maps' dtype."""
    from depthnerf.model.features import sample_maps, sample_maps_inference

    gen = torch.Generator().manual_seed(1)
    maps = torch.randn(2, 5, 7, 6, generator=gen)
    grid = (torch.rand(2, 50, 2, generator=gen) * 2 - 1) * 1.4
    grid[0, :4] = torch.tensor([[float("nan"), 0.3], [float("inf"), -0.2], [-float("inf"), float("nan")],
                                [0.1, float("inf")]])
    torch.testing.assert_close(sample_maps_inference(maps, grid), sample_maps(maps, grid))
    half = sample_maps_inference(maps.bfloat16(), grid)
    assert half.dtype == torch.bfloat16
    torch.testing.assert_close(half.float(), sample_maps(maps.bfloat16().float(), grid), atol=1e-2, rtol=1e-2)
    if torch.cuda.is_available():
        torch.testing.assert_close(sample_maps_inference(maps.cuda(), grid.cuda()).cpu(), sample_maps(maps, grid))
        # CUDA inference takes it (eager too, not only compiled); a call with gradients keeps the fused gather
        assert torch.equal(sample_maps(maps.cuda(), grid.cuda()), sample_maps_inference(maps.cuda(), grid.cuda()))


def test_in_frame_is_in_front_and_inside_the_closed_image_rectangle():
    """``in_frame`` of a 4 x 6 (H x W) image against its definition, one point at a time: z > 0 and
    ``0 <= u <= W``, ``0 <= v <= H`` (edges included), on a grid of (u, v) that straddles each edge and z of
    both signs."""
    from depthnerf.model.features import in_frame

    h, w = 4, 6
    values = [-0.5, 0.0, 3.0, 4.0, 4.5, 5.5, 6.0, 6.5]
    cases = [(u, v, z) for u in values for v in values for z in (-1.0, 0.0, 2.0)]
    uv = torch.tensor([[[[u, v] for u, v, _ in cases]]], dtype=torch.float64)
    cam = torch.tensor([[[[0.1, -0.2, z] for _, _, z in cases]]], dtype=torch.float64)
    out = in_frame(cam, uv, (h, w))
    expected = [float(z > 0 and 0 <= u <= w and 0 <= v <= h) for u, v, z in cases]
    assert out.dtype == torch.float64 and out[0, 0].tolist() == expected
    assert 0 < sum(expected) < len(expected)


def test_deferred_reads_equal_the_fused_gather():
    """:class:`MapSamples` (``--gather inside``: the MLP forward reads the maps) gives :func:`sample_maps`' values,
    whole or by channel ranges, for coordinates outside the map and non-finite ones; from bf16 maps it returns
    fp32 within bf16's rounding of the features; and traced by dynamo the same values."""
    from depthnerf.model.features import MapSamples, sample_maps

    gen = torch.Generator().manual_seed(2)
    maps = torch.randn(3, 5, 7, 12, generator=gen)
    grid = (torch.rand(3, 40, 2, generator=gen) * 2 - 1) * 1.4
    grid[1, :3] = torch.tensor([[float("nan"), 0.3], [float("inf"), -0.2], [-float("inf"), float("nan")]])
    ref = sample_maps(maps, grid).reshape(3 * 40, 12)
    deferred = MapSamples(maps=maps, grid=grid)
    corners = deferred.corners()
    torch.testing.assert_close(deferred.read(corners), ref, rtol=0, atol=1e-6)
    torch.testing.assert_close(deferred.read(corners, 4, 8), ref[:, 4:8], rtol=0, atol=1e-6)
    half = MapSamples(maps=maps.bfloat16(), grid=grid).read(corners, 8, 12)
    assert half.dtype == torch.float32
    torch.testing.assert_close(half, sample_maps(maps.bfloat16().float(), grid).reshape(120, 12)[:, 8:],
                               rtol=0, atol=1e-6)  # the same sum of the rounded features
    assert 0 < (half - ref[:, 8:]).abs().max() <= maps.abs().max() * 2 ** -8

    def read_block(m, g):
        samples = MapSamples(maps=m, grid=g)
        return samples.read(samples.corners(), 4, 8)

    # traced by dynamo (aot_eager: the graph without code generation; inductor's kernels run in the subprocesses
    # of tests/test_bench_view_variants.py, whose imports cannot collide with this process's)
    device = "cuda" if torch.cuda.is_available() else "cpu"
    compiled = torch.compile(read_block, backend="aot_eager", dynamic=True)
    torch.testing.assert_close(compiled(maps.to(device), grid.to(device)).cpu(), ref[:, 4:8], rtol=0, atol=1e-5)
