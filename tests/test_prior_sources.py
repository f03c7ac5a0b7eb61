"""The prior sources against each other: a live estimator rounded as the cache stores it equals the cached prior,
the oracle source equals 1/z, and the conditioning stage normalises every source's prior the same way."""

from __future__ import annotations

import pytest
import torch
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.data.srn import index_split, load_object
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.depth.cache import as_cached
from depthnerf.depth.estimators import oracle_disparity
from depthnerf.depth.normalize import normalize_disparity
from depthnerf.depth.prior import DatasetViews, PriorConfig, open_prior
from depthnerf.errors import DepthnerfError
from depthnerf.model.conditioning import condition, condition_views


@pytest.fixture(scope="module")
def setup(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("priors")
    root = make_srn_fixture(tmp / "srn", splits={"test": 2}, views=3, size=16, with_depth=True, with_mask=True)
    torch.manual_seed(0)
    weights = tmp / "w.safetensors"
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(4, 6, 8), input_size=16)), weights)
    assert main(["depth", "--data", str(root), "--depth", "bundled", "--depth-checkpoint", str(weights),
                 "--no-progress"]) == 0
    return root, str(weights), index_split(root, "cars", "test").objects


def test_live_prior_rounded_as_cached_equals_the_cache(setup):
    root, weights, records = setup
    prior = PriorConfig("bundled", weights)
    cached = open_prior(prior, data_root=root, resolution=16, records=records)
    live = open_prior(prior, match_cache=True)
    raw = open_prior(prior)
    assert (cached.kind, live.kind, raw.kind) == ("cache", "live", "live")
    for record in records:
        obj = load_object(record, [2, 0], resolution=16, pixel_center=0.0)
        where = DatasetViews(record, (2, 0))
        from_cache = cached.disparity(obj.images, where=where)
        from_live = live.disparity(obj.images)
        assert torch.equal(from_cache, from_live)  # bit-exact by design: one rounding rule (as_cached)
        assert torch.equal(as_cached(raw.disparity(obj.images)), from_live)
        a, b = condition_views(cached, obj), condition(live, obj.images, obj.masks, obj.poses, obj.intrinsics)
        assert torch.equal(a.inputs.disparity, b.inputs.disparity) and torch.equal(a.inputs.images, b.inputs.images)
        assert torch.equal(a.inputs.disparity[0, :, 0], normalize_disparity(from_cache, obj.masks))
    with pytest.raises(DepthnerfError, match="serves dataset views only"):
        cached.disparity(obj.images)


def test_oracle_and_none_sources(setup):
    root, _, records = setup
    oracle_cache = open_prior(PriorConfig("oracle"), data_root=root, resolution=16, records=records)
    oracle_live = open_prior(PriorConfig("oracle"))
    obj = load_object(records[0], [1], resolution=16, with_depth=True, pixel_center=0.0)
    expect = oracle_disparity(obj.depths)
    assert torch.equal(oracle_cache.disparity(obj.images, where=DatasetViews(records[0], (1,))), expect)
    assert torch.equal(oracle_live.disparity(obj.images, depths=obj.depths), expect)
    with pytest.raises(DepthnerfError, match="which a photo does not have; choose --depth"):
        oracle_live.disparity(obj.images)
    none = open_prior(PriorConfig("none"), data_root=root)
    cond = condition_views(none, obj)
    assert none.kind == "none" and cond.disparity is None and cond.inputs.disparity is None
    assert none.provenance is None


def test_as_cached_is_the_cache_storage_rule():
    small = torch.tensor([[[0.1, 1.0 / 3.0]]])
    assert torch.equal(as_cached(small), small.half().float())
    big = torch.tensor([[[7e4, 1.0 / 3.0]]])  # would overflow float16: stored (and rounded) as float32
    assert torch.equal(as_cached(big), big)


def test_missing_cache_names_the_unified_flags(tmp_path, setup):
    root = make_srn_fixture(tmp_path / "empty", splits={"test": 1}, views=3, size=16)
    with pytest.raises(DepthnerfError, match=r"run: depthnerf depth --data .* --depth bundled --depth-checkpoint "):
        open_prior(PriorConfig("bundled", setup[1]), data_root=root, resolution=16)
