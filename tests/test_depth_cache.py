"""The prior cache (`depthnerf depth`), PriorStore loading and its errors, and `depthnerf depth-eval`."""

from __future__ import annotations

import json
import re
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS
from fixtures_srn import first_object, make_srn_fixture

from depthnerf.cli import main
from depthnerf.data import srn_format
from depthnerf.data.srn import index_split, load_object
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.depth.cache import PriorStore
from depthnerf.depth.estimators import make_estimator, oracle_disparity
from depthnerf.errors import DepthnerfError


def _weights(path: Path, seed: int) -> str:
    torch.manual_seed(seed)
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=16)), path)
    return str(path)


@pytest.fixture
def data(tmp_path) -> Path:
    return make_srn_fixture(tmp_path / "srn", splits={"train": 2, "test": 1}, views=3, size=16, with_depth=True)


def _depth(data: Path, ckpt: str, *extra: str) -> int:
    return main(["depth", "--data", str(data), "--estimator", "bundled", "--checkpoint", ckpt, "--no-progress",
                 *extra])


def test_precompute_then_load_matches_the_estimator_and_resumes(data, tmp_path, capsys):
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, "--batch-size", "2") == 0
    assert "3 objects computed" in capsys.readouterr().out
    store = PriorStore.open(data, "bundled", ckpt, resolution=16)
    records = index_split(data, "cars", "train").objects + index_split(data, "cars", "test").objects
    store.check(records)
    est = make_estimator("bundled", ckpt)
    for record in records:
        expect = est.predict(load_object(record, pixel_center=0.0).images)
        got = store.load(record, [2, 0])
        assert got.shape == (2, 16, 16) and got.dtype == torch.float32
        assert torch.allclose(got, expect[[2, 0]], rtol=2e-3, atol=1e-3)  # float16 storage
        assert torch.allclose(store.load(record, [0, 1, 2]), expect, rtol=2e-3, atol=1e-3)
    manifest = json.loads((store.root / "manifest.json").read_text())
    assert manifest["provenance"]["weights_hash"] == est.provenance.weights_hash
    assert manifest["splits"]["cars_train"] == {"objects": 2, "complete": True}
    assert store.provenance["weights_hash"] == est.provenance.weights_hash and store.provenance["resolution"] == 16
    # resumable: nothing to do the second time; a deleted object is recomputed alone
    assert _depth(data, ckpt) == 0
    assert "0 objects computed" in capsys.readouterr().out
    next((store.root / "cars_train").glob("*.safetensors")).unlink()
    assert _depth(data, ckpt, "--splits", "train") == 0
    assert "1 objects computed (0 were stale), 1 already up to date" in capsys.readouterr().out
    with pytest.raises(DepthnerfError, match="view index 3 out of range"):
        store.load(records[0], [3])


def test_missing_partial_stale_and_other_weights_name_the_command(data, tmp_path, capsys):
    ckpt_a, ckpt_b = _weights(tmp_path / "a.safetensors", 0), _weights(tmp_path / "b.safetensors", 1)
    with pytest.raises(DepthnerfError) as err:  # nothing cached yet
        PriorStore.open(data, "bundled", ckpt_a, resolution=16)
    assert f"run: depthnerf depth --data {data} --depth bundled --depth-checkpoint {ckpt_a}" in str(err.value)
    assert "\n" not in str(err.value)
    assert _depth(data, ckpt_a, "--splits", "train") == 0
    with pytest.raises(DepthnerfError, match=r"found only: bundled-[0-9a-f]{12}-16.*run: depthnerf depth"):
        PriorStore.open(data, "bundled", ckpt_b, resolution=16)  # other weights
    with pytest.raises(DepthnerfError, match="--resolution 8"):
        PriorStore.open(data, "bundled", ckpt_a, resolution=8)  # other resolution
    store = PriorStore.open(data, "bundled", ckpt_a, resolution=16)
    test_record = index_split(data, "cars", "test").objects[0]
    with pytest.raises(DepthnerfError, match="missing.*--category cars --splits test --resolution 16"):
        store.load(test_record, [0])  # partial: test split never computed
    # stale: regenerate one image of a train object -> fingerprint changes
    record = index_split(data, "cars", "train").objects[0]
    fresh = PriorStore.open(data, "bundled", ckpt_a, resolution=16)
    img = np.zeros((16, 16, 3), dtype=np.uint8)
    img[4:12, 4:12] = 90
    srn_format.write_rgb(record.rgb_path(1), img)
    with pytest.raises(DepthnerfError, match="stale.*run: depthnerf depth .*--splits train") as err:
        fresh.load(record, [0])
    assert str(record.object_id) in str(err.value)
    # the CLI reports it as one line and exit status 2
    assert main(["depth-eval", "--data", str(data), "--estimator", "bundled", "--checkpoint",
                 str(tmp_path / "nope.safetensors"), "--no-progress"]) == 2
    assert capsys.readouterr().err.count("\n") == 1
    # rerunning the command fixes the stale object (and only it)
    assert _depth(data, ckpt_a, "--splits", "train") == 0
    assert "1 objects computed (1 were stale)" in capsys.readouterr().out
    PriorStore.open(data, "bundled", ckpt_a, resolution=16).load(record, [0])


def test_oracle_and_none_stores(data):
    assert PriorStore.open(data, "none") is None
    store = PriorStore.open(data, "oracle", resolution=16)
    record = index_split(data, "cars", "train").objects[1]
    depth = load_object(record, [1, 2], with_depth=True, pixel_center=0.0).depths
    got = store.load(record, [1, 2])
    mask = depth > 0
    assert mask.any() and torch.allclose(got[mask], 1 / depth[mask]) and (got[~mask] == 0).all()
    assert torch.equal(got, oracle_disparity(depth))
    assert store.load(record, [0]).shape == (1, 16, 16)
    assert PriorStore.open(data, "oracle", resolution=8).load(record, [0]).shape == (1, 8, 8)
    assert store.provenance["estimator"] == "oracle"
    no_depth = make_srn_fixture(data.parent / "nodepth", splits={"train": 1})
    bare = index_split(no_depth, "cars", "train").objects[0]
    with pytest.raises(DepthnerfError, match="needs ground-truth depth"):
        store.load(bare, [0])


def test_depth_eval_oracle_is_perfect_and_cache_matches_direct(data, tmp_path, capsys):
    out = tmp_path / "oracle.json"
    assert main(["depth-eval", "--data", str(data), "--estimator", "oracle", "--json", str(out),
                 "--no-progress", "--split", "train"]) == 0
    scores = json.loads(out.read_text())
    assert scores["abs_rel"] == pytest.approx(0.0, abs=1e-6) and scores["delta1"] == 1.0 and scores["images"] == 6
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    direct, cached = tmp_path / "direct.json", tmp_path / "cached.json"
    args = ["depth-eval", "--data", str(data), "--estimator", "bundled", "--checkpoint", ckpt, "--no-progress",
            "--max-views", "2"]
    assert main([*args, "--json", str(direct)]) == 0
    assert _depth(data, ckpt, "--splits", "test") == 0
    assert main([*args, "--json", str(cached)]) == 0
    a, b = json.loads(direct.read_text()), json.loads(cached.read_text())
    assert (a["source"], b["source"]) == ("estimator", "cache") and a["images"] == b["images"] == 2
    assert a["abs_rel"] == pytest.approx(b["abs_rel"], rel=2e-2, abs=1e-4)
    assert 0 < a["abs_rel"] < 1 and 0 <= a["delta1"] <= 1
    capsys.readouterr()
    assert main(["depth", "--data", str(data), "--estimator", "oracle"]) == 0
    assert "needs no cache" in capsys.readouterr().out


def test_depth_eval_flat_reference_matches_a_brute_force_loop(data, tmp_path, capsys):
    """The flat reference is a constant disparity aligned to the mean foreground disparity of each image."""
    out = tmp_path / "oracle.json"
    assert main(["depth-eval", "--data", str(data), "--estimator", "oracle", "--json", str(out),
                 "--no-progress", "--split", "train"]) == 0
    assert "flat " in capsys.readouterr().out
    flat = json.loads(out.read_text())["flat_reference"]
    rel, hits = [], []
    for record in index_split(data, "cars", "train").objects:
        depths = load_object(record, list(range(record.num_views)), with_depth=True, pixel_center=0.0).depths.double().numpy()
        for z in depths:
            fg = z[z > 0]
            z_flat = 1.0 / np.mean(1.0 / fg)
            rel.append(np.mean(np.abs(z_flat - fg) / fg))
            hits.append(np.mean(np.maximum(z_flat / fg, fg / z_flat) < 1.25))
    assert len(rel) == 6 and np.mean(rel) > 1e-3
    assert flat["abs_rel"] == pytest.approx(np.mean(rel), rel=1e-5)
    assert flat["delta1"] == pytest.approx(np.mean(hits), rel=1e-5)
    assert flat["per_category"]["cars"]["abs_rel"] == pytest.approx(flat["abs_rel"])


def test_bad_inputs_are_one_line_errors(data, tmp_path, capsys):
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, "--splits", "val") == 2  # explicitly requested split does not exist
    err = capsys.readouterr().err
    assert err.startswith("error: ") and "cars_val" in err and err.count("\n") == 1
    broken = first_object(data, "cars", "test") / "rgb" / "000001.png"
    broken.write_bytes(b"garbage")
    assert _depth(data, ckpt, "--splits", "test") == 2
    assert str(broken) in capsys.readouterr().err


@pytest.mark.parametrize("flags, line", [
    (["--resolution", "7"], "--resolution must be >= 8, got 7"),  # was: cached at 7 px, which nothing reads
    (["--category", "planes"], "{data}: --category planes: no planes_<split> folder (train, val, test) exists here "
                               "(categories here: cars)"),  # was: 'none of the requested splits exist'
])
def test_depth_refuses_flags_that_cannot_work_in_one_line(data, tmp_path, capsys, flags, line):
    """Before an estimator loads or a prior is written, in the words train and eval use."""
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, *flags) == 2
    assert capsys.readouterr().err == f"error: {line.format(data=data)}\n"
    assert not (data / "depth_priors").exists()


@pytest.mark.parametrize("flags, line", [
    (["--max-objects", "0"], "--max-objects must be positive, got 0"),  # was: every object, exit 0
    (["--max-objects", "-1"], "--max-objects must be positive, got -1"),  # was: an IndexError traceback
    (["--batch-size", "0"], "--batch-size must be positive, got 0"),  # was: a ValueError traceback
    (["--json", "{data}"], "{data}: --json names a folder; give the path of the JSON file to write"),
])
def test_depth_eval_refuses_flags_that_cannot_work_in_one_line(data, capsys, flags, line):
    """Before any file is read (a folder as --json was an IsADirectoryError once every image had been scored)."""
    flags = [f.format(data=data) for f in flags]
    assert main(["depth-eval", "--data", str(data), "--depth", "oracle", "--no-progress", *flags]) == 2
    assert capsys.readouterr().err == f"error: {line.format(data=data)}\n"


def test_depth_eval_refuses_a_json_path_under_a_file_before_scoring(data, tmp_path, capsys):
    """It was found only when the scores were written, after every image had been scored."""
    (tmp_path / "notes").write_text("")
    out = tmp_path / "notes" / "scores.json"
    assert main(["depth-eval", "--data", str(data), "--depth", "oracle", "--no-progress", "--json", str(out)]) == 2
    captured = capsys.readouterr()
    assert captured.err == f"error: {out}: --json lies under {tmp_path / 'notes'}, which is a file, not a folder\n"
    assert captured.out == ""


@pytest.mark.parametrize("estimator", ["oracle", "none"])
def test_an_estimator_without_a_cache_still_checks_the_data_folder(tmp_path, capsys, estimator):
    """``depthnerf depth --data /typo --depth oracle`` said "needs no cache" and exited 0."""
    missing = tmp_path / "typo"
    assert main(["depth", "--data", str(missing), "--depth", estimator, "--no-progress"]) == 2
    assert capsys.readouterr().err == f"error: {missing}: dataset folder does not exist\n"


def test_depth_anything_cache_from_a_local_checkpoint(data, tmp_path, capsys):
    from depthnerf.depth.depth_anything import make_tiny_checkpoint

    ckpt = str(make_tiny_checkpoint(tmp_path / "tiny_da"))
    assert main(["depth", "--data", str(data), "--estimator", "depth-anything-v2", "--checkpoint", ckpt,
                 "--splits", "test", "--no-progress"]) == 0
    store = PriorStore.open(data, "depth-anything-v2", ckpt, resolution=16)
    assert store.root.name.startswith("depth-anything-v2-") and store.root.name.endswith("-16")
    record = index_split(data, "cars", "test").objects[0]
    expect = make_estimator("depth-anything-v2", ckpt).predict(load_object(record, pixel_center=0.0).images)
    assert torch.allclose(store.load(record, [0, 1, 2]), expect, rtol=2e-3, atol=1e-3)
    with pytest.raises(DepthnerfError, match="--depth depth-anything-v2 --depth-checkpoint .*--splits train"):
        store.load(index_split(data, "cars", "train").objects[0], [0])


def _damage(path: Path, kind: str) -> None:
    """Damage a cache file written by ``depthnerf depth`` (its metadata kept, so only the damage is wrong)."""
    from safetensors.torch import load_file, safe_open, save_file

    with safe_open(str(path), framework="pt") as handle:
        meta = handle.metadata()
    disparity = load_file(str(path))["disparity"]
    if kind in ("text", "truncated"):
        path.write_bytes(b"not a tensor file" if kind == "text" else path.read_bytes()[:100])
        return
    tensors = {"shape": {"disparity": torch.ones(3, 9, 9, dtype=disparity.dtype)},
               "renamed": {"disp": disparity},
               "views": {"disparity": disparity[:2].contiguous()},
               "float64": {"disparity": disparity.double()},
               "nan": {"disparity": torch.full_like(disparity, float("nan"))},
               "inf": {"disparity": disparity.index_put((torch.tensor(2), torch.tensor(3), torch.tensor(4)),
                                                        torch.tensor(float("inf"), dtype=disparity.dtype))}}[kind]
    save_file(tensors, str(path), metadata=meta)


@pytest.mark.parametrize("kind, problem, at", [
    ("shape", r"depth prior is 3x9x9, the object's 3 views at 16 px are 3x16x16", "check"),  # was a ValueError
    ("renamed", r"unreadable depth prior \(no 'disparity' tensor; tensors: disp\)", "check"),  # was in a worker
    ("views", r"depth prior holds 2 views, the object has 3", "check"),  # was in a worker
    ("float64", r"unreadable depth prior \(disparity is F64, not F16 or F32\)", "check"),
    ("text", r"unreadable depth prior \(.*header.*\)", "check"),  # was "depth prior missing"
    ("truncated", r"unreadable depth prior \(.*\)", "check"),  # was "depth prior missing"
    ("nan", r"depth prior holds non-finite values \(view 1\)", "load"),  # trained silently
    ("inf", r"depth prior holds non-finite values \(view 2\)", "load"),
])
def test_a_damaged_cache_file_is_one_line_and_depth_recomputes_it(data, tmp_path, capsys, kind, problem, at):
    """Reading names the file, the damage and the command; that command recomputes the file (it said "already up
    to date" and the advice looped). The header is checked up front, the values when they are read."""
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, "--splits", "train") == 0
    record = index_split(data, "cars", "train").objects[0]
    store = PriorStore.open(data, "bundled", ckpt, resolution=16)
    path = store.root / "cars_train" / f"{record.object_id}.safetensors"
    before = store.load(record, [0, 1, 2])
    _damage(path, kind)
    fresh = PriorStore.open(data, "bundled", ckpt, resolution=16)
    line = (re.escape(f"{path}: ") + problem + re.escape(f"; run: depthnerf depth --data {data} --depth bundled "
                                                        f"--depth-checkpoint {ckpt} --category cars --splits train "
                                                        "--resolution 16"))
    if at == "load":
        fresh.check([record])  # a sound header: values are checked where they are read
    with pytest.raises(DepthnerfError) as err:
        fresh.check([record]) if at == "check" else fresh.load(record, [1, 2] if kind == "nan" else [2, 0])
    assert re.fullmatch(line, str(err.value)) and "\n" not in str(err.value)
    if kind == "inf":  # the views without damage still read
        assert torch.equal(fresh.load(record, [0, 1]), before[:2])
    capsys.readouterr()
    assert _depth(data, ckpt, "--splits", "train") == 0
    out = capsys.readouterr().out
    assert f"note: {path}: " in out and "1 objects computed (0 were stale, 1 were unreadable or damaged), 1 already " \
        "up to date" in out
    assert torch.equal(PriorStore.open(data, "bundled", ckpt, resolution=16).load(record, [0, 1, 2]), before)
    assert _depth(data, ckpt, "--splits", "train") == 0
    assert "0 objects computed (0 were stale), 2 already up to date" in capsys.readouterr().out


def test_an_error_in_a_loader_worker_is_its_one_line(data, tmp_path, capsys):
    """torch re-raises a worker's DepthnerfError with the worker's traceback as its text (25 lines reached the
    user); the main process gets the line the worker raised, through a real DataLoader with a worker."""
    from torch.utils.data import DataLoader

    from depthnerf.depth.prior import PriorConfig, open_prior
    from depthnerf.train.batching import ItemKey, collate_packed
    from depthnerf.train.items import TrainItems

    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, "--splits", "train") == 0
    records = index_split(data, "cars", "train").objects
    source = open_prior(PriorConfig("bundled", ckpt), data_root=data, resolution=16, records=records)
    _damage(source.store.root / "cars_train" / f"{records[0].object_id}.safetensors", "nan")
    items = TrainItems(records, source, resolution=16, target_views=1, rays_per_object=4, target_priors=False)
    key = ItemKey(0, 0, False)
    with pytest.raises(DepthnerfError) as direct:  # in this process
        items[key]
    loader = DataLoader(items, batch_sampler=[[key]], collate_fn=collate_packed, num_workers=1)
    with pytest.raises(DepthnerfError) as err:
        next(iter(loader))
    assert str(err.value) == str(direct.value) and "non-finite" in str(err.value) and "\n" not in str(err.value)
    assert str(DepthnerfError("a\nb")) == "a\nb"  # any other text is kept as given


def test_train_with_a_worker_prints_a_damaged_prior_as_one_line(data, tmp_path, capsys):
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt, "--splits", "train") == 0
    record = index_split(data, "cars", "train").objects[0]
    path = PriorStore.open(data, "bundled", ckpt, resolution=16).root / "cars_train" / f"{record.object_id}.safetensors"
    _damage(path, "nan")
    capsys.readouterr()
    assert main(["train", "--preset", "cpu-cars", "--data", str(data), "--depth", "bundled", "--depth-checkpoint", ckpt,
                 "--out", str(tmp_path / "run"), "--max-steps", "1", "--log.val_every", "0", "--device", "cpu",
                 *TINY_TRAIN_FLAGS, "--data.resolution", "16", "--data.num_workers", "1",
                 "--model.encoder.num_layers", "2"]) == 2  # 2 stages: 16 px keeps a 4x4 deepest stage
    err = capsys.readouterr().err
    assert err.endswith(f"error: {path}: depth prior holds non-finite values (view 0); run: depthnerf depth --data "
                        f"{data} --depth bundled --depth-checkpoint {ckpt} --category cars --splits train "
                        "--resolution 16\n"), err
    assert "Traceback" not in err


def test_a_cache_folder_without_its_manifest_names_the_manifest_and_depth_restores_it(data, tmp_path, capsys):
    """The folder of the right weights and resolution exists, its manifest.json is gone: the error names the
    manifest (not 'no priors ... found only: <that folder>'), and rerunning depth writes the manifest again."""
    ckpt = _weights(tmp_path / "a.safetensors", 0)
    assert _depth(data, ckpt) == 0
    store = PriorStore.open(data, "bundled", ckpt, resolution=16)
    manifest = store.root / "manifest.json"
    kept = json.loads(manifest.read_text())
    manifest.unlink()
    with pytest.raises(DepthnerfError) as err:
        PriorStore.open(data, "bundled", ckpt, resolution=16)
    assert str(err.value).startswith(f"{manifest}: cache manifest is missing")
    assert f"rerun: depthnerf depth --data {data}" in str(err.value) and "found only" not in str(err.value)
    capsys.readouterr()
    assert _depth(data, ckpt) == 0
    assert "0 objects computed (0 were stale), 3 already up to date" in capsys.readouterr().out
    restored = json.loads(manifest.read_text())
    assert restored["splits"] == kept["splits"] and restored["provenance"] == kept["provenance"]
    PriorStore.open(data, "bundled", ckpt, resolution=16).check(index_split(data, "cars", "train").objects)
