"""The batched training step and its deterministic pieces against reference loops and torch's own kernels:
per-object BatchNorm, the batched step vs one object at a time, a rank split, the deterministic feature gather
and map resizing vs ``grid_sample`` / ``interpolate``; CUDA-only checks skip cleanly without a GPU."""

from __future__ import annotations

import contextlib
import math
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
import torch.nn.functional as F

from depthnerf.data.cameras import look_at
from depthnerf.model import EncoderConfig, FieldConfig, PixelNeRF, PixelNeRFConfig, SourceViews
from depthnerf.model.features import resize_bilinear_matmul, sample_maps
from depthnerf.model.norm import ObjectBatchNorm2d, _repeat_index, _repeat_index_traced, object_groups
from depthnerf.render.config import RenderConfig, SamplerConfig
from depthnerf.train.batching import ItemKey, PackedBatch, TrainBatch
from depthnerf.train.step import BatchLoss, train_step

CUDA = pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")


@contextlib.contextmanager
def deterministic():
    before = torch.are_deterministic_algorithms_enabled()
    torch.use_deterministic_algorithms(True)
    try:
        yield
    finally:
        torch.use_deterministic_algorithms(before)


# --- deterministic feature gather and resizing -----------------------------------------------------------------

@pytest.mark.parametrize("size", [(5, 7), (1, 4), (16, 16)])
def test_deterministic_gather_equals_grid_sample(size):
    """Under deterministic algorithms the feature gather (index gathers) equals grid_sample with the model's
    convention (bilinear, align_corners=True, border padding): values and gradients, float32 tolerances."""
    hf, wf = size
    gen = torch.Generator().manual_seed(0)
    maps = torch.randn(3, 6, hf, wf, generator=gen, requires_grad=True)
    grid = ((torch.rand(3, 50, 2, generator=gen) * 2 - 1) * 1.3).requires_grad_(True)  # some beyond the border
    ref = F.grid_sample(maps, grid[:, :, None], mode="bilinear", padding_mode="border", align_corners=True)
    ref = ref[..., 0].transpose(1, 2)
    with deterministic():
        out = sample_maps(maps.permute(0, 2, 3, 1), grid)
        up = torch.randn(ref.shape, generator=gen)
        g_out = torch.autograd.grad((out * up).sum(), (maps, grid))
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    g_ref = torch.autograd.grad((ref * up).sum(), (maps, grid))
    torch.testing.assert_close(g_out[0], g_ref[0], rtol=1e-5, atol=1e-5)
    inside = (grid.abs() < 1).all(-1, keepdim=True).expand_as(grid)  # the clamp edge's gradient is a convention
    torch.testing.assert_close(g_out[1][inside], g_ref[1][inside], rtol=1e-4, atol=1e-4)


@pytest.mark.parametrize("shapes", [((8, 8), (16, 16)), ((4, 4), (16, 16)), ((2, 3), (7, 5)), ((1, 1), (4, 4))])
def test_matmul_resize_equals_interpolate(shapes):
    (hi, wi), (ho, wo) = shapes
    gen = torch.Generator().manual_seed(1)
    x = torch.randn(2, 3, hi, wi, generator=gen, requires_grad=True)
    ref = F.interpolate(x, (ho, wo), mode="bilinear", align_corners=True)
    out = resize_bilinear_matmul(x, (ho, wo))
    torch.testing.assert_close(out, ref, rtol=1e-5, atol=1e-6)
    up = torch.randn(ref.shape, generator=gen)
    torch.testing.assert_close(torch.autograd.grad((out * up).sum(), x)[0],
                               torch.autograd.grad((ref * up).sum(), x)[0], rtol=1e-5, atol=1e-5)


# --- per-object BatchNorm ----------------------------------------------------------------------------------------

@pytest.mark.parametrize("views", [1, 2])
def test_object_batchnorm_equals_one_call_per_object(views):
    """Grouped statistics equal BatchNorm run once per object: outputs and input gradients bit for bit (the same
    per-channel reductions), parameter gradients and running statistics up to float rounding (sums over the
    objects in another order)."""
    gen = torch.Generator().manual_seed(2)
    x = (torch.randn(3 * views, 4, 5, 6, generator=gen) * 2 + 1).requires_grad_(True)
    grouped, plain = ObjectBatchNorm2d(4), torch.nn.BatchNorm2d(4)
    with torch.no_grad():
        for bn in (grouped, plain):
            bn.weight.copy_(torch.tensor([1.0, 2.0, -0.5, 0.3]))
            bn.bias.copy_(torch.tensor([0.1, 0.0, 0.2, -0.3]))
    groups = object_groups(grouped, 3)
    out = grouped(x, groups)
    groups.fold()
    ref = torch.cat([plain(part) for part in x.split(views)])
    assert torch.equal(out, ref)
    up = torch.randn(out.shape, generator=gen)
    g = torch.autograd.grad((out * up).sum(), [x, grouped.weight, grouped.bias])
    g_ref = torch.autograd.grad((ref * up).sum(), [x, plain.weight, plain.bias])
    assert torch.equal(g[0], g_ref[0])
    for a, b in zip(g[1:], g_ref[1:], strict=True):
        torch.testing.assert_close(a, b, rtol=1e-4, atol=1e-5)
    torch.testing.assert_close(grouped.running_mean, plain.running_mean)
    torch.testing.assert_close(grouped.running_var, plain.running_var)
    assert int(grouped.num_batches_tracked) == int(plain.num_batches_tracked) == 3
    assert torch.equal(grouped(x), plain(x)) and torch.equal(grouped(x, object_groups(grouped, 1)), plain(x))


@pytest.mark.parametrize("sizes,groups", [([3, 5, 2, 3, 5, 2], 4), ([64] * 4, 2), ([1], 3), ([7, 1, 9], 1)])
def test_the_traced_repeat_index_equals_the_host_one_and_a_loop(sizes, groups):
    """The per-object BatchNorm plan's gather indices: the static-shape tensor version (used under
    ``torch.compile``) equals the host (numpy) version and a brute-force loop over vectors and copies."""
    out, back = _repeat_index(sizes, groups, torch.device("cpu"))
    traced = _repeat_index_traced(sizes, groups, torch.device("cpu"))
    assert torch.equal(traced[0], out) and torch.equal(traced[1], back)
    flat = torch.arange(sum(sizes))
    vectors = flat.split(sizes)
    laid_out = torch.cat([v for v in vectors for _ in range(groups)])  # each vector `groups` times in a row
    assert torch.equal(flat[out], laid_out)
    for k in range(groups):  # row k of the read-back = copy k of every vector
        assert torch.equal(laid_out[back[k]], flat)


def test_object_groups_plan_folds_every_layer_once_and_rejects_misuse():
    """A plan shares the repeats of all its tracked layers (one per momentum value) and folds them at once,
    equal to BatchNorm once per object, plan after plan; an untracked or evaluation-mode layer is not in the plan
    and stays plain. A layer run twice with one plan, a planned layer that did not run, and a layer outside the
    plan are errors, not a wrong fold."""
    gen = torch.Generator().manual_seed(4)
    net = torch.nn.ModuleList([ObjectBatchNorm2d(3), ObjectBatchNorm2d(5, momentum=0.3),
                               ObjectBatchNorm2d(3, track_running_stats=False), ObjectBatchNorm2d(5),
                               ObjectBatchNorm2d(4)])
    plain = [torch.nn.BatchNorm2d(3), torch.nn.BatchNorm2d(5, momentum=0.3),
             torch.nn.BatchNorm2d(3, track_running_stats=False), torch.nn.BatchNorm2d(5), torch.nn.BatchNorm2d(4)]
    net[4].eval()
    plain[4].eval()
    with torch.no_grad():
        for m in [*net, *plain]:
            m.weight.uniform_(0.5, 2, generator=gen)
            if m.running_mean is not None:
                m.running_mean.uniform_(-1, 1, generator=gen)
                m.running_var.uniform_(0.5, 2, generator=gen)
        for bn, ref in zip(net, plain, strict=True):
            ref.load_state_dict(bn.state_dict())
    for _ in range(2):
        xs = [torch.randn(4, m.num_features, 5, 5, generator=gen) for m in net]
        groups = object_groups(net, 2)
        assert [len(s.norms) for s in groups.shared] == [2, 1]  # the eval-mode and untracked layers: plain
        out = [bn(x, groups) for bn, x in zip(net, xs, strict=True)]
        groups.fold()
        refs = [torch.cat([bn(part) for part in x.split(2)]) if bn.training else bn(x)
                for bn, x in zip(plain, xs, strict=True)]
        for a, b in zip(out, refs, strict=True):
            torch.testing.assert_close(a, b, rtol=1e-5, atol=1e-5)
    for bn, ref in zip(net, plain, strict=True):
        for name, value in ref.state_dict().items():
            torch.testing.assert_close(bn.state_dict()[name], value)
    assert int(net[0].num_batches_tracked) == 4 and int(net[4].num_batches_tracked) == 0
    x = xs[0]
    groups = object_groups(net, 2)
    net[0](x, groups)
    with pytest.raises(RuntimeError, match="twice"):
        net[0](x, groups)
    with pytest.raises(RuntimeError, match="did not run"):
        groups.fold()
    with pytest.raises(RuntimeError, match="outside"):
        ObjectBatchNorm2d(3)(x, groups)


def test_encoder_walk_equals_torchvision_blocks():
    """The trunk runs torchvision's BasicBlocks through ``basic_block`` (so the plan reaches every BatchNorm):
    with plain BatchNorm it equals the blocks' own forward bit for bit, values and gradients."""
    from depthnerf.model.encoder import ResNetTrunk

    torch.manual_seed(0)
    trunk = ResNetTrunk(EncoderConfig(backbone="resnet18"), False).eval()
    x = torch.randn(2, 3, 32, 32, generator=torch.Generator().manual_seed(1), requires_grad=True)
    walked = trunk(x)
    refs = [trunk.relu(trunk.bn1(trunk.conv1(x)))]
    ref = trunk.maxpool(refs[0])
    for name in ("layer1", "layer2", "layer3"):
        ref = getattr(trunk, name)(ref)
        refs.append(ref)
    for a, b in zip(walked, refs, strict=True):
        assert torch.equal(a, b)
    up = [torch.randn(r.shape) for r in refs]
    g = torch.autograd.grad(sum((a * u).sum() for a, u in zip(walked, up, strict=True)), [x, *trunk.parameters()])
    g_ref = torch.autograd.grad(sum((a * u).sum() for a, u in zip(refs, up, strict=True)), [x, *trunk.parameters()])
    assert all(torch.equal(a, b) for a, b in zip(g, g_ref, strict=True))


# --- the batched step ----------------------------------------------------------------------------------------------

def tiny_setup(b: int, depth_aware: bool = False, seed: int = 0, device: str = "cpu", sym_pp: bool = False):
    """A tiny model, loss and batch of ``b`` objects; ``sym_pp``: as the shipped ``cpu-*-sym-pp`` models, the mirror
    branch and the prior read at each point (depth-aware), the first object with a symmetry plane, the rest without."""
    field = FieldConfig(d_hidden=32, n_blocks=3, combine_layer=2, density_bias_init=0.5)
    cfg = PixelNeRFConfig(encoder=EncoderConfig(backbone="resnet18"), coarse=field, fine=field, mirror=sym_pp,
                          prior_at_point=sym_pp)
    torch.manual_seed(seed)
    model = PixelNeRF(cfg, depth_aware=depth_aware).to(device).train()
    gen = torch.Generator().manual_seed(seed + 1)
    size, r = 32, 24
    az = torch.rand(b, 1, generator=gen) * 2 * math.pi
    eye = torch.stack([1.3 * torch.cos(az), 1.3 * torch.sin(az), 0.3 + 0.4 * torch.rand(b, 1, generator=gen)], -1)
    origins = torch.randn(b, r, 3, generator=gen) * 0.1 + torch.tensor([1.2, 0.0, 0.3])
    dirs = F.normalize(-origins + torch.randn(b, r, 3, generator=gen) * 0.1, dim=-1)
    plane = None
    if sym_pp:  # object 0 mirror-symmetric in the y = 0 plane, the others without a plane
        plane = torch.zeros(b, 4)
        plane[0, 1] = 1.0
    source = SourceViews(images=torch.rand(b, 1, 3, size, size, generator=gen), poses=look_at(eye),
                         focal=torch.full((b,), size * 1.0), principal=torch.full((b, 2), (size - 1) / 2),
                         disparity=torch.rand(b, 1, 1, size, size, generator=gen) if depth_aware else None,
                         symmetry_plane=plane)
    batch = TrainBatch(source=source, ray_origins=origins, ray_dirs=dirs, target_rgb=torch.rand(b, r, 3, generator=gen),
                       target_prior=torch.rand(b, r, generator=gen), target_fg=torch.rand(b, r, generator=gen) > 0.4,
                       target_cos=torch.rand(b, r, generator=gen) * 0.2 + 0.8)
    keys = [ItemKey(k, 1000 + 17 * k, True) for k in range(b)]
    render = RenderConfig(sampler=SamplerConfig(n_coarse=8, n_importance=4, n_gaussian=4))
    # every ray of the untrained tiny field has opacity ~0.39: a floor of 0 keeps them all in the depth term
    loss = BatchLoss(model, render, depth_weight=0.1, background_weight=0.2, foreground_weight=0.3,
                     depth_min_opacity=0.0)
    return model, loss, batch.to(device), keys


def grads(model: torch.nn.Module) -> dict[str, torch.Tensor]:
    out = {n: p.grad.detach().clone() for n, p in model.named_parameters() if p.grad is not None}
    model.zero_grad(set_to_none=True)
    return out


def assert_grads_close(a: dict, b: dict, rel: float) -> None:
    """Every parameter's gradient agrees to ``rel`` in norm (``|a - b| <= rel |b|``): elementwise tolerances do
    not fit gradients summed over thousands of rounding-affected terms (BatchNorm's backward cancels)."""
    assert a.keys() == b.keys() and a
    for k in a:
        x, y = a[k].double().cpu(), b[k].double().cpu()
        assert (x - y).norm() <= rel * y.norm() + 1e-12, (k, float((x - y).norm() / y.norm()))


@pytest.mark.parametrize("depth_aware", [False, True])
def test_batched_step_equals_the_per_object_loop(depth_aware):
    """All objects through the encoder and fields at once give the per-object loop's loss terms and gradients
    (BatchNorm statistics and noise are per object), up to float32 rounding."""
    model, loss, batch, keys = tiny_setup(3, depth_aware)
    batched = train_step(loss, batch, keys, 5, 0.8, 1.8, torch.device("cpu"))
    g_batched = grads(model)
    looped = train_step(loss, batch, keys, 5, 0.8, 1.8, torch.device("cpu"), per_object=True)
    g_looped = grads(model)
    assert batched.shape == (6,) and (batched[3:] > 0).all()  # depth, background and foreground terms are on
    torch.testing.assert_close(batched, looped, rtol=1e-5, atol=1e-7)
    assert_grads_close(g_batched, g_looped, rel=1e-4)


def compiled_step_check() -> None:
    """The body of :func:`test_compiled_fields_step_equals_the_eager_step`, run in a fresh interpreter."""
    from depthnerf.train.step import compiled_fields

    model, loss, batch, keys = tiny_setup(2, depth_aware=True)
    eager = train_step(loss, batch, keys, 3, 0.8, 1.8, torch.device("cpu"))
    g_eager = grads(model)
    runtime = compiled_fields(model)
    assert set(runtime.forwards) == {"coarse", "fine"}
    compiled = BatchLoss(model, loss.render_cfg, loss.depth_weight, loss.background_weight, runtime,
                         foreground_weight=loss.foreground_weight, depth_min_opacity=loss.depth_min_opacity)
    torch._dynamo.utils.counters.clear()
    fused = train_step(compiled, batch, keys, 3, 0.8, 1.8, torch.device("cpu"))
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] >= 2  # coarse and fine MLPs went through dynamo
    g_fused = grads(model)
    torch.testing.assert_close(fused, eager, rtol=1e-5, atol=1e-7)
    assert_grads_close(g_fused, g_eager, rel=1e-4)
    assert type(model.coarse.forward).__name__ == "method"  # the wrapper is held by the runtime, not the module


def compiled_whole_step_check(sym_pp: bool = False) -> None:
    """The body of :func:`test_compiled_whole_step_is_one_graph_and_equals_the_eager_step` (fresh interpreter)."""
    model, loss, batch, keys = tiny_setup(2, depth_aware=True, sym_pp=sym_pp)
    state = {k: v.clone() for k, v in model.state_dict().items()}
    eager = train_step(loss, batch, keys, 3, 0.8, 1.8, torch.device("cpu"))
    g_eager = grads(model)
    stats_eager = {k: v.clone() for k, v in model.state_dict().items() if "running" in k}
    model.load_state_dict(state)
    compiled = BatchLoss(model, loss.render_cfg, loss.depth_weight, loss.background_weight, compile_step="aot_eager",
                         foreground_weight=loss.foreground_weight, depth_min_opacity=loss.depth_min_opacity)
    torch._dynamo.utils.counters.clear()
    packed = PackedBatch.pack(batch).to("cpu")  # as the loop gets it from a worker: the fields view one storage
    whole = train_step(compiled, packed, keys, 3, 0.8, 1.8, torch.device("cpu"))
    assert torch._dynamo.utils.counters["stats"]["unique_graphs"] == 1  # encoder, render and loss: one graph
    assert not torch._dynamo.utils.counters["graph_break"], dict(torch._dynamo.utils.counters["graph_break"])
    torch.testing.assert_close(whole, eager, rtol=1e-5, atol=1e-7)
    assert_grads_close(grads(model), g_eager, rel=1e-4)
    for k, v in stats_eager.items():  # per-object BatchNorm folded its running statistics inside the graph
        torch.testing.assert_close(model.state_dict()[k], v, rtol=1e-5, atol=1e-6)


@pytest.mark.slow
@pytest.mark.parametrize("sym_pp", [False, True])
def test_compiled_whole_step_is_one_graph_and_equals_the_eager_step(sym_pp):
    """``depthnerf train --compile-step``: :meth:`BatchLoss.losses` (encoder with per-object BatchNorm, both
    render passes, the loss terms) traces as ONE graph with no break, and its loss terms, gradients and updated
    running statistics equal the eager step's up to float32 rounding (fresh interpreter, as below). Backend
    ``aot_eager``: dynamo's graph and AOT autograd's forward/backward without inductor's code generation, which
    takes minutes on this CPU (inductor's numerics: the fields test below). ``sym_pp``: the shipped ``cpu-*-sym-pp``
    models' mirror branch and prior at each point, which the GPU checkpoints continue training."""
    here = Path(__file__).resolve().parent
    code = (f"import sys; sys.path.insert(0, {str(here)!r}); import test_train_step as t; "
            f"t.compiled_whole_step_check(sym_pp={sym_pp})")
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=here.parent,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]


@pytest.mark.slow
def test_compiled_fields_step_equals_the_eager_step():
    """``depthnerf train --compile``: the fields' MLPs through ``torch.compile`` (inductor on the CPU here) give the
    eager step's loss terms and gradients up to float32 rounding, and leave the model's modules unchanged. Run in
    a fresh interpreter, as ``depthnerf train --compile`` runs: inductor's C++ toolchain imports setuptools, whose
    distutils shim can fail in a process that earlier tests have filled with other imports."""
    here = Path(__file__).resolve().parent
    code = f"import sys; sys.path.insert(0, {str(here)!r}); import test_train_step as t; t.compiled_step_check()"
    proc = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=here.parent,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]


def test_rank_split_of_the_batched_step_equals_the_whole_batch():
    """2 ranks x 2 objects (DDP averages their gradients) equal 1 process x 4 objects."""
    model, loss, batch, keys = tiny_setup(4)
    whole = train_step(loss, batch, keys, 2, 0.8, 1.8, torch.device("cpu"))
    g_whole = grads(model)
    parts, g_parts = [], []
    for lo in (0, 2):
        sub = batch.slice(lo, lo + 2, dim=0)
        parts.append(train_step(loss, sub, keys[lo:lo + 2], 2, 0.8, 1.8, torch.device("cpu")))
        g_parts.append(grads(model))
    torch.testing.assert_close((parts[0] + parts[1]) / 2, whole, rtol=1e-5, atol=1e-7)
    assert_grads_close({k: (g_parts[0][k] + g_parts[1][k]) / 2 for k in g_whole}, g_whole, rel=1e-4)


def deterministic_loss(loss: BatchLoss, batch: TrainBatch) -> torch.Tensor:
    """The step's colour loss with deterministic sampling (train=False), comparable across devices."""
    from depthnerf.render.pipeline import render_rays
    from depthnerf.render.rays import RayBundle

    m = loss.model
    enc = m.encode(batch.source)
    near = torch.full_like(batch.ray_origins[..., 0], 0.8)
    rays = RayBundle(batch.ray_origins, batch.ray_dirs, near, near + 1.0)
    out = render_rays(m.field(enc, "coarse"), m.field(enc, "fine"), rays, loss.render_cfg, train=False)
    return ((out.coarse.rgb - batch.target_rgb) ** 2).mean() + ((out.fine.rgb - batch.target_rgb) ** 2).mean()


@CUDA
def test_cuda_batched_model_matches_the_cpu_reference():
    """The batched model and renderer on CUDA (fp32, TF32 off) equal the CPU one-object-at-a-time reference
    within float32 tolerances: loss and gradients (sampling made deterministic, since CUDA and CPU generators
    draw different numbers). The CUDA training step itself runs and stays finite under bf16 autocast."""
    torch.backends.cuda.matmul.allow_tf32 = False
    torch.backends.cudnn.allow_tf32 = False
    model, loss, batch, keys = tiny_setup(3)
    ref = sum(deterministic_loss(loss, batch.item(k)) for k in range(3)) / 3
    ref.backward()
    g_ref = grads(model)
    model_c, loss_c, batch_c, _ = tiny_setup(3, device="cuda")
    model_c.load_state_dict(model.state_dict())
    out = deterministic_loss(loss_c, batch_c)
    out.backward()
    torch.testing.assert_close(out.cpu(), ref, rtol=1e-4, atol=1e-6)
    assert_grads_close(grads(model_c), g_ref, rel=1e-3)
    terms = train_step(loss_c, batch_c, keys, 1, 0.8, 1.8, torch.device("cuda"),
                       amp=torch.autocast("cuda", dtype=torch.bfloat16))
    assert terms.device.type == "cuda" and torch.isfinite(terms).all()


@CUDA
def test_cuda_deterministic_step_is_bitwise_repeatable():
    """Under --deterministic's settings two identical CUDA steps give bit-identical losses and gradients."""
    import os

    os.environ.setdefault("CUBLAS_WORKSPACE_CONFIG", ":4096:8")
    results = []
    with deterministic():
        for _ in range(2):
            model, loss, batch, keys = tiny_setup(3, device="cuda")
            out = train_step(loss, batch, keys, 1, 0.8, 1.8, torch.device("cuda"),
                             amp=torch.autocast("cuda", dtype=torch.bfloat16))
            results.append((out, grads(model)))
    assert torch.equal(results[0][0], results[1][0])
    for k, v in results[0][1].items():
        assert torch.equal(v, results[1][1][k]), k


@pytest.mark.parametrize("device", ["cpu", pytest.param("cuda", marks=CUDA)])
def test_resumed_fused_adam_keeps_channels_last_moments_and_steps_like_the_uninterrupted_one(device, tmp_path):
    """Checkpoint files hold contiguous moments; loading them back must restore a channels-last parameter's
    strides (CUDA's fused Adam refuses a layout mismatch), and the next step equals the uninterrupted run's."""
    from depthnerf.train.checkpoint import TrainingState, load_checkpoint, save_checkpoint

    torch.manual_seed(0)
    x = torch.randn(2, 4, 8, 8, device=device).to(memory_format=torch.channels_last)

    def make():
        torch.manual_seed(1)
        model = torch.nn.Conv2d(4, 8, 3).to(device=device, memory_format=torch.channels_last)
        return model, torch.optim.Adam(model.parameters(), lr=1e-2, fused=True)

    def step(model, opt):
        opt.zero_grad()
        model(x).square().mean().backward()
        opt.step()

    model, opt = make()
    step(model, opt)
    ckpt = save_checkpoint(tmp_path, model, opt, {"toy": 1}, TrainingState(step=1, best_psnr=0.0))
    step(model, opt)

    resumed, resumed_opt = make()
    load_checkpoint(ckpt, resumed, resumed_opt, {"toy": 1})
    for param in resumed.parameters():
        for name in ("exp_avg", "exp_avg_sq"):
            assert resumed_opt.state[param][name].stride() == param.stride(), name
    step(resumed, resumed_opt)
    for a, b in zip(model.parameters(), resumed.parameters(), strict=True):
        assert torch.equal(a, b)
