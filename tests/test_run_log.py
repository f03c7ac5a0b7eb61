"""A run folder's logs and guards (:mod:`depthnerf.train.run_log`) against what was written into them: the metric
lines and TensorBoard scalars a resume keeps (read back with TensorBoard's own reader), strict JSON for non-finite
values, the launches record and its world-size note, and which ``--out`` folders a run refuses."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest

from depthnerf.errors import DepthnerfError
from depthnerf.train.run_log import (
    RUN_CONFIG_KEYS,
    RunLog,
    check_run_dir,
    read_launches,
    read_metrics,
    read_run_record,
    record_launch,
)


def _strict(line: str) -> dict:
    """``json.loads`` that refuses the non-standard ``NaN`` / ``Infinity`` constants."""
    def refuse(name: str) -> None:
        raise ValueError(f"not JSON: {name}")

    return json.loads(line, parse_constant=refuse)


def test_a_resume_keeps_the_metric_lines_up_to_its_step_and_none_after_a_cut_line(tmp_path):
    """Lines of steps 1..6 and a resume from step 4: steps 1..4 stay (step 4 is the checkpoint's own line), the
    lines after it go; blank lines are skipped; a line cut by a kill ends what is kept (all after it came later)."""
    log = RunLog(tmp_path, 0, tensorboard=False)
    for step in range(1, 7):
        log.log(step, {"loss": step / 10})
    RunLog(tmp_path, 4, tensorboard=False).log(5, {"loss": 5.5})
    assert [(m["step"], m["loss"]) for m in read_metrics(tmp_path)] == [(1, 0.1), (2, 0.2), (3, 0.3), (4, 0.4),
                                                                      (5, 5.5)]
    path = tmp_path / "metrics.jsonl"
    lines = path.read_text().splitlines()
    path.write_text("\n".join(lines) + "\n\n")  # a blank line (an edit by hand) is no metric
    assert len(read_metrics(tmp_path)) == 5
    path.write_text("\n".join([*lines[:2], '{"step": 3, "lo', *lines[3:]]) + "\n")
    RunLog(tmp_path, 4, tensorboard=False)
    assert [m["step"] for m in read_metrics(tmp_path)] == [1, 2]


def test_a_resume_whose_validation_is_due_drops_that_steps_validation_line(tmp_path):
    """The checkpoint of step 4 has its validation due: a validation line of step 4 (a resume killed after logging
    it, before recording it in the checkpoint) goes, step 4's training line and earlier validations stay; without
    the flag the line stays."""
    log = RunLog(tmp_path, 0, tensorboard=False)
    for step in (2, 4):
        log.log(step, {"loss": step / 10})
        log.log(step, {"val_psnr": 10.0 + step}, prefix="val")
    RunLog(tmp_path, 4, tensorboard=False, validation_due=True)
    assert [(m["step"], "val_psnr" in m) for m in read_metrics(tmp_path)] == [(2, False), (2, True), (4, False)]
    log = RunLog(tmp_path, 4, tensorboard=False)
    log.log(4, {"val_psnr": 14.0}, prefix="val")
    RunLog(tmp_path, 4, tensorboard=False)
    assert [(m["step"], "val_psnr" in m) for m in read_metrics(tmp_path)][-1] == (4, True)


def test_non_finite_values_are_written_as_strict_json_nulls(tmp_path):
    log = RunLog(tmp_path, 0, tensorboard=False)
    log.log(1, {"loss": math.inf, "psnr": -math.inf, "depth": math.nan, "lr": 0.5, "count": 3})
    line = (tmp_path / "metrics.jsonl").read_text().splitlines()[0]
    assert _strict(line) == {"step": 1, "loss": None, "psnr": None, "depth": None, "lr": 0.5, "count": 3}


def test_a_run_folder_deleted_while_training_is_one_line_naming_the_metrics_file(tmp_path):
    run = tmp_path / "run"
    run.mkdir()
    log = RunLog(run, 0, tensorboard=False)
    log.log(1, {"loss": 0.5})
    (run / "metrics.jsonl").unlink()
    run.rmdir()
    with pytest.raises(DepthnerfError,
                       match=r"run/metrics.jsonl: cannot append the step-2 metrics .*moved or deleted"):
        log.log(2, {"loss": 0.4})


def _two_attempts(run, start_step: int, steps: tuple[int, ...]) -> list[tuple[int, float]]:
    """Steps 1..6 logged (loss = step), then a second process starting at ``start_step`` logs ``steps`` (loss =
    10 + step); the ``train/loss`` curve TensorBoard's own reader gives back."""
    accumulator = pytest.importorskip("tensorboard.backend.event_processing.event_accumulator")
    log = RunLog(run, 0)
    for step in range(1, 7):
        log.log(step, {"loss": float(step)})
    log.close()
    log = RunLog(run, start_step)
    for step in steps:
        log.log(step, {"loss": 10.0 + step})
    log.close()
    events = accumulator.EventAccumulator(str(run / "tb"))
    events.Reload()
    return [(e.step, e.value) for e in events.Scalars("train/loss")]


def test_a_resumed_runs_tensorboard_scalars_are_those_of_an_uninterrupted_run(tmp_path):
    """Read back with TensorBoard's own reader: steps 1..6 logged, a resume from the checkpoint of step 4 logs
    steps 5 and 6 again; the curve is steps 1..6 with the first process's values up to step 4 (which the
    checkpoint holds) and the resumed ones after, as an uninterrupted run would have logged them."""
    assert _two_attempts(tmp_path, 4, (5, 6)) == [(1, 1.0), (2, 2.0), (3, 3.0), (4, 4.0), (5, 15.0), (6, 16.0)]


def test_a_restart_before_the_first_checkpoint_drops_the_killed_attempts_tensorboard_scalars(tmp_path):
    """A run killed before its first checkpoint starts again from step 0 (``--resume`` finds no checkpoint): its
    metric lines are dropped, and TensorBoard (its own reader) shows only the new attempt's steps too."""
    assert _two_attempts(tmp_path, 0, (1, 2)) == [(1, 11.0), (2, 12.0)]
    assert [(m["step"], m["loss"]) for m in read_metrics(tmp_path)] == [(1, 11.0), (2, 12.0)]


def test_launches_note_only_a_resume_with_another_world_size(tmp_path):
    """A first start, a restart from step 0 on 2 ranks (nothing to compare: no note), a resume on the same 2
    ranks (no note), a resume on 1 rank (a note naming both sizes)."""
    assert record_launch(tmp_path, 0, 1, "cpu") is None
    assert record_launch(tmp_path, 0, 2, "cpu") is None
    assert record_launch(tmp_path, 5, 2, "cpu") is None
    note = record_launch(tmp_path, 8, 1, "cpu")
    assert note is not None and "world size 1" in note and "previous launch had 2" in note
    assert [(x["start_step"], x["world_size"]) for x in read_launches(tmp_path)] == [(0, 1), (0, 2), (5, 2), (8, 1)]


def test_launches_note_a_cuda_resume_that_drops_deterministic(tmp_path):
    """--deterministic is a flag of each command, not of the run: a CUDA resume without it is noted, once both
    notes apply both are on the one line; the CPU (deterministic kernels either way) and a first start are not."""
    assert record_launch(tmp_path, 0, 1, "cuda:0", deterministic=True) is None
    assert record_launch(tmp_path, 4, 1, "cuda:0", deterministic=True) is None
    note = record_launch(tmp_path, 8, 1, "cuda:0")
    assert note is not None and note.startswith("note: resuming without --deterministic") and note.count("\n") == 0
    assert record_launch(tmp_path, 9, 1, "cuda:0") is None  # the previous launch had it off already
    record_launch(tmp_path, 10, 2, "cuda:0", deterministic=True)
    both = record_launch(tmp_path, 12, 1, "cuda:0")
    assert "world size 1" in both and "without --deterministic" in both and both.count("note:") == 1
    (tmp_path / "cpu").mkdir()
    record_launch(tmp_path / "cpu", 0, 1, "cpu", deterministic=True)
    assert record_launch(tmp_path / "cpu", 3, 1, "cpu") is None
    assert [x["deterministic"] for x in read_launches(tmp_path)] == [True, True, False, False, True, False]


def test_a_launch_after_a_cut_line_is_recorded_on_its_own_line(tmp_path):
    """A kill cut the last line short: the next launch starts a line of its own, and every whole line before and
    after the cut one is read."""
    record_launch(tmp_path, 0, 2, "cpu")
    with open(tmp_path / "launches.jsonl", "a") as f:
        f.write('{"start_step": 4, "world')
    assert record_launch(tmp_path, 4, 2, "cpu") is None
    record_launch(tmp_path, 9, 2, "cpu")
    assert [x["start_step"] for x in read_launches(tmp_path)] == [0, 4, 9]


def _config(run: Path, data: object) -> None:
    run.mkdir(parents=True, exist_ok=True)
    (run / "config.json").write_text(json.dumps(data))


def test_out_holding_a_config_that_is_not_a_runs_is_refused_unless_the_run_has_a_checkpoint(tmp_path):
    """A run's config holds every key of ``RUN_CONFIG_KEYS``; one that holds only some of them is another file;
    with a checkpoint of its own the folder is a run and its config is not judged here."""
    _config(tmp_path / "run", {k: {} for k in RUN_CONFIG_KEYS})
    check_run_dir(tmp_path / "run", has_checkpoint=False)
    for key in sorted(RUN_CONFIG_KEYS):
        _config(tmp_path / key, {key: {}, "name": "mine"})
        with pytest.raises(DepthnerfError, match="not a depthnerf run's config"):
            check_run_dir(tmp_path / key, has_checkpoint=False)
        check_run_dir(tmp_path / key, has_checkpoint=True)


def test_out_that_is_a_file_or_holds_a_checkpoints_file_is_refused(tmp_path):
    (tmp_path / "file").write_text("x")
    with pytest.raises(DepthnerfError, match="--out is a file"):
        check_run_dir(tmp_path / "file", has_checkpoint=False)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "checkpoints").write_text("x")
    for has_checkpoint in (False, True):
        with pytest.raises(DepthnerfError, match="is a file, not a run's checkpoints folder"):
            check_run_dir(tmp_path / "run", has_checkpoint=has_checkpoint)
    check_run_dir(tmp_path / "new", has_checkpoint=False)


@pytest.mark.parametrize("text, said", [("[1]", "not a run record"), ("{\"a\": ", "unreadable run record")])
def test_a_run_record_is_an_object_or_one_line_naming_it(tmp_path, text, said):
    assert read_run_record(tmp_path / "prior.json") is None
    (tmp_path / "prior.json").write_text(text)
    with pytest.raises(DepthnerfError, match=f"{tmp_path / 'prior.json'}: {said}"):
        read_run_record(tmp_path / "prior.json")
    (tmp_path / "prior.json").write_text('{"weights": "x"}')
    assert read_run_record(tmp_path / "prior.json") == {"weights": "x"}
