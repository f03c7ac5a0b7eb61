"""The wrong weights, pointed at on purpose: every one is refused in one line naming the file, nothing is unpickled.

- ``--depth depth-anything-v2 --depth-checkpoint DIR``: a folder without or with a damaged ``config.json``, another
  model type (a tiny BERT, a metric Depth Anything), a truncated ``model.safetensors``, another network's weights
  under a Depth Anything config (which ``transformers`` would initialise at random), a ``pytorch_model.bin`` (never
  unpickled), and a hub id whose cached copy is another model (a hand-built Hugging Face cache, offline).
- ``--depth bundled --depth-checkpoint``: a misspelled shipped name, a folder, a model checkpoint, impossible sizes
  in the config, non-finite weights.
- ``--checkpoint``: a misspelled shipped name (the closest one suggested), a bad ``step``, framing or prior in the
  metadata, ``hf://`` paths with ``.`` / ``..`` segments, and a run folder without a checkpoint yet.
"""

from __future__ import annotations

import contextlib
import io
import json
import os
import shutil
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import save_tiny, tiny_bundled, tiny_config
from safetensors import safe_open
from safetensors.torch import load_file, save_file

from depthnerf.cli import main
from depthnerf.depth.depth_anything import make_tiny_checkpoint
from depthnerf.depth.estimators import make_estimator
from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.hub import parse_hub_reference
from depthnerf.pretrained.load import load_pretrained
from depthnerf.pretrained.spec import SPEC_KEY
from depthnerf.train.config import inference_spec


@pytest.fixture(scope="module")
def tiny_da(tmp_path_factory) -> Path:
    return make_tiny_checkpoint(tmp_path_factory.mktemp("tiny_da") / "good")


def refused(estimator: str, checkpoint: str | Path, says: str) -> str:
    """The one-line error loading ``checkpoint`` gives; it must contain ``says``."""
    with pytest.raises(DepthnerfError) as err:
        make_estimator(estimator, str(checkpoint))
    message = str(err.value)
    assert says in message and "\n" not in message, message
    return message


def copy_of(tiny_da: Path, folder: Path) -> Path:
    shutil.copytree(tiny_da, folder)
    return folder


def test_depth_anything_folder_without_or_with_a_damaged_config(tiny_da, tmp_path):
    missing = copy_of(tiny_da, tmp_path / "noconfig")
    (missing / "config.json").unlink()
    refused("depth-anything-v2", missing, f"{missing / 'config.json'}: missing")  # was "Unrecognized model"
    for name, text in (("notjson", b"{oops"), ("binary", b"\x00\xff\xfe"), ("list", b"[1, 2]")):
        folder = copy_of(tiny_da, tmp_path / name)
        (folder / "config.json").write_bytes(text)
        refused("depth-anything-v2", folder, str(folder / "config.json"))


def test_depth_anything_folder_of_another_model_type(tiny_da, tmp_path):
    from transformers import BertConfig, BertModel, DepthAnythingConfig

    bert = tmp_path / "bert"
    BertModel(BertConfig(vocab_size=32, hidden_size=8, num_hidden_layers=1, num_attention_heads=2,
                         intermediate_size=8)).save_pretrained(bert)
    shutil.copy(tiny_da / "preprocessor_config.json", bert)
    refused("depth-anything-v2", bert, "is a 'bert' model, not Depth Anything")
    metric = copy_of(tiny_da, tmp_path / "metric")  # outputs depth in metres: the prior would be inverted
    config = DepthAnythingConfig.from_pretrained(metric)
    config.depth_estimation_type = "metric"
    config.save_pretrained(metric)
    refused("depth-anything-v2", metric, "a metric Depth Anything model")


def test_depth_anything_damaged_or_foreign_weights(tiny_da, tmp_path):
    truncated = copy_of(tiny_da, tmp_path / "truncated")
    data = (truncated / "model.safetensors").read_bytes()
    (truncated / "model.safetensors").write_bytes(data[:len(data) // 2])
    refused("depth-anything-v2", truncated, "not a loadable Depth Anything checkpoint")  # was a SafetensorError
    foreign = copy_of(tiny_da, tmp_path / "foreign")  # loaded "fine" before, every weight at random
    save_file({"vit.embeddings.cls_token": torch.zeros(1, 1, 16)}, foreign / "model.safetensors",
              metadata={"format": "pt"})
    refused("depth-anything-v2", foreign, "the weights do not fit the Depth Anything model")
    resized = copy_of(tiny_da, tmp_path / "resized")  # was a RuntimeError about ignore_mismatched_sizes
    config = json.loads((resized / "config.json").read_text())
    (resized / "config.json").write_text(json.dumps({**config, "fusion_hidden_size": 12}))
    refused("depth-anything-v2", resized, "of another shape")


class _Trap:
    """Unpickling this would create ``path``."""

    def __init__(self, path: Path) -> None:
        self.path = str(path)

    def __reduce__(self):
        return os.makedirs, (self.path,)


def test_depth_anything_never_unpickles_a_pytorch_model_bin(tiny_da, tmp_path):
    folder = copy_of(tiny_da, tmp_path / "bin")
    state = load_file(folder / "model.safetensors")
    (folder / "model.safetensors").rename(folder / "unrelated.safetensors")  # hashed, but not the model's file
    torch.save({"trap": _Trap(tmp_path / "unpickled"), **state}, folder / "pytorch_model.bin")
    refused("depth-anything-v2", folder, "model.safetensors")  # was an UnpicklingError traceback
    (folder / "unrelated.safetensors").unlink()
    refused("depth-anything-v2", folder, "pytorch_model.bin is never read")
    assert not (tmp_path / "unpickled").exists()


def test_depth_anything_hub_id_whose_cached_copy_is_another_model(tmp_path, monkeypatch):
    from huggingface_hub import constants
    from transformers import BertConfig, BertModel

    monkeypatch.setattr(constants, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(constants, "HF_HUB_CACHE", str(tmp_path / "hf-cache"))
    source = tmp_path / "bert"
    BertModel(BertConfig(vocab_size=32, hidden_size=8, num_hidden_layers=1, num_attention_heads=2,
                         intermediate_size=8)).save_pretrained(source)
    commit = "0123456789abcdef0123456789abcdef01234567"
    repo = tmp_path / "hf-cache" / "models--alice--not-depth"
    (repo / "refs").mkdir(parents=True)
    (repo / "refs" / "main").write_text(commit)
    shutil.copytree(source, repo / "snapshots" / commit)
    refused("depth-anything-v2", "alice/not-depth", "alice/not-depth: config.json is a 'bert' model")


def test_bundled_wrong_names_folders_and_files(tmp_path):
    refused("bundled", "srn18k", "srn18k: not found: neither a shipped bundled net (srn (the default), srn-18k, legacy)")
    refused("bundled", tmp_path, "a directory")  # was "bundled depth weights not found"
    model = save_tiny(tmp_path / "model.safetensors", tiny_config("cars", "none"))
    refused("bundled", model, "a depthnerf model checkpoint goes to --checkpoint")
    weights = tiny_bundled(tmp_path / "w.safetensors")
    tensors = load_file(weights)
    with safe_open(str(weights), framework="pt") as handle:
        meta = handle.metadata()
    config = json.loads(meta["config"])
    save_file(tensors, tmp_path / "nolevels.safetensors", metadata={**meta, "config": json.dumps({**config,
                                                                                           "widths": []})})
    refused("bundled", tmp_path / "nolevels.safetensors", "valid 'config'")  # was an IndexError
    save_file({k: v * float("nan") if v.is_floating_point() else v for k, v in tensors.items()},
              tmp_path / "nan.safetensors", metadata=meta)
    refused("bundled", tmp_path / "nan.safetensors", "non-finite")  # was accepted: NaN priors


def _with_meta(source: Path, target: Path, **changes: str) -> Path:
    with safe_open(str(source), framework="pt") as handle:
        meta = handle.metadata()
    save_file(load_file(source), target, metadata={**meta, **changes})
    return target


def test_checkpoint_metadata_a_user_did_not_write(tmp_path):
    cfg = tiny_config("cars", "none")
    spec = json.loads(inference_spec(cfg, framing="srn").to_json())
    good = save_tiny(tmp_path / "good.safetensors", cfg)
    good = _with_meta(good, tmp_path / "spec.safetensors", **{SPEC_KEY: json.dumps(spec)})
    assert load_pretrained(good).spec.framing == "srn"
    cases = {"step": ({"step": "abc"}, "metadata 'step' is 'abc'"),  # was a ValueError traceback
             "framing": ({SPEC_KEY: json.dumps({**spec, "framing": "weird"})}, "framing 'weird'"),
             "prior": ({SPEC_KEY: json.dumps({**spec, "prior": {"estimator": "midas"}})},
                       "inference spec: unknown depth prior 'midas': choose "),
             # numbers training never writes: each was a traceback in rendering, or (pixel_center) silently used
             "z-range": ({SPEC_KEY: json.dumps({**spec, "z_near": 5.0, "z_far": 1.0})},
                         "inference spec: z_near / z_far must satisfy 0 <= z_near < z_far (finite), got 5.0, 1.0"),
             "nan-near": ({SPEC_KEY: json.dumps({**spec, "z_near": float("nan")})}, "got nan, "),
             "resolution": ({SPEC_KEY: json.dumps({**spec, "resolution": -3})},
                            "inference spec: resolution must be >= 8, got -3"),
             "samples": ({SPEC_KEY: json.dumps({**spec, "render": {**spec["render"], "sampler": {
                 **spec["render"]["sampler"], "n_coarse": 0}}})}, "render.sampler.n_coarse must be >= 1, got 0"),
             "pixel-centre": ({SPEC_KEY: json.dumps({**spec, "pixel_center": 5.0})},
                              "pixel_center must be in [0, 1), got 5.0"),
             # a field every spec holds, gone: a TypeError traceback, or (model) a default config's network built
             "no-render": ({SPEC_KEY: json.dumps({k: v for k, v in spec.items() if k != "render"})},
                           "inference spec lacks render"),
             "no-model": ({SPEC_KEY: json.dumps({k: v for k, v in spec.items() if k != "model"})},
                          "inference spec lacks model")}
    for name, (changes, says) in cases.items():
        path = _with_meta(good, tmp_path / f"{name}.safetensors", **changes)
        with pytest.raises(DepthnerfError) as err:
            load_pretrained(path)
        assert str(err.value).startswith(f"{path}: ") and says in str(err.value), str(err.value)


def test_weights_of_the_wrong_kind_of_dtype_are_refused(tmp_path):
    """Float weights stored as integers were cast and truncated silently (a model scoring nonsense)."""
    good = save_tiny(tmp_path / "good.safetensors", tiny_config("cars", "none"))
    with safe_open(str(good), "pt") as handle:
        meta = handle.metadata()
    tensors = load_file(good)
    name = next(k for k, v in tensors.items() if v.is_floating_point())
    save_file({**tensors, name: tensors[name].long()}, tmp_path / "ints.safetensors", metadata=meta)
    with pytest.raises(DepthnerfError) as err:
        load_pretrained(tmp_path / "ints.safetensors")
    assert str(err.value) == (f"{tmp_path / 'ints.safetensors'}: checkpoint does not match the model config: dtype "
                              f"mismatch for {name}: file torch.int64 vs model torch.float32")
    save_file({k: v.half() if v.is_floating_point() else v for k, v in tensors.items()}, tmp_path / "fp16.safetensors",
              metadata=meta)
    assert load_pretrained(tmp_path / "fp16.safetensors").step == 7  # another precision is cast, as shipped fp16 is


def test_misspelled_checkpoint_names_suggest_the_closest(tmp_path):
    with pytest.raises(DepthnerfError, match="did you mean cpu-cars-depth\\?"):
        load_pretrained("cpu-cars-dept")
    for reference in ("hf://alice/dn/../x.safetensors", "hf://alice/dn/./model.safetensors", "hf://../dn"):
        with pytest.raises(DepthnerfError, match="'.' and '..' are not allowed"):  # was "download failed"
            parse_hub_reference(reference)


def test_a_run_stopped_before_its_first_checkpoint_is_named_as_a_run(tmp_path):
    """A run folder train started (``launches.jsonl``, ``data_card.json``) but that has no ``checkpoints/`` yet was
    called "not a checkpoint file, checkpoint folder, run folder, ..." by ``eval --run`` and ``reconstruct``."""
    run = tmp_path / "run"
    run.mkdir()
    (run / "launches.jsonl").write_text("{}\n")
    with pytest.raises(DepthnerfError, match=f"^{run}: run folder has no checkpoint yet"):
        load_pretrained(run)
    (run / "checkpoints").mkdir()
    with pytest.raises(DepthnerfError, match=f"^{run}: run folder has no complete checkpoint yet"):
        load_pretrained(run)
    with pytest.raises(DepthnerfError, match="not a checkpoint file, checkpoint folder, run folder"):
        load_pretrained(tmp_path)  # no run's files: the general line


def test_cli_refuses_a_truncated_depth_anything_in_one_line(tiny_da, tmp_path, srn_root):
    truncated = copy_of(tiny_da, tmp_path / "truncated")
    data = (truncated / "model.safetensors").read_bytes()
    (truncated / "model.safetensors").write_bytes(data[:100])
    err = io.StringIO()
    with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
        code = main(["depth", "--data", str(srn_root), "--depth", "depth-anything-v2", "--depth-checkpoint",
                     str(truncated), "--no-progress"])
    lines = [line for line in err.getvalue().splitlines() if line.startswith(("error", "Traceback"))]
    assert code == 2 and len(lines) == 1 and lines[0].startswith(f"error: {truncated}"), err.getvalue()


def test_depth_anything_with_a_few_tensors_missing_loads_with_a_warning(tiny_da, tmp_path):
    """One tensor short (a key another transformers version names differently) is a warning, not a refusal: the
    refusal is for weights that leave more than a tenth of the model at random."""
    from depthnerf.errors import UsageWarning

    folder = copy_of(tiny_da, tmp_path / "short")
    state = load_file(folder / "model.safetensors")
    dropped = sorted(state)[0]
    del state[dropped]
    save_file(state, folder / "model.safetensors", metadata={"format": "pt"})
    with pytest.warns(UsageWarning, match=rf"1 of its \d+ tensors missing, 0 of another shape, e.g. {dropped}"):
        make_estimator("depth-anything-v2", str(folder))
