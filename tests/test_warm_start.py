"""``train --init-from`` from a checkpoint of another category than the run's data: one warning line naming both
categories (a cross-category warm start may be deliberate, so it is no error); none for the same category."""

from __future__ import annotations

import json
import warnings

import pytest

from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.errors import UsageWarning
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.train.warm_start import warm_start
from tests.fixtures_checkpoints import save_tiny, tiny_config


def test_a_source_of_another_category_is_warned_of(tmp_path):
    cfg = tiny_config("cars", "none")
    chairs = save_tiny(tmp_path / "chairs.safetensors", apply_overrides(cfg, ["--data.category", "chairs"]))
    model = PixelNeRF(cfg.model, depth_aware=False)
    with pytest.warns(UsageWarning, match=rf"^{chairs}: --init-from is a chairs model, the run trains on cars "
                                          r"data; the warm start begins from another category's weights$"):
        warm_start(model, str(chairs), cfg.model, False, "cars")
    cars = save_tiny(tmp_path / "cars.safetensors", cfg)
    with warnings.catch_warnings():
        warnings.simplefilter("error", UsageWarning)
        warm_start(model, str(cars), cfg.model, False, "cars")
        warm_start(model, str(chairs), cfg.model, False)  # no category given: nothing to compare


def test_train_prints_the_warning_once_and_trains(tmp_path, capsys):
    from depthnerf.cli import main
    from tests.fixtures_srn import make_srn_fixture

    root = make_srn_fixture(tmp_path / "data", "cars", {"train": 2}, views=4, size=16)
    cfg = apply_overrides(tiny_config("cars", "none"), ["--data.num_workers", "0", "--log.val_every", "0",
                                                        "--schedule.objects_phase1", "1",
                                                        "--schedule.objects_phase2", "1"])
    chairs = save_tiny(tmp_path / "chairs.safetensors", apply_overrides(cfg, ["--data.category", "chairs"]))
    (tmp_path / "config.json").write_text(json.dumps(to_dict(cfg)))
    assert main(["train", "--config", str(tmp_path / "config.json"), "--data", str(root), "--out",
                 str(tmp_path / "run"), "--max-steps", "1", "--init-from", str(chairs), "--no-progress"]) == 0
    lines = [line for line in capsys.readouterr().err.splitlines() if "another category" in line]
    assert lines == [f"warning: {chairs}: --init-from is a chairs model, the run trains on cars data; the warm "
                     "start begins from another category's weights"]
