"""The inference policy (depthnerf.render.precision): CPU numerics untouched, CUDA defaults, and the field's
autocast/point-chunk switches exercised on the CPU."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from test_model import query, randomize, small_config, sources

import depthnerf.render.precision as precision
from depthnerf.errors import DepthnerfError
from depthnerf.model import PixelNeRF
from depthnerf.model.pixelnerf import FieldRuntime
from depthnerf.render.precision import (
    CPU_POINT_CHUNK,
    CPU_RAY_CHUNK,
    CUDA_POINT_CHUNK,
    field_runtime,
    inference_policy,
)


def test_policy_per_device():
    cpu = inference_policy("cpu")
    assert cpu.autocast is None and cpu.ray_chunk == CPU_RAY_CHUNK == 4096 and cpu.point_chunk == CPU_POINT_CHUNK
    cuda = inference_policy("cuda")
    assert cuda.autocast == torch.bfloat16 and cuda.ray_chunk > cpu.ray_chunk and cuda.point_chunk == CUDA_POINT_CHUNK
    assert inference_policy("cuda", fp32=True).autocast is None
    assert cuda.residual is None and cuda.compile_mode == "default" and not cuda.compile
    assert inference_policy("cuda", bf16_residual=True).residual == torch.bfloat16
    tuned = inference_policy("cuda", compile_mode="max-autotune-no-cudagraphs")
    assert tuned.compile and tuned.compile_mode == "max-autotune-no-cudagraphs"  # the mode implies --compile


@pytest.mark.parametrize("device, flags, line", [
    ("cpu", {"bf16_residual": True}, "--bf16-residual is a CUDA setting (bf16 autocast); on cpu the fields "
                                     "render in fp32"),
    ("cuda", {"bf16_residual": True, "fp32": True}, "--bf16-residual keeps the residual stream in bf16 under bf16 "
                                                    "autocast; --fp32 turns autocast off: pass one of them"),
    ("cuda", {"compile_mode": "fastest"}, "--compile-mode must be one of default, reduce-overhead, max-autotune, "
                                          "max-autotune-no-cudagraphs, got 'fastest'"),
    ("cpu", {"gather": "inline"}, "--gather must be one of before, inside, inside-bf16, got 'inline'"),
])
def test_flags_a_device_cannot_run_are_one_line(device, flags, line):
    with pytest.raises(DepthnerfError) as err:
        inference_policy(device, **flags)
    assert str(err.value) == line


def test_the_compile_mode_reaches_torch_compile(monkeypatch):
    """``--compile-mode`` is what ``torch.compile`` gets (no compilation here: the call is recorded)."""
    asked = []
    monkeypatch.setattr(precision.torch, "compile", lambda fn, **kw: asked.append(kw) or fn)
    model = PixelNeRF(small_config(), depth_aware=False)
    field_runtime(model, inference_policy("cpu", compile_mode="max-autotune-no-cudagraphs"))
    assert asked == [{"dynamic": True, "mode": "max-autotune-no-cudagraphs"}] * 2  # coarse and fine
    asked.clear()
    field_runtime(model, inference_policy("cpu", compile=True))
    assert [kw["mode"] for kw in asked] == ["default", "default"]


@torch.no_grad()
def test_a_bf16_residual_stream_stays_within_bf16_rounding():
    """The CUDA opt-in ``--bf16-residual``, on the CPU: under bf16 autocast the residual stream is kept in bf16.
    The outputs stay fp32 and within bf16 rounding of the fp32 field, and differ from the fp32-stream bf16 ones
    (so the setting took effect); the runtime leaves nothing on the model."""
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    enc = model.encode(sources())
    pts, dirs = query(r=9, s=5)
    ref_rgb, ref_sigma = model.field(enc, "fine")(pts, dirs)
    amp_rgb, amp_sigma = model.field(enc, "fine", FieldRuntime(autocast=torch.bfloat16))(pts, dirs)
    runtime = FieldRuntime(autocast=torch.bfloat16, residual=torch.bfloat16, chunk_points=11)
    rgb, sigma = model.field(enc, "fine", runtime)(pts, dirs)
    assert rgb.dtype == torch.float32 and sigma.dtype == torch.float32
    torch.testing.assert_close(rgb, ref_rgb, rtol=0, atol=3e-2)
    torch.testing.assert_close(sigma, ref_sigma, rtol=5e-2, atol=5e-2)
    assert not torch.equal(rgb, amp_rgb) or not torch.equal(sigma, amp_sigma)
    assert model.field(enc, "fine")(pts, dirs)[0].equal(ref_rgb)


def test_the_residual_dtype_is_refused_with_autograd():
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    field = model.network("fine")
    inputs, latent = torch.zeros(1, 1, 3, field.lin_in.in_features), torch.zeros(1, 1, 3, field.lin_z[0].in_features)
    with pytest.raises(ValueError, match="inference setting"):
        field(inputs, latent, projected=False, residual_dtype=torch.bfloat16)


@torch.no_grad()
def test_cpu_runtime_is_fp32_in_its_point_chunks_and_bf16_stays_close():
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    enc = model.encode(sources())
    pts, dirs = query(r=9, s=5)
    ref_rgb, ref_sigma = model.field(enc, "fine")(pts, dirs)
    rgb, sigma = model.field(enc, "fine", field_runtime(model, inference_policy("cpu")))(pts, dirs)
    # the CPU runtime is fp32 in CPU_POINT_CHUNK chunks: exactly that, and the config's chunking to fp32 rounding
    own = model.field(enc, "fine", FieldRuntime(chunk_points=CPU_POINT_CHUNK))(pts, dirs)
    assert torch.equal(rgb, own[0]) and torch.equal(sigma, own[1])
    torch.testing.assert_close(rgb, ref_rgb, rtol=1e-5, atol=1e-6)
    torch.testing.assert_close(sigma, ref_sigma, rtol=1e-5, atol=1e-5)
    # the CUDA settings' logic, on the CPU: bf16 autocast and another point chunk (fp32 outputs, bf16 accuracy)
    rgb, sigma = model.field(enc, "fine", FieldRuntime(autocast=torch.bfloat16, chunk_points=11))(pts, dirs)
    assert rgb.dtype == torch.float32 and sigma.dtype == torch.float32
    torch.testing.assert_close(rgb, ref_rgb, rtol=0, atol=3e-2)
    torch.testing.assert_close(sigma, ref_sigma, rtol=5e-2, atol=5e-2)
    rgb, _ = model.field(enc, "fine", FieldRuntime(chunk_points=11))(pts, dirs)  # other chunking, fp32: rounding
    torch.testing.assert_close(rgb, ref_rgb, rtol=1e-5, atol=1e-6)
    assert model.field(enc, "fine")(pts, dirs)[0].equal(ref_rgb)  # the runtimes left nothing on the model


@pytest.mark.parametrize("separate_fine", [True, False])
@torch.no_grad()
def test_compile_wraps_the_forwards_without_touching_the_modules(separate_fine):
    """``--compile`` gives the runtime compiled wrappers of the MLPs' forwards (the fine pass uses the coarse one's
    when there is no fine network) and changes no module; the field calls what the runtime holds."""
    cfg = small_config()
    if not separate_fine:
        cfg = dataclasses.replace(cfg, fine=None)
    model = randomize(PixelNeRF(cfg, depth_aware=False))
    runtime = field_runtime(model, inference_policy("cpu", compile=True))
    assert set(runtime.forwards) == {"coarse", "fine"}
    assert (runtime.forwards["fine"] is runtime.forwards["coarse"]) == (not separate_fine)
    assert all("forward" not in vars(m) for m in model.modules())  # nothing monkey-patched
    calls = []

    def counted(which):
        def forward(*args, **kwargs):
            calls.append(which)
            return model.network(which)(*args, **kwargs)
        return forward

    enc = model.encode(sources())
    pts, dirs = query(r=4, s=3)
    ref = model.field(enc, "fine")(pts, dirs)
    out = model.field(enc, "fine", FieldRuntime(forwards={"fine": counted("fine")}))(pts, dirs)
    assert calls and set(calls) == {"fine"} and all(torch.equal(a, b) for a, b in zip(out, ref, strict=True))


def test_source_frame_geometry_stays_fp32_under_autocast():
    """Under bf16 autocast the points and view directions are still brought into the source cameras in fp32
    (a bf16 matmul would round the coordinates to ~1e-3 before the positional encoding and the projection):
    the results equal the fp32 ones bit for bit, values and gradients."""
    from depthnerf.data.cameras import look_at
    from depthnerf.model.features import rotate_dirs, to_source_frames

    gen = torch.Generator().manual_seed(3)
    pts = (torch.rand(2, 7, 3, generator=gen) * 2 - 1).requires_grad_(True)
    dirs = torch.nn.functional.normalize(torch.randn(2, 7, 3, generator=gen), dim=-1)
    w2c = torch.linalg.inv(look_at(torch.randn(2, 2, 3, generator=gen) + torch.tensor([0.0, 0.0, 2.0])))
    ref = (*to_source_frames(pts, w2c), rotate_dirs(dirs, w2c))
    g_ref = torch.autograd.grad(sum(t.sum() for t in ref[:2]), pts)[0]
    with torch.autocast("cpu", dtype=torch.bfloat16):
        out = (*to_source_frames(pts, w2c), rotate_dirs(dirs, w2c))
    g_out = torch.autograd.grad(sum(t.sum() for t in out[:2]), pts)[0]  # backward outside, as train_step
    for a, b in zip(out, ref, strict=True):
        assert a.dtype == torch.float32 and torch.equal(a, b)
    assert torch.equal(g_out, g_ref)


@torch.no_grad()
def test_a_compiled_field_keeps_the_bf16_residual_stream():
    """``--compile`` with ``--bf16-residual``: the MLP forward traced by dynamo (backend ``aot_eager``: the graph
    without inductor's code generation, seconds on the CPU) gives the eager bf16-stream field's values."""
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    enc = model.encode(sources())
    pts, dirs = query(r=9, s=5)
    eager = FieldRuntime(autocast=torch.bfloat16, residual=torch.bfloat16)
    forwards = {w: torch.compile(model.network(w).forward, dynamic=True, backend="aot_eager")
                for w in ("coarse", "fine")}
    compiled = dataclasses.replace(eager, forwards=forwards)
    for a, b in zip(model.field(enc, "fine", compiled)(pts, dirs), model.field(enc, "fine", eager)(pts, dirs),
                    strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


@pytest.mark.parametrize("mirror, on_map, views", [(False, True, 1), (True, True, 2), (True, False, 1)])
@torch.no_grad()
def test_the_gather_inside_the_mlp_gives_the_same_fields(mirror, on_map, views):
    """``--gather inside``: the MLP forward reads the maps itself (:class:`MapSamples`), with projected features
    or not, the mirror branch and several source views; the fields' values are those of the gather before the MLP up to float
    rounding, ``inside-bf16`` within the features' bf16 rounding, and traced by dynamo (``aot_eager``) the same."""
    cfg = small_config(lin_z_on_map=on_map)
    cfg.mirror = mirror
    model = randomize(PixelNeRF(cfg, depth_aware=False))
    src = sources(b=2, v=views)
    if mirror:
        src.symmetry_plane = torch.tensor([[0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]])
    enc = model.encode(src)
    pts, dirs = query(r=9, s=5)
    runtimes = {"before": FieldRuntime(), "inside": FieldRuntime(gather_inside=True),
                "inside-bf16": FieldRuntime(gather_inside=True, map_dtype=torch.bfloat16)}
    ref = model.field(enc, "fine", runtimes["before"])(pts, dirs)
    for a, b in zip(model.field(enc, "fine", runtimes["inside"])(pts, dirs), ref, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-5)
    half = model.field(enc, "fine", runtimes["inside-bf16"])(pts, dirs)
    gaps = [float((a - b).abs().max()) for a, b in zip(half, ref, strict=True)]
    assert 0 < max(gaps) < 0.05  # the features rounded to bf16 (8 bits of mantissa)
    forwards = {w: torch.compile(model.network(w).forward, dynamic=True, backend="aot_eager")
                for w in ("coarse", "fine")}
    compiled = dataclasses.replace(runtimes["inside-bf16"], forwards=forwards)
    for a, b in zip(model.field(enc, "fine", compiled)(pts, dirs), half, strict=True):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)


def test_the_gather_flag_reaches_the_runtime_and_implies_compile(monkeypatch):
    """``--gather``: ``inside*`` implies ``--compile`` (no compilation here: the call is recorded) and sets the
    runtime's ``gather_inside`` / ``map_dtype``; ``before`` leaves both off."""
    monkeypatch.setattr(precision.torch, "compile", lambda fn, **kw: fn)
    model = PixelNeRF(small_config(), depth_aware=False)
    for gather, inside, dtype in (("before", False, None), ("inside", True, None), ("inside-bf16", True, torch.bfloat16)):
        policy = inference_policy("cpu", gather=gather)
        runtime = field_runtime(model, policy)
        assert policy.gather == gather and policy.compile == inside and bool(runtime.forwards) == inside
        assert runtime.gather_inside == inside and runtime.map_dtype == dtype


def test_the_gather_inside_is_an_inference_setting():
    """With autograd (training) the features are sampled before the MLP whatever the runtime says, so the
    gradients are the fused ``embedding_bag``'s; the maps are not cast."""
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    pts, dirs = query()
    grads = []
    for runtime in (FieldRuntime(), FieldRuntime(gather_inside=True, map_dtype=torch.bfloat16)):
        model.zero_grad()
        rgb, sigma = model.field(model.encode(sources()), "coarse", runtime)(pts, dirs)
        (rgb.sum() + sigma.sum()).backward()
        grads.append(model.coarse.lin_z[0].weight.grad.clone())
    assert torch.equal(grads[0], grads[1]) and grads[0].abs().sum() > 0


@torch.no_grad()
def test_the_relu_epilogue_gives_the_blocks_values():
    """``FieldRuntime.relu_epilogue``: each block's first linear as one ``_addmm_activation`` (bias and ReLU in
    the matrix product's epilogue on CUDA). The field's values are the plain blocks' in fp32 (to float rounding)
    and under bf16 autocast (to bf16 rounding: the same bf16 operands, the bias added in another order), eager and
    traced by dynamo (``aot_eager``); the op keeps the autocast dtype."""
    from depthnerf.model.field import linear_relu

    layer = torch.nn.Linear(6, 5)
    x = torch.randn(7, 6)
    torch.testing.assert_close(linear_relu(x, layer), torch.relu(layer(x)))
    with torch.autocast("cpu", dtype=torch.bfloat16):
        assert linear_relu(x, layer).dtype == torch.bfloat16
    model = randomize(PixelNeRF(small_config(), depth_aware=False))
    enc = model.encode(sources())
    pts, dirs = query(r=9, s=5)
    forwards = {w: torch.compile(model.network(w).forward, dynamic=True, backend="aot_eager")
                for w in ("coarse", "fine")}
    for autocast, atol in ((None, 1e-5), (torch.bfloat16, 2e-2)):
        plain = FieldRuntime(autocast=autocast)
        ref = model.field(enc, "fine", plain)(pts, dirs)
        for runtime in (dataclasses.replace(plain, relu_epilogue=True),
                        dataclasses.replace(plain, relu_epilogue=True, forwards=forwards)):
            for a, b in zip(model.field(enc, "fine", runtime)(pts, dirs), ref, strict=True):
                torch.testing.assert_close(a, b, rtol=0, atol=atol)
