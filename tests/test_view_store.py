"""The view store (:mod:`depthnerf.data.view_store`): training items read from it equal, to the bit, the items
decoded from the PNG files (8-bit at their own size: stored as uint8; resized: float32), with and without mask
files, target priors and bounding boxes; changed objects are decoded again; a store of another resolution, a
missing or a damaged object is one line naming it; and a run trained from a store (in a loader worker, resumed)
equals the run trained from the files."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_srn import make_srn_fixture

from depthnerf.data import srn_format
from depthnerf.data.srn import index_split
from depthnerf.data.view_store import ViewStore
from depthnerf.depth.prior import PriorConfig, open_prior
from depthnerf.errors import DepthnerfError
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.batching import BatchPlan, TrainBatch, step_keys
from depthnerf.train.items import TrainItems
from depthnerf.train.run_log import read_metrics

FIELDS = ("ray_origins", "ray_dirs", "target_rgb", "target_prior", "target_fg", "target_cos")


def tensors(batch: TrainBatch) -> dict[str, torch.Tensor | None]:
    out = {name: getattr(batch, name) for name in FIELDS}
    out.update(images=batch.source.images, poses=batch.source.poses, focal=batch.source.focal,
               principal=batch.source.principal, disparity=batch.source.disparity)
    return out


def assert_same_items(a: TrainItems, b: TrainItems, keys) -> None:
    for key in keys:
        x, y = tensors(a[key]), tensors(b[key])
        for name in x:
            if x[name] is None:
                assert y[name] is None, name
            else:
                assert x[name].dtype == y[name].dtype and torch.equal(x[name], y[name]), (key, name)


def scramble_colours(root: Path, seed: int = 0) -> None:
    """Random colours in every RGB file, keeping white pixels white (so the masks and boxes stay the sphere's):
    no symmetry of the fixture's images can hide a swapped row and column."""
    rng = np.random.default_rng(seed)
    for path in sorted(root.rglob("rgb/*.png")):
        img = np.asarray(srn_format.read_rgb(path))
        white = (img == 1.0).all(-1, keepdims=True)
        srn_format.write_rgb(path, np.where(white, 1.0, rng.integers(0, 250, img.shape) / 255.0))


def items_pair(root: Path, store_dir: Path, resolution: int, depth: str, target_priors: bool):
    records = index_split(root, "cars", "train").objects
    prior = open_prior(PriorConfig(depth), data_root=root, resolution=resolution, records=records)
    store = ViewStore(store_dir, resolution, 0.5)
    counts = store.ensure(records)
    common = dict(resolution=resolution, target_views=0, rays_per_object=64, target_priors=target_priors,
                  pixel_center=0.5)
    plan = BatchPlan(num_objects=len(records), seed=3, bbox_steps=2, objects_phase1=2, objects_phase2=2)
    keys = [k for step in range(5) for k in step_keys(plan, step)]
    assert any(k.use_bbox for k in keys) and not all(k.use_bbox for k in keys)
    return (TrainItems(records, prior, **common), TrainItems(records, prior, **common, view_store=store), keys,
            counts, store, records)


@pytest.mark.parametrize("resolution, dtype", [(16, "uint8"), (8, "float32")])
@pytest.mark.parametrize("with_mask", [False, True])
def test_items_from_the_store_equal_items_from_the_files(tmp_path, resolution, dtype, with_mask):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=5, size=16, with_depth=True,
                            with_mask=with_mask)
    scramble_colours(root)
    files, stored, keys, counts, store, records = items_pair(root, tmp_path / "store", resolution, "oracle", True)
    assert counts == {"built": 2, "rebuilt": 0, "reused": 0}
    meta = json.loads((store.object_dir(records[0]) / "meta.json").read_text())
    assert meta["images"] == dtype
    assert_same_items(files, stored, keys)
    assert stored[keys[0]].target_prior is not None


def test_alpha_composited_images_are_stored_exactly_as_float32(tmp_path):
    """RGBA PNGs composite on white to values that are not k / 255: the store keeps float32, and items agree."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=4, size=16)
    scramble_colours(root)
    records = index_split(root, "cars", "train").objects
    rgb = records[0].rgb_path(1)
    rgba = np.concatenate([np.asarray(srn_format.read_rgb(rgb)), np.full((16, 16, 1), 0.5, np.float32)], axis=-1)
    from PIL import Image
    Image.fromarray((rgba * 255).round().astype(np.uint8), "RGBA").save(rgb)
    files, stored, keys, _, store, records = items_pair(root, tmp_path / "store", 16, "none", False)
    assert json.loads((store.object_dir(records[0]) / "meta.json").read_text())["images"] == "float32"
    assert json.loads((store.object_dir(records[1]) / "meta.json").read_text())["images"] == "uint8"
    assert_same_items(files, stored, keys)


def test_a_changed_object_is_decoded_again(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=4, size=16)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    assert store.ensure(records) == {"built": 2, "rebuilt": 0, "reused": 0}
    assert store.ensure(records) == {"built": 0, "rebuilt": 0, "reused": 2}
    path = records[1].rgb_path(2)
    img = np.asarray(srn_format.read_rgb(path))
    srn_format.write_rgb(path, 1.0 - img)
    os.utime(path, ns=(1, 1))  # a new modification time even on a coarse-grained file system
    assert store.ensure(records) == {"built": 0, "rebuilt": 1, "reused": 1}
    np.testing.assert_array_equal(store.open(records[1]).views([2])[0][0].permute(1, 2, 0).numpy(),
                                  srn_format.read_rgb(path))
    # other ranks' shares: each rank handles records[rank::world]
    assert store.ensure(records, rank=1, world=2) == {"built": 0, "rebuilt": 0, "reused": 1}


def test_a_store_of_another_resolution_is_refused(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    ViewStore(tmp_path / "store", 16, 0.5).ensure(records)
    with pytest.raises(DepthnerfError, match=r"manifest\.json: the view store was made for .*'resolution': 16"):
        ViewStore(tmp_path / "store", 8, 0.5).ensure(records)


def test_missing_and_damaged_objects_are_one_line(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records[:1])
    with pytest.raises(DepthnerfError, match=rf"{records[1].object_id}: missing from the view store"):
        store.open(records[1])
    (store.object_dir(records[0]) / "images.npy").write_bytes(b"not an array")
    with pytest.raises(DepthnerfError, match=r"unreadable view store object .*delete the folder to rebuild it"):
        store.open(records[0])


def cli(*args: str) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "depthnerf", *args], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def test_a_run_trained_from_the_store_equals_the_run_trained_from_the_files(tmp_path):
    """A worker process reads the store, the run resumes halfway with the store, and the loss curve and final
    weights equal a run decoded from the PNG files."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 3}, views=4, size=32, with_mask=True)
    base = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(root), "--log.val_every", "0",
            "--checkpoint-every", "2", *TINY, *(["--deterministic"] if torch.cuda.is_available() else [])]
    cli(*base, "--max-steps", "4", "--out", str(tmp_path / "files"))
    store = ["--data.view_store", str(tmp_path / "store"), "--data.num_workers", "1"]
    first = cli(*base, *store, "--max-steps", "2", "--out", str(tmp_path / "stored"))
    assert "view store " in first.stderr and "3 objects decoded" in first.stderr
    again = cli("train", "--out", str(tmp_path / "stored"), "--resume", "--max-steps", "4", *store[:2])
    assert "0 objects decoded, 0 changed since and decoded again, 3 reused" in again.stderr

    def curve(run: Path) -> dict[int, float]:
        return {m["step"]: m["loss"] for m in read_metrics(run) if "loss" in m}

    assert curve(tmp_path / "stored") == curve(tmp_path / "files") and len(curve(tmp_path / "files")) == 4
    weights = [ckpt.read_weights(ckpt.latest_checkpoint(tmp_path / r / "checkpoints") / "model.safetensors")[0]
               for r in ("files", "stored")]
    assert weights[0].keys() == weights[1].keys()
    assert all(torch.equal(weights[0][k], weights[1][k]) for k in weights[0])


def test_pixels_and_views_index_like_the_loaded_tensors(tmp_path):
    """Against the loaded views' own indexing, one pixel at a time, for a stored object and an in-memory one."""
    from depthnerf.data.srn import load_object
    from depthnerf.data.view_store import StoredObject

    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=4, size=16, with_mask=True)
    scramble_colours(root)
    record = index_split(root, "cars", "train").objects[0]
    obj = load_object(record, resolution=16, pixel_center=0.5)
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure([record])
    gen = torch.Generator().manual_seed(0)
    v, r, c = (torch.randint(n, (50,), generator=gen) for n in (4, 16, 16))
    for arrays in (store.open(record), StoredObject.from_views(obj)):
        rgb, fg = arrays.pixels(v, r, c)
        for k in range(50):
            assert torch.equal(rgb[k], obj.images[v[k], :, r[k], c[k]])
            assert bool(fg[k]) == bool(obj.masks[v[k], r[k], c[k]])
        images, masks = arrays.views([2, 0])
        assert torch.equal(images, obj.images[[2, 0]]) and torch.equal(masks, obj.masks[[2, 0]])
        assert torch.equal(arrays.poses, obj.poses) and torch.equal(arrays.bboxes, obj.bboxes)
        assert arrays.intrinsics == obj.intrinsics


def test_runs_that_start_together_share_one_store(tmp_path):
    """Four processes build the same store at once (as the GPU study's runs do): all succeed and the store is
    whole; a folder left without its meta.json is decoded again."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 6}, views=4, size=16)
    code = ("import sys; from depthnerf.data.srn import index_split; from depthnerf.data.view_store import ViewStore; "
            "ViewStore(sys.argv[2], 16, 0.5).ensure(index_split(sys.argv[1], 'cars', 'train').objects)")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(root), str(tmp_path / "store")],
                              stderr=subprocess.PIPE, text=True) for _ in range(4)]
    for proc in procs:
        assert proc.wait(timeout=120) == 0, proc.stderr.read()
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    assert store.ensure(records) == {"built": 0, "rebuilt": 0, "reused": 6}
    assert not [p for p in (tmp_path / "store" / "cars_train").iterdir() if p.name.startswith(".")]
    (store.object_dir(records[2]) / "meta.json").unlink()
    assert store.ensure(records) == {"built": 1, "rebuilt": 0, "reused": 5}
    store.open(records[2])
