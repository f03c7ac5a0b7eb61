"""The view store (:mod:`depthnerf.data.view_store`): training items read from it equal, to the bit, the items
decoded from the PNG files (8-bit at their own size: stored as uint8; resized: float32), with and without mask
files, target priors and bounding boxes; changed objects are decoded again; a store of another resolution, a
missing or a damaged object is one line naming it; and a run trained from a store (in a loader worker, resumed)
equals the run trained from the files."""

from __future__ import annotations

import json
import os
import re
import subprocess
import sys
import time
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


@pytest.mark.parametrize(("resolution", "pixel_center", "said"), [
    (8, 0.5, r"'resolution': 16"),
    (16, 0.0, r"'pixel_center': 0\.5"),
])
def test_a_store_of_another_resolution_or_pixel_centre_is_refused(tmp_path, resolution, pixel_center, said):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    ViewStore(tmp_path / "store", 16, 0.5).ensure(records)
    with pytest.raises(DepthnerfError, match=r"manifest\.json: the view store was made for .*" + said):
        ViewStore(tmp_path / "store", resolution, pixel_center).ensure(records)


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


def cli(*args: str, cwd: Path | None = None) -> subprocess.CompletedProcess:
    proc = subprocess.run([sys.executable, "-m", "depthnerf", *args], capture_output=True, text=True, cwd=cwd)
    assert proc.returncode == 0, proc.stderr[-3000:]
    return proc


def test_a_run_trained_from_the_store_equals_the_run_trained_from_the_files(tmp_path):
    """A worker process reads the store, the run resumes halfway with the store, and the loss curve and final
    weights equal a run decoded from the PNG files."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 3}, views=4, size=32, with_mask=True)
    exact = ["--deterministic"] if torch.cuda.is_available() else []  # not stored in the run: every command says it
    base = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(root), "--log.val_every", "0",
            "--checkpoint-every", "2", *TINY, *exact]
    cli(*base, "--max-steps", "4", "--out", str(tmp_path / "files"))
    store = ["--data.view_store", "store", "--data.num_workers", "1"]  # relative to the first run's folder
    first = cli(*base, *store, "--max-steps", "2", "--out", str(tmp_path / "stored"), cwd=tmp_path)
    assert "view store " in first.stderr and "3 objects decoded" in first.stderr
    saved = json.loads((tmp_path / "stored" / "config.json").read_text())["data"]["view_store"]
    assert saved == str((tmp_path / "store").resolve())
    again = cli("train", "--out", str(tmp_path / "stored"), "--resume", "--max-steps", "4", *exact)  # from elsewhere
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
    """Four processes build the same store at once, released together (as the GPU study's runs start): all
    succeed and the store is whole, with no temporary folder left; a folder left without its meta.json is decoded
    again."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 12}, views=4, size=16)
    go = tmp_path / "go"
    code = ("import sys, time, pathlib; from depthnerf.data.srn import index_split; "
            "from depthnerf.data.view_store import ViewStore; records = index_split(sys.argv[1], 'cars', 'train').objects\n"
            "while not pathlib.Path(sys.argv[3]).exists(): time.sleep(0.005)\n"
            "print(ViewStore(sys.argv[2], 16, 0.5).ensure(records))")
    procs = [subprocess.Popen([sys.executable, "-c", code, str(root), str(tmp_path / "store"), str(go)],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for _ in range(4)]
    time.sleep(3)  # every process has imported and indexed by now, and waits for the flag
    go.touch()
    outs = [proc.communicate(timeout=120) for proc in procs]
    assert all(proc.returncode == 0 for proc in procs), [err for _, err in outs]
    counts = [eval(out) for out, _ in outs]  # noqa: S307 - a dict printed by the child
    assert all(sum(c.values()) == 12 for c in counts)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    assert store.ensure(records) == {"built": 0, "rebuilt": 0, "reused": 12}
    assert not [p for p in (tmp_path / "store" / "cars_train").iterdir() if p.name.startswith(".")]
    (store.object_dir(records[2]) / "meta.json").unlink()
    assert store.ensure(records) == {"built": 1, "rebuilt": 0, "reused": 11}
    store.open(records[2])


def test_the_dataset_itself_or_a_foreign_folder_is_never_a_store(tmp_path):
    """Naming the data folder (or any folder with other things in it) as the store is refused before anything is
    written, and a store never replaces an object folder that holds anything but its own files."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    before = sorted(str(p.relative_to(root)) for p in root.rglob("*"))
    with pytest.raises(DepthnerfError, match=r"srn: not empty and not a view store \(it holds cars_train\)"):
        ViewStore(root, 16, 0.5).ensure(records)
    assert sorted(str(p.relative_to(root)) for p in root.rglob("*")) == before
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    (store.object_dir(records[0]) / "meta.json").unlink()
    (store.object_dir(records[0]) / "notes.txt").write_text("mine")
    with pytest.raises(DepthnerfError, match=r"not a view store object \(it holds .*notes\.txt.*refusing"):
        store.ensure(records)
    assert (store.object_dir(records[0]) / "notes.txt").read_text() == "mine"
    (tmp_path / "afile").write_text("x")
    for where, said in ((tmp_path / "afile", "--data.view_store is a file, not a folder"),
                        (tmp_path / "afile" / "s", "--data.view_store lies under")):
        for probe in (ViewStore(where, 16, 0.5).check, lambda w=where: ViewStore(w, 16, 0.5).ensure(records)):
            with pytest.raises(DepthnerfError, match=said):
                probe()
    with pytest.raises(DepthnerfError, match=r"srn: not empty and not a view store"):
        ViewStore(root, 16, 0.5).check()
    ViewStore(tmp_path / "new" / "store", 16, 0.5).check()  # a new folder passes, and nothing is made yet
    assert not (tmp_path / "new").exists()


def test_an_object_rebuilt_from_other_data_under_a_run_is_refused(tmp_path):
    """Two datasets with the same object ids share one store: the second rebuilds the objects, and the first
    run's next read of them stops with one line instead of training on the other dataset's views."""
    first = make_srn_fixture(tmp_path / "a", splits={"train": 2}, views=3, size=16)
    second = make_srn_fixture(tmp_path / "b", splits={"train": 2}, views=3, size=16)
    scramble_colours(second, seed=5)
    store_a = ViewStore(tmp_path / "store", 16, 0.5)
    records_a = index_split(first, "cars", "train").objects
    store_a.ensure(records_a)
    store_a.open(records_a[0])
    counts = ViewStore(tmp_path / "store", 16, 0.5).ensure(index_split(second, "cars", "train").objects)
    assert counts["rebuilt"] == 2
    with pytest.raises(DepthnerfError, match=r"rebuilt from other files since this run started"):
        store_a.open(records_a[0])


def test_each_rank_checks_every_object_after_the_barrier(tmp_path):
    """Ranks that do not share a disk: an object changed in another rank's share is still decoded again by the
    full check that follows the barrier (depthnerf.train.items.ready_view_store)."""
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    path = records[0].rgb_path(1)
    srn_format.write_rgb(path, 1.0 - np.asarray(srn_format.read_rgb(path)))
    os.utime(path, ns=(1, 1))
    assert store.ensure(records, rank=1, world=2) == {"built": 0, "rebuilt": 0, "reused": 1}
    assert store.ensure(records) == {"built": 0, "rebuilt": 1, "reused": 1}


def test_a_damaged_meta_file_is_one_line(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    meta = store.object_dir(records[0]) / "meta.json"
    for damaged, why in (("[1, 2]", "not a JSON object"), ('{"views": 3, "finger', "Unterminated string")):
        meta.write_text(damaged)  # a damaged file is reported as such, naming it, not as a missing object
        with pytest.raises(DepthnerfError, match=rf"^{re.escape(str(meta))}: unreadable view store metadata "
                                                 rf"\({why}.*delete the folder to rebuild it$"):
            ViewStore(tmp_path / "store", 16, 0.5).open(records[0])
    assert ViewStore(tmp_path / "store", 16, 0.5).ensure(records) == {"built": 1, "rebuilt": 0, "reused": 0}
    ViewStore(tmp_path / "store", 16, 0.5).open(records[0])  # ... and the next build replaces it
    (store.object_dir(records[0]) / "meta.json").write_text('{"views": 3, "fingerprint": "x"}')
    with pytest.raises(DepthnerfError, match=r"unreadable view store object .*intrinsics"):
        ViewStore(tmp_path / "store", 16, 0.5).open(records[0])


RANK_CODE = """
import sys, torch, torch.distributed as dist
from depthnerf.data.srn import index_split
from depthnerf.distributed import DistInfo
from depthnerf.errors import DepthnerfError
from depthnerf.train.config import preset
from depthnerf.train.items import ready_view_store
import dataclasses
rank, port, root, store = int(sys.argv[1]), sys.argv[2], sys.argv[3], sys.argv[4]
dist.init_process_group("gloo", init_method=f"tcp://127.0.0.1:{port}", rank=rank, world_size=2)
cfg = preset("cpu-cars")
cfg = dataclasses.replace(cfg, data=dataclasses.replace(cfg.data, resolution=16, pixel_center=0.5, view_store=store))
try:
    ready_view_store(cfg.data, index_split(root, "cars", "train").objects, DistInfo(rank, 2, torch.device("cpu")))
    print("no error")
except DepthnerfError as err:
    print(f"error: {err}")
"""


def test_a_rank_that_cannot_build_its_share_stops_every_rank(tmp_path):
    """Rank 1 cannot build its share: both ranks stop with its one line (naming the rank) instead of rank 0
    waiting at a barrier for a rank that died."""
    import socket

    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    ViewStore(tmp_path / "st", 16, 0.5).ensure([])  # an empty store, then a folder it must not replace
    foreign = tmp_path / "st" / "cars_train" / records[1].object_id  # records[1::2] is rank 1's share
    foreign.mkdir(parents=True)
    (foreign / "notes.txt").write_text("mine")
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    procs = [subprocess.Popen([sys.executable, "-c", RANK_CODE, str(r), str(port), str(root), str(tmp_path / "st")],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    outs = [p.communicate(timeout=120)[0].strip() for p in procs]
    for out in outs:
        assert out.startswith("error: ") and f"{foreign}: not a view store object" in out, outs
        assert out.endswith("(rank 1)"), outs


def test_a_killed_builds_leftovers_are_swept_after_an_hour(tmp_path):
    from depthnerf.data.view_store import LEFTOVER_AGE_S

    root = make_srn_fixture(tmp_path / "srn", splits={"train": 1}, views=3, size=16)
    records = index_split(root, "cars", "train").objects
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    split = store.object_dir(records[0]).parent
    old, live = split / ".abc.tmp-x1", split / ".abc.tmp-x2"
    for folder in (old, live):
        folder.mkdir()
        (folder / "images.npy").write_bytes(b"partial")
    stale = time.time() - LEFTOVER_AGE_S - 10
    os.utime(old, (stale, stale))
    store.ensure(records)
    assert not old.exists() and live.exists()  # a build that may still be running is left alone


def test_ranks_on_separate_disks_each_end_with_every_object(tmp_path):
    """Two ranks, each with its own store folder (no shared disk): after start-up each store holds every object,
    its own share built in the first pass and the other rank's in the second."""
    import socket

    root = make_srn_fixture(tmp_path / "srn", splits={"train": 3}, views=3, size=16)
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    stores = [tmp_path / f"disk{r}" for r in (0, 1)]
    procs = [subprocess.Popen([sys.executable, "-c", RANK_CODE, str(r), str(port), str(root), str(stores[r])],
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True) for r in (0, 1)]
    outs = [p.communicate(timeout=120) for p in procs]
    assert [out.strip() for out, _ in outs] == ["no error", "no error"], outs
    records = index_split(root, "cars", "train").objects
    for store in stores:
        assert ViewStore(store, 16, 0.5).ensure(records) == {"built": 0, "rebuilt": 0, "reused": 3}


@pytest.mark.parametrize("target_priors", [False, True])
def test_a_packed_batch_unpacks_to_the_same_tensors_in_one_storage(tmp_path, target_priors):
    """What a DataLoader worker sends (``collate_packed``): one byte tensor; unpacked, every field equals the
    collated batch's (dtype, shape, bits), None fields stay None, and all tensors view one storage (one pin, one
    host-to-device copy); it crosses a process boundary as one shared-memory segment."""
    import io
    import pickle
    from multiprocessing.reduction import ForkingPickler

    import torch.multiprocessing  # noqa: F401 - registers the shared-memory reductions

    from depthnerf.train.batching import PackedBatch, collate

    root = make_srn_fixture(tmp_path / "srn", splits={"train": 3}, views=5, size=16, with_depth=True,
                            with_mask=True)
    files, _, keys, *_ = items_pair(root, tmp_path / "store", 16, "oracle", target_priors)
    batch = collate([files[k] for k in keys[:3]])
    packed = PackedBatch.pack(batch)
    sent = io.BytesIO()
    ForkingPickler(sent).dump(packed)  # as a worker's queue pickles it
    for unpacked in (packed.to("cpu"), pickle.loads(sent.getvalue()).to("cpu")):
        x, y = tensors(batch), tensors(unpacked)
        for name in x:
            if x[name] is None:
                assert y[name] is None, name
            else:
                assert x[name].dtype == y[name].dtype and x[name].shape == y[name].shape, name
                assert torch.equal(x[name], y[name]), name
        storages = {t.untyped_storage().data_ptr() for t in y.values() if t is not None}
        assert len(storages) == 1
    assert packed.flat.dtype == torch.uint8 and packed.flat.dim() == 1
