"""The inference session (:mod:`depthnerf.infer.session`): one checkpoint and the caller's overrides resolved once,
and every inference path (``depthnerf eval``, ``depthnerf reconstruct`` / ``Reconstructor``, the demo, the app)
a thin user of it.

- A device whose policy says bf16 and large ray chunks (CUDA's, simulated on the CPU) reaches ``Reconstructor``,
  the demo and the app without any flag: the field runs under bf16 autocast with the policy's chunks.
- The same checkpoint gets the same resolved spec, device policy and chunk through all four paths.
- The prior's override rule is one function; its refusals are one line each.
- A checkpoint written by training states its data's framing; older ones derive it at load.
"""

from __future__ import annotations

import contextlib
import io
import json
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_checkpoints import save_tiny, tiny_bundled, tiny_config
from fixtures_srn import make_srn_fixture

from depthnerf.app.logic import AppConfig, AppSession, examples
from depthnerf.cli import main
from depthnerf.demo import load_checkpoint_for
from depthnerf.depth.prior import PriorConfig
from depthnerf.errors import DepthnerfError
from depthnerf.infer import session as session_module
from depthnerf.infer.session import InferenceSession, SessionOptions, resolve_prior
from depthnerf.pretrained.load import SPEC_FRAMING, load_pretrained
from depthnerf.reconstruct.reconstructor import ReconstructConfig, Reconstructor
from depthnerf.render.precision import CUDA_POINT_CHUNK, CUDA_RAY_CHUNK, InferencePolicy, inference_policy

SIMULATED_GPU = InferencePolicy(autocast=torch.bfloat16, ray_chunk=CUDA_RAY_CHUNK, point_chunk=CUDA_POINT_CHUNK,
                                compile=False)
"""CUDA's policy (bf16 autocast, 65536 rays, 2^20 points per chunk), given to a CPU device."""


def quiet(*args) -> int:
    with contextlib.redirect_stdout(io.StringIO()):
        return main([str(a) for a in args])


@pytest.fixture(scope="module")
def tiny(tmp_path_factory) -> dict[str, Path]:
    """A tiny depth-aware cars checkpoint (16 px, random bundled depth weights) and a test split with its
    prior cache."""
    tmp = tmp_path_factory.mktemp("session")
    weights = tiny_bundled(tmp / "bundled.safetensors")
    ckpt = save_tiny(tmp / "cars.safetensors", tiny_config("cars", "bundled", weights))
    root = make_srn_fixture(tmp / "data", "cars", {"test": 1}, views=4, size=16, with_mask=True)
    assert quiet("depth", "--data", root, "--depth", "bundled", "--depth-checkpoint", weights, "--splits", "test",
                 "--no-progress") == 0
    return {"tmp": tmp, "ckpt": ckpt, "root": root, "weights": weights}


@pytest.fixture
def simulated_gpu(monkeypatch):
    """Every session's device policy is CUDA's (the CPU computes it)."""
    asked = []

    def policy(device, *, fp32=False, compile=False, **_):
        asked.append(torch.device(device).type)
        return SIMULATED_GPU
    monkeypatch.setattr(session_module, "inference_policy", policy)
    return asked


def test_reconstructor_gets_the_device_policy(tiny, simulated_gpu, monkeypatch):
    """No flag and no policy argument: ``Reconstructor.from_pretrained`` (the Python API) renders under the
    device's policy, bf16 autocast and CUDA-sized chunks, exactly as ``depthnerf reconstruct`` does."""
    rec = Reconstructor.from_pretrained(tiny["ckpt"])
    session = rec.session
    assert simulated_gpu == ["cpu"] and session.policy is SIMULATED_GPU and session.chunk == CUDA_RAY_CHUNK
    assert session.runtime.autocast == torch.bfloat16 and session.runtime.chunk_points == CUDA_POINT_CHUNK
    calls = []
    render_poses = session_module.render_poses

    def spy(model, enc, poses, intr, near, far, cfg, chunk, device, on_group=None, guide=None, runtime=None):
        calls.append((chunk, runtime))
        return render_poses(model, enc, poses, intr, near, far, cfg, chunk, device, on_group, guide, runtime)
    monkeypatch.setattr(session_module, "render_poses", spy)
    photo = examples()[0]
    cfg = ReconstructConfig(views=2, mesh_resolution=8, background_removal="off")
    bf16 = rec.reconstruct(photo, config=cfg)
    assert calls and all(chunk == CUDA_RAY_CHUNK and runtime is session.runtime for chunk, runtime in calls)
    # the same photo under the CPU's own policy: fp32, 4096 rays; bf16 moved the pixels by bf16 rounding only
    monkeypatch.setattr(session_module, "inference_policy", inference_policy)
    fp32 = Reconstructor.from_pretrained(tiny["ckpt"]).reconstruct(photo, config=cfg)
    assert calls[-1][0] == 4096 and calls[-1][1].autocast is None
    assert not np.array_equal(bf16.views, fp32.views) and np.abs(bf16.views - fp32.views).max() < 0.05


def test_demo_and_app_get_the_device_policy(tiny, simulated_gpu):
    demo = load_checkpoint_for("cars", str(tiny["ckpt"]))
    app = AppSession(AppConfig(checkpoints=(str(tiny["ckpt"]),), work_dir=tiny["tmp"] / "app"))
    rec = app.models.get(str(tiny["ckpt"]), "bundled", str(tiny["weights"]))
    for session in (demo, rec.session):
        assert session.policy is SIMULATED_GPU and session.chunk == CUDA_RAY_CHUNK
        assert session.runtime.autocast == torch.bfloat16


def test_every_path_resolves_the_same_spec(tiny, monkeypatch):
    """eval, reconstruct, the demo and the app build their session from the same checkpoint: the same resolved
    spec (model, render config, prior and weights, pixel centre, framing, resolution), device policy and chunk."""
    made: list[InferenceSession] = []
    init = InferenceSession.__init__

    def recording(self, *args, **kwargs):
        init(self, *args, **kwargs)
        made.append(self)
    monkeypatch.setattr(InferenceSession, "__init__", recording)
    ckpt, tmp = str(tiny["ckpt"]), tiny["tmp"]
    assert quiet("eval", "--checkpoint", ckpt, "--data", tiny["root"], "--out", tmp / "eval", "--no-mesh",
                 "--no-progress", "--device", "cpu") == 0
    assert quiet("reconstruct", examples()[0], "--checkpoint", ckpt, "--out", tmp / "rec", "--views", "1",
                 "--mesh-resolution", "0", "--background-removal", "off", "--no-progress", "--device", "cpu") == 0
    load_checkpoint_for("cars", ckpt)
    AppSession(AppConfig(checkpoints=(ckpt,), work_dir=tmp / "app2")).models.get(ckpt)
    assert len(made) == 4
    eval_s, rec_s, demo_s, app_s = made
    assert (eval_s.options.inputs, rec_s.options.inputs, demo_s.options.inputs, app_s.options.inputs) == (
        "dataset", "photos", "views", "photos")
    for other in (rec_s, demo_s, app_s):
        assert other.spec == eval_s.spec and other.policy == eval_s.policy and other.chunk == eval_s.chunk
        assert other.pretrained.sha256 == eval_s.pretrained.sha256 and other.framing == eval_s.framing
    assert eval_s.spec.prior == PriorConfig("bundled", str(tiny["weights"])) and eval_s.spec.framing == "srn"
    summary = json.loads((tmp / "eval" / "summary.json").read_text())
    manifest = json.loads((tmp / "rec" / "manifest.json").read_text())
    assert summary["pixel_center"] == eval_s.spec.pixel_center and summary["z_range"] == manifest["settings"]["z_range"]
    assert summary["depth_prior"] == manifest["settings"]["depth_estimator"] == "bundled"


def test_one_prior_override_rule():
    trained = PriorConfig("bundled", "w.safetensors")
    assert trained.override() == trained and trained.override("bundled") == trained
    assert trained.override(None, "v") == PriorConfig("bundled", "v")
    assert trained.override("depth-anything-v2") == PriorConfig("depth-anything-v2", None)
    assert trained.override("oracle", "x") == PriorConfig("oracle", "x")
    assert resolve_prior(trained, None, None, photos=True, where="c") == trained
    base = PriorConfig("none")
    assert resolve_prior(base, None, None, photos=True, where="c") == base
    assert resolve_prior(base, "none", None, photos=True, where="c") == base
    refusals = [(base, "bundled", None, True, "c: a baseline checkpoint (trained without a depth prior) takes no "
                 "depth prior; drop --depth bundled, or use a depth-aware checkpoint"),
                (base, None, "w", True, "drop --depth-checkpoint"),
                (trained, "none", None, False, "c: depth-aware checkpoint needs a depth prior"),
                (PriorConfig("oracle"), None, None, True, "c: the 'oracle' prior needs ground-truth depth, which a "
                 "photo does not have; pass --depth depth-anything-v2 or bundled")]
    for prior, depth, weights, photos, line in refusals:
        with pytest.raises(DepthnerfError, match=line.replace("(", r"\(").replace(")", r"\)")):
            resolve_prior(prior, depth, weights, photos=photos, where="c")
    assert resolve_prior(PriorConfig("oracle"), None, None, photos=False, where="c") == PriorConfig("oracle")
    with pytest.raises(DepthnerfError, match="--chunk must be >= 1, got 0"):
        SessionOptions(chunk=0)


def test_session_overrides(tiny):
    """Pixel centre and guided request land in the resolved spec; the checkpoint's own stays ``pretrained.spec``."""
    from depthnerf.render.source_guide import guided_config

    session = InferenceSession(tiny["ckpt"], SessionOptions(pixel_center=0.5, guided=guided_config(12), chunk=99))
    trained = session.pretrained.spec
    assert session.spec.pixel_center == 0.5 and trained.pixel_center == 0.0 and session.chunk == 99
    assert session.guided is not None and session.guided.budget == 12 and not trained.render.guided.enabled
    assert session.spec.model == trained.model and session.spec.prior == trained.prior


def test_training_states_the_framing_and_older_checkpoints_derive_it(tmp_path):
    root = make_srn_fixture(tmp_path / "data", "cars", {"train": 2}, views=4, size=32, with_mask=True)
    (root / "cars_card.json").write_text(json.dumps({"generator": "depthnerf-synth-1/cars"}))  # legacy framing
    assert quiet("train", "--depth", "none", "--data", root, "--out", tmp_path / "run", "--max-steps", "1",
                 "--log.val_every", "0", "--data.resolution", "32", "--data.num_workers", "0",
                 "--model.coarse.d_hidden", "16", "--model.fine.d_hidden", "16", "--model.encoder.backbone",
                 "resnet18", "--schedule.objects_phase1", "1", "--schedule.rays_per_object", "16",
                 "--render.sampler.n_coarse", "4", "--render.sampler.n_importance", "2", "--render.sampler.n_gaussian",
                 "2", "--no-progress", "--device", "cpu") == 0
    pre = load_pretrained(tmp_path / "run")
    assert pre.spec.framing == "legacy" and pre.framing_origin == SPEC_FRAMING
    older = save_tiny(tmp_path / "older.safetensors", tiny_config("cars", "none"))  # no spec: derived at load
    (tmp_path / "older.json").write_text(json.dumps({"framing": "legacy"}))
    pre = load_pretrained(older)
    assert pre.spec.framing == "legacy" and pre.framing_origin == str(tmp_path / "older.json")


def test_a_reconstruction_records_the_pixel_centre_and_encoder_norm_it_ran_with(tiny):
    """``pixel_center`` and ``encoder_norm`` change what a reconstruction renders (the input camera, the encoder's
    statistics), so the manifest's settings state them, overridden or not, as eval's summary does."""
    cfg = ReconstructConfig(views=1, mesh_resolution=0, background_removal="off")
    plain = Reconstructor.from_pretrained(tiny["ckpt"]).reconstruct(examples()[0], config=cfg)
    assert plain.settings["pixel_center"] == 0.0 and plain.settings["encoder_norm"] == "running"
    rec = Reconstructor.from_pretrained(tiny["ckpt"], pixel_center=0.5, encoder_norm="image")
    out = rec.reconstruct(examples()[0], config=cfg)
    assert out.settings["pixel_center"] == 0.5 and out.settings["encoder_norm"] == "image"
    manifest = rec.save(out, tiny["tmp"] / "recorded")
    assert (manifest["settings"]["pixel_center"], manifest["settings"]["encoder_norm"]) == (0.5, "image")
