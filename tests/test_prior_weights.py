"""Which depth weights a model reads: the shipped bundled nets by name, and the weights hash as the judge.

- Every shipped net exists, loads, is small and is recorded by its name; the default is :data:`DEFAULT_NET`.
- :func:`portable_prior` renames weights to the shipped net with their hash, whatever path or default recorded them.
- Every shipped depth-aware checkpoint reads, by default, exactly the weights it was trained with.
- A session whose prior serves other weights than the checkpoint recorded refuses (one line); an explicit
  ``--depth-checkpoint`` to other weights warns instead, printed by the CLI as one ``warning:`` line.
- A resumed run whose prior now serves other weights than its ``prior.json`` recorded refuses.
"""

from __future__ import annotations

import contextlib
import io
import json
import shutil
import warnings
from pathlib import Path

import pytest
from fixtures_checkpoints import TINY_TRAIN_FLAGS, tiny_bundled, tiny_config, tiny_model
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.config_io import to_dict
from depthnerf.depth.bundled import DEFAULT_NET, SHIPPED_NETS, bundled_provenance, load_bundled_net
from depthnerf.depth.prior import PriorConfig, portable_prior
from depthnerf.errors import DepthnerfError, UsageWarning
from depthnerf.files import sha256_files
from depthnerf.infer.session import InferenceSession, SessionOptions
from depthnerf.pretrained.load import load_pretrained, shipped_checkpoints
from depthnerf.pretrained.spec import SPEC_KEY
from depthnerf.pretrained.weights import save_weights
from depthnerf.train.config import inference_spec


def quiet(*args) -> int:
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(io.StringIO()):
        return main([str(a) for a in args])


def file_hash(path: Path) -> str:
    return sha256_files([path], names=False)


def test_shipped_nets_load_by_name_and_differ():
    assert DEFAULT_NET in SHIPPED_NETS and len(SHIPPED_NETS) >= 2
    hashes = set()
    for name, path in SHIPPED_NETS.items():
        assert path.is_file() and path.stat().st_size <= 10 * 2**20, name
        load_bundled_net(name)
        prov = bundled_provenance(name)
        assert prov.checkpoint == name and prov.weights_hash == file_hash(path)
        hashes.add(prov.weights_hash)
    assert len(hashes) == len(SHIPPED_NETS)
    assert bundled_provenance(None).checkpoint == DEFAULT_NET
    assert bundled_provenance(None).weights_hash == file_hash(SHIPPED_NETS[DEFAULT_NET])


def test_portable_prior_names_shipped_weights_by_their_hash(tmp_path):
    legacy = SHIPPED_NETS["legacy"]
    copy = shutil.copy(legacy, tmp_path / "somewhere.safetensors")
    for recorded in (None, str(copy), "srn"):  # a default since changed, a path, another name: the hash decides
        assert portable_prior(PriorConfig("bundled", recorded), file_hash(legacy)) == PriorConfig("bundled", "legacy")
    own = tiny_bundled(tmp_path / "own.safetensors")
    mine = PriorConfig("bundled", str(own))
    assert portable_prior(mine, file_hash(own)) == mine  # not shipped: kept as given
    assert portable_prior(mine, None) == mine
    assert portable_prior(PriorConfig("none"), file_hash(legacy)) == PriorConfig("none")
    assert portable_prior(PriorConfig("depth-anything-v2"), "ab" * 32) == PriorConfig("depth-anything-v2")


def test_every_shipped_depth_checkpoint_reads_the_weights_it_was_trained_on():
    checked = 0
    for name in shipped_checkpoints():
        spec = load_pretrained(name).spec
        if not spec.depth_aware:
            continue
        assert spec.prior.estimator == "bundled" and spec.prior.checkpoint in SHIPPED_NETS, name
        assert bundled_provenance(spec.prior.checkpoint).weights_hash == spec.prior_weights_hash, name
        checked += 1
    assert checked > 0


def spec_checkpoint(path: Path, weights: Path, recorded_hash: str) -> Path:
    """A tiny depth-aware checkpoint whose spec names ``weights`` and records ``recorded_hash``."""
    cfg = tiny_config("cars", "bundled", weights)
    spec = inference_spec(cfg, recorded_hash, "srn")
    save_weights(path, tiny_model(cfg), to_dict(cfg.model), step=1, extra={SPEC_KEY: spec.to_json()})
    return path


def test_session_checks_the_weights_against_the_recorded_hash(tmp_path):
    a = tiny_bundled(tmp_path / "a.safetensors", input_size=16)
    b = tiny_bundled(tmp_path / "b.safetensors", input_size=32)
    assert file_hash(a) != file_hash(b)
    good = spec_checkpoint(tmp_path / "good.safetensors", a, file_hash(a))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        InferenceSession(good, SessionOptions(inputs="photos"))
        InferenceSession(good, SessionOptions(inputs="photos", depth_checkpoint=str(a)))  # the same weights
    stale = spec_checkpoint(tmp_path / "stale.safetensors", b, file_hash(a))  # names b, was trained on a
    with pytest.raises(DepthnerfError, match=r"stale.safetensors: trained on 'bundled' weights sha256 "
                                             rf"{file_hash(a)[:12]}\.\.\., but .*b.safetensors has sha256 "
                                             rf"{file_hash(b)[:12]}.*pass --depth-checkpoint"):
        InferenceSession(stale, SessionOptions(inputs="photos"))
    with pytest.warns(UsageWarning, match="other priors than it was trained on"):
        InferenceSession(good, SessionOptions(inputs="photos", depth_checkpoint=str(b)))
    InferenceSession(good, SessionOptions(inputs="photos", depth="bundled", depth_checkpoint=str(a)))


def test_resume_refuses_a_prior_that_changed_under_the_run(tmp_path):
    root = make_srn_fixture(tmp_path / "data", "cars", {"train": 2}, views=4, size=32, with_mask=True)
    weights = tiny_bundled(tmp_path / "w.safetensors", input_size=32)
    depth = ("depth", "--data", root, "--depth", "bundled", "--depth-checkpoint", weights, "--splits", "train",
             "--no-progress")
    assert quiet(*depth) == 0
    run = tmp_path / "run"
    train = ("train", "--preset", "cpu-cars", "--data", root, "--out", run, "--depth", "bundled",
             "--depth-checkpoint", weights, "--log.val_every", "0", "--checkpoint-every", "1", *TINY_TRAIN_FLAGS)
    assert quiet(*train, "--max-steps", "1") == 0
    assert json.loads((run / "prior.json").read_text())["weights_hash"] == file_hash(weights)
    tiny_bundled(weights, input_size=64)  # the file changes under the run
    assert quiet(*depth) == 0  # and its priors are cached: only the hash check stands in the way
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        assert main([str(a) for a in (*train, "--max-steps", "2", "--resume")]) == 2
    line = err.getvalue().strip().splitlines()[-1]
    assert "prior.json: trained on 'bundled' weights sha256" in line and "restore the weights" in line
    assert (run / "checkpoints" / "latest").read_text().strip().endswith("1")  # the run is untouched


def test_depth_for_a_checkpoint_caches_what_it_reads(tmp_path):
    """``depthnerf depth --for CKPT`` caches the checkpoint's own weights at its resolution: a session on the
    dataset then opens, where the default weights' cache alone would not do."""
    root = make_srn_fixture(tmp_path / "data", "cars", {"test": 1}, views=4, size=16, with_mask=True)
    a = tiny_bundled(tmp_path / "a.safetensors", input_size=16)
    ckpt = spec_checkpoint(tmp_path / "m.safetensors", a, file_hash(a))
    options = SessionOptions(inputs="dataset", data_root=str(root))
    with pytest.raises(DepthnerfError, match=r"no 'bundled' depth priors for weights .*--depth-checkpoint"):
        InferenceSession(ckpt, options)
    assert quiet("depth", "--data", root, "--for", ckpt, "--no-progress") == 0
    assert [p.name for p in (root / "depth_priors").iterdir()] == [f"bundled-{file_hash(a)[:12]}-16"]
    InferenceSession(ckpt, options)
    assert quiet("depth", "--data", root, "--for", ckpt, "--depth-checkpoint", a, "--no-progress") == 2
    assert quiet("depth", "--data", root, "--for", ckpt, "--resolution", "0", "--no-progress") == 2  # not its 16


def test_cli_prints_the_override_warning_as_one_line(tmp_path):
    a = tiny_bundled(tmp_path / "a.safetensors", input_size=16)
    b = tiny_bundled(tmp_path / "b.safetensors", input_size=32)
    ckpt = spec_checkpoint(tmp_path / "m.safetensors", a, file_hash(a))
    photo = Path(__file__).resolve().parents[1] / "depthnerf" / "app" / "examples" / "car_rgba.png"
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        assert main(["reconstruct", str(photo), "--checkpoint", str(ckpt), "--depth-checkpoint", str(b), "--views",
                     "1", "--mesh-resolution", "0", "--out", str(tmp_path / "out"), "--no-progress"]) == 0
    lines = [line for line in err.getvalue().splitlines() if "other priors" in line]
    assert len(lines) == 1 and lines[0].startswith(f"warning: {ckpt}: trained on 'bundled' weights sha256 "
                                                   f"{file_hash(a)[:12]}")
    assert f"{file_hash(b)[:12]}" in lines[0]
