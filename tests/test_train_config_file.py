"""``depthnerf train --config FILE``: settings from a JSON file, laid over the preset and under the flags.

The config is built in layers (preset, then the file, then the named flags, then ``--section.field`` overrides), so
a run's own ``config.json`` reproduces that run, a file holding only what differs changes only that, and a flag
still wins. Every mistake in the file is one ``error:`` line naming it."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from depthnerf.cli import main
from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.errors import DepthnerfError
from depthnerf.train.config import check_config, preset


def printed(capsys, *flags: str) -> dict:
    assert main(["train", *flags, "--print-config"]) == 0
    return json.loads(capsys.readouterr().out)


def one_error(capsys, *flags: str) -> str:
    assert main(["train", *flags, "--print-config"]) == 2
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


def write(path: Path, data) -> str:
    path.write_text(json.dumps(data))
    return str(path)


def test_a_printed_config_reproduces_the_run_it_came_from(capsys, tmp_path):
    flags = ["--preset", "cpu-chairs", "--depth", "none", "--seed", "7", "--schedule.lr", "2e-4",
             "--model.coarse.d_hidden", "96", "--data", str(tmp_path)]
    full = printed(capsys, *flags)
    assert printed(capsys, "--config", write(tmp_path / "run.json", full)) == full  # its preset named inside


def test_a_file_of_differences_changes_only_those(capsys, tmp_path):
    data = str(tmp_path)
    plain = printed(capsys, "--preset", "cpu-chairs", "--data", data)
    file = write(tmp_path / "diff.json", {"preset": "cpu-chairs", "schedule": {"lr": 2e-4}, "render": {"sampler": {
        "n_importance": 8}}})
    got = printed(capsys, "--config", file, "--data", data)
    assert got["schedule"]["lr"] == 2e-4 and got["render"]["sampler"]["n_importance"] == 8
    assert plain["schedule"]["lr"] != 2e-4 and plain["render"]["sampler"]["n_importance"] != 8
    got["schedule"]["lr"], got["render"]["sampler"]["n_importance"] = (plain["schedule"]["lr"],
                                                                      plain["render"]["sampler"]["n_importance"])
    assert got == plain  # every other field is the preset's, nested sections merged key by key
    no_name = write(tmp_path / "bare.json", {"seed": 3})  # no preset in the file: --preset, else the default
    assert printed(capsys, "--config", no_name, "--preset", "cpu-chairs", "--data", data) == {**plain, "seed": 3}
    assert printed(capsys, "--config", no_name)["preset"] == "cpu-cars"


def test_flags_win_over_the_file(capsys, tmp_path):
    file = write(tmp_path / "c.json", {"seed": 3, "schedule": {"lr": 2e-4, "max_steps": 50}, "prior": {
        "estimator": "none"}})
    got = printed(capsys, "--config", file, "--seed", "9", "--schedule.lr", "5e-4", "--depth", "oracle")
    assert (got["seed"], got["schedule"]["lr"], got["schedule"]["max_steps"]) == (9, 5e-4, 50)
    assert got["prior"]["estimator"] == "oracle"
    assert printed(capsys, "--config", file)["prior"]["estimator"] == "none"  # the file's baseline switch holds


@pytest.mark.parametrize(("content", "said"), [
    ("{not json", "unreadable --config file"),
    ("[1, 2]", "unreadable --config file (a JSON object was expected, got list)"),
    ('{"schedule": {"lrr": 1e-4}}', "unknown field(s) lrr for ScheduleConfig"),
    ('{"schedule": {"lr": "fast"}}', "schedule.lr: expected float, got 'fast'"),
    ('{"model": 5}', "model: expected a mapping for PixelNeRFConfig"),
    ('{"schedule": {"lr": -1}}', "--schedule.lr must be"),  # the config's own checks run on the file's values too
])
def test_a_bad_config_file_is_one_line_naming_it(capsys, tmp_path, content, said):
    path = tmp_path / "bad.json"
    path.write_text(content)
    line = one_error(capsys, "--config", str(path))
    assert said in line and (str(path) in line or said.startswith("--")), line


def test_a_missing_file_or_a_second_preset_is_one_line(capsys, tmp_path):
    assert "missing.json: unreadable --config file" in one_error(capsys, "--config", str(tmp_path / "missing.json"))
    file = write(tmp_path / "chairs.json", {"preset": "cpu-chairs"})
    assert "a cpu-chairs config, but --preset cpu-cars" in one_error(capsys, "--config", file, "--preset", "cpu-cars")


def test_on_resume_the_file_may_change_only_what_a_flag_may(capsys, tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    stored = json.loads(json.dumps(to_dict(preset("cpu-cars"))))
    stored["data"]["root"] = str(tmp_path)
    (run / "config.json").write_text(json.dumps(stored))
    longer = write(tmp_path / "longer.json", {"schedule": {"max_steps": 99}})
    got = printed(capsys, "--out", str(run), "--resume", "--config", longer)
    assert got["schedule"]["max_steps"] == 99 and {**got, "schedule": stored["schedule"]} == stored
    other = write(tmp_path / "other.json", {"schedule": {"lr": 1e-5}})
    line = one_error(capsys, "--out", str(run), "--resume", "--config", other)
    assert f"--resume: the flags and --config {other} contradict the run's config" in line and "schedule.lr" in line


def test_train_config_refuses_a_depth_loss_min_opacity_outside_0_1():
    cfg = preset("cpu-cars")
    assert cfg.schedule.depth_loss_min_opacity == 0.5
    for good in ("0", "0.25", "0.99"):
        flags = ["--schedule.depth_loss_min_opacity", good]
        assert check_config(apply_overrides(cfg, flags)).schedule.depth_loss_min_opacity == float(good)
    for bad in ("1", "-0.1", "nan", "2"):
        with pytest.raises(DepthnerfError, match=r"^--schedule\.depth_loss_min_opacity must be in \[0, 1\), got"):
            check_config(apply_overrides(cfg, ["--schedule.depth_loss_min_opacity", bad]))
