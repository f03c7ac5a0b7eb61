"""The depth-anything-v2 backend on a tiny random local checkpoint, and the bundled network."""

from __future__ import annotations

from pathlib import Path

import pytest
import torch

from depthnerf.depth.bundled import (
    DEFAULT_WEIGHTS,
    BundledDepthNet,
    BundledEstimator,
    BundledNetConfig,
    load_bundled_net,
    network_size,
    save_bundled,
)
from depthnerf.depth.depth_anything import licence_of, make_tiny_checkpoint
from depthnerf.depth.estimators import DepthEstimator, describe_estimator, make_estimator
from depthnerf.errors import DepthnerfError


@pytest.fixture(scope="module")
def tiny_da(tmp_path_factory) -> Path:
    return make_tiny_checkpoint(tmp_path_factory.mktemp("tiny_da"))


def test_depth_anything_tiny_checkpoint_end_to_end(tiny_da):
    est = make_estimator("depth-anything-v2", str(tiny_da))
    assert isinstance(est, DepthEstimator) and not est.needs_depth
    images = torch.rand(3, 3, 40, 52, generator=torch.Generator().manual_seed(0))
    # the processor resizes to multiples of the 14-pixel patch
    pixels = est.processor(images=list(images), return_tensors="pt", do_rescale=False)["pixel_values"]
    assert pixels.shape[0] == 3 and pixels.shape[-1] % 14 == 0 and pixels.shape[-2] % 14 == 0
    assert pixels.shape[-2:] != images.shape[-2:]
    disp = est.predict(images)
    assert disp.shape == (3, 40, 52) and disp.dtype == torch.float32  # resized back to the image
    assert torch.isfinite(disp).all() and disp.std() > 0
    single = torch.cat([est.predict(images[i:i + 1]) for i in range(3)])
    assert torch.allclose(single, disp, atol=1e-4, rtol=1e-4)  # batching does not change the output
    prov = est.provenance
    assert prov.estimator == "depth-anything-v2" and len(prov.weights_hash) == 64 and prov.input_resolution == 42
    assert prov == describe_estimator("depth-anything-v2", str(tiny_da))


def test_depth_anything_hash_follows_weights_and_bad_paths_fail(tiny_da, tmp_path):
    other = make_tiny_checkpoint(tmp_path / "other")
    with torch.no_grad():
        from safetensors.torch import load_file, save_file

        state = load_file(other / "model.safetensors")
        key = next(iter(state))
        state[key] = state[key] + 1.0
        save_file(state, other / "model.safetensors", metadata={"format": "pt"})
    assert describe_estimator("depth-anything-v2", str(other)).weights_hash != \
        describe_estimator("depth-anything-v2", str(tiny_da)).weights_hash
    with pytest.raises(DepthnerfError, match="no such checkpoint directory"):
        make_estimator("depth-anything-v2", str(tmp_path / "missing"))
    (tmp_path / "empty").mkdir()
    with pytest.raises(DepthnerfError, match="no \\*.safetensors"):
        make_estimator("depth-anything-v2", str(tmp_path / "empty"))
    hub = describe_estimator("depth-anything-v2")
    assert hub.checkpoint == "depth-anything/Depth-Anything-V2-Base-hf" and "CC-BY-NC-4.0" in hub.licence
    assert "Apache-2.0" in describe_estimator("depth-anything-v2", "depth-anything/Depth-Anything-V2-Small-hf").licence


def test_depth_anything_licence_is_judged_from_the_checkpoints_own_name(tmp_path):
    """A size word in a folder above the checkpoint named the licence: a non-commercial Large model under
    ``small_disk/`` was recorded as Apache-2.0."""
    assert "CC-BY-NC-4.0" in licence_of("/data/small_disk/Depth-Anything-V2-Large-hf")
    assert "Apache-2.0" in licence_of("/data/large_disk/Depth-Anything-V2-Small-hf/")
    assert licence_of("/srv/database/da-v2").startswith("unknown")
    folder = make_tiny_checkpoint(tmp_path / "small_runs" / "Depth-Anything-V2-Base-hf")
    assert "CC-BY-NC-4.0" in describe_estimator("depth-anything-v2", str(folder)).licence


def test_bundled_network_round_trip_and_resizing(tmp_path):
    config = BundledNetConfig(widths=(4, 6, 8), input_size=32, unshuffle=2)
    torch.manual_seed(0)
    net = BundledDepthNet(config)
    for module in net.modules():  # non-trivial running statistics, so that they must be saved too
        if isinstance(module, torch.nn.BatchNorm2d):
            module.running_mean.uniform_(-0.1, 0.1)
            module.running_var.uniform_(0.5, 1.5)
    path = tmp_path / "w.safetensors"
    save_bundled(net, path, notes={"trained_on": "nothing"})
    loaded, meta = load_bundled_net(path)
    assert loaded.config == config and meta["trained_on"] == "nothing"
    x = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        assert torch.allclose(loaded(x), net.eval()(x), atol=1e-6)
    est = make_estimator("bundled", str(path))
    assert isinstance(est, BundledEstimator) and est.provenance.input_resolution == 32
    out = est.predict(torch.rand(3, 3, 50, 70))
    assert out.shape == (3, 50, 70) and torch.isfinite(out).all()
    assert network_size(config, 50, 70) == (24, 32)
    assert torch.allclose(est.predict(x), loaded(x), atol=1e-6)  # no resize at the native size
    path.write_bytes(b"not safetensors")
    with pytest.raises(DepthnerfError, match="w.safetensors"):
        make_estimator("bundled", str(path))
    with pytest.raises(DepthnerfError, match="not found"):
        make_estimator("bundled", str(tmp_path / "nope.safetensors"))


def test_shipped_bundled_weights_load_and_predict():
    assert DEFAULT_WEIGHTS.is_file(), "the bundled weights must ship with the package"
    assert DEFAULT_WEIGHTS.stat().st_size <= 10 * 2**20
    est = make_estimator("bundled")
    images = torch.ones(2, 3, 128, 128)
    images[:, :, 40:90, 30:100] = torch.tensor([0.6, 0.2, 0.2])[:, None, None]
    disp = est.predict(images)
    assert disp.shape == (2, 128, 128) and torch.isfinite(disp).all()
    assert est.provenance.weights_hash == describe_estimator("bundled").weights_hash
    assert est.predict(torch.rand(1, 3, 64, 96)).shape == (1, 64, 96)


def test_shipped_bundled_weights_beat_a_flat_prior_on_unseen_synthetic_objects(tmp_path):
    """Regression guard for the shipped weights: on objects of a seed never trained on, the aligned AbsRel is
    well below that of a constant prediction (which already reaches ~0.06 cars / ~0.08 chairs)."""
    from depthnerf.data.srn import index_split, load_object
    from depthnerf.data.synth.generate import SynthConfig, generate
    from depthnerf.depth.metrics import affine_invariant_scores

    est = make_estimator("bundled")
    for category in ("cars", "chairs"):
        generate(SynthConfig(category=category, out=tmp_path, train_objects=0, val_objects=0, test_objects=1,
                             views_test=8, seed=777, progress=False))
        obj = load_object(index_split(tmp_path, category, "test").objects[0], with_depth=True, pixel_center=0.0)
        ours = affine_invariant_scores(est.predict(obj.images), obj.depths)
        flat = affine_invariant_scores(torch.zeros_like(obj.depths), obj.depths)
        assert ours.valid.all()
        assert ours.abs_rel.mean() < 0.75 * flat.abs_rel.mean(), category
        assert ours.abs_rel.mean() < 0.06 and ours.delta1.mean() > 0.95, category
