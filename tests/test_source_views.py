"""Several source views per training item (``--data.source_views``, pixelNeRF's ``--nviews``): the item holds
exactly the views its draw names, the view store gives the same items, one source draws as before, and a run
trained on two views is evaluated on two (``eval --input-views``)."""

from __future__ import annotations

import json

import torch
from fixtures_srn import make_srn_fixture
from test_eval_protocol import TINY, cli
from test_view_store import assert_same_items, scramble_colours

from depthnerf.data.srn import index_split, load_object
from depthnerf.data.view_store import ViewStore
from depthnerf.depth.prior import PriorConfig, open_prior
from depthnerf.train.batching import BatchPlan, ItemKey, pick_views, step_keys
from depthnerf.train.items import TrainItems


def test_sources_and_targets_are_one_permutation_and_one_source_draws_as_before():
    for sources in (1, 2, 3):
        gen, ref = torch.Generator().manual_seed(5), torch.Generator().manual_seed(5)
        src, targets = pick_views(6, 0, gen, sources)
        perm = torch.randperm(6, generator=ref).tolist()
        assert src == perm[:sources] and targets == perm[sources:]
    src, targets = pick_views(6, 2, torch.Generator().manual_seed(5), 2)
    assert len(targets) == 2 and not set(src) & set(targets)


def test_an_item_holds_the_drawn_source_views_and_the_store_agrees(tmp_path):
    root = make_srn_fixture(tmp_path / "srn", splits={"train": 2}, views=5, size=16, with_depth=True)
    scramble_colours(root)
    records = index_split(root, "cars", "train").objects
    prior = open_prior(PriorConfig("oracle"), data_root=root, resolution=16, records=records)
    store = ViewStore(tmp_path / "store", 16, 0.5)
    store.ensure(records)
    common = dict(resolution=16, target_views=2, rays_per_object=32, target_priors=False, pixel_center=0.5,
                  source_views=2)
    files = TrainItems(records, prior, **common)
    key = ItemKey(object_index=1, seed=11, use_bbox=False)
    src, _ = pick_views(5, 2, torch.Generator().manual_seed(11), 2)
    want = load_object(records[1], src, resolution=16, pixel_center=0.5)
    item = files[key]
    assert item.source.images.shape == (1, 2, 3, 16, 16) and item.source.disparity.shape == (1, 2, 1, 16, 16)
    assert torch.equal(item.source.images[0], want.images) and torch.equal(item.source.poses[0], want.poses)
    plan = BatchPlan(num_objects=2, seed=3, bbox_steps=1, objects_phase1=2, objects_phase2=2)
    keys = [k for step in range(3) for k in step_keys(plan, step)]
    assert_same_items(files, TrainItems(records, prior, **common, view_store=store), keys)


def test_a_two_view_run_trains_and_is_evaluated_on_two_views(tmp_path, capsys):
    root = tmp_path / "data"
    make_srn_fixture(root, "cars", {"train": 2}, views=3, size=32, with_mask=True)
    make_srn_fixture(root, "cars", {"test": 1}, views=66, size=32, with_mask=True)
    run = tmp_path / "run"
    assert cli("train", "--depth", "none", "--data", root, "--out", run, *TINY, "--data.source_views", "2") == 0
    assert json.loads((run / "config.json").read_text())["data"]["source_views"] == 2
    out = tmp_path / "eval"
    assert cli("eval", "--run", run, "--out", out, "--input-views", "64", "20", "--views-stride", "32",
               "--no-mesh", "--no-progress") == 0
    assert json.loads((out / "summary.json").read_text())["input_views"] == [64, 20]
    capsys.readouterr()
    assert cli("train", "--depth", "none", "--data", root, "--out", tmp_path / "run3", *TINY,
               "--data.source_views", "3") == 2
    err = capsys.readouterr().err
    assert "has 3 views; a training object needs at least 4 (--data.source_views 3 and a target)" in err
    assert err.count("\n") == 1
