"""Training under user mistakes: nonsense settings, damaged run files, the wrong folder or data, a full disk, a
second process on the same run, a kill between a checkpoint and its ``best`` copy. Each is one ``error:`` line
(exit 2) or is mended, never a traceback, a silently changed run or a lost checkpoint."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_srn import make_srn_fixture

from depthnerf.cli import main
from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.errors import DepthnerfError
from depthnerf.pretrained.spec import spec_from_train_config
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.config import check_config, from_dict_config, inference_spec, preset, z_range
from depthnerf.train.run_log import read_run_record, run_lock

BASE = ["train", "--preset", "cpu-cars", "--depth", "none", "--log.val_every", "0", "--device", "cpu", *TINY]


def one_error(capsys) -> str:
    err = capsys.readouterr().err
    lines = [line for line in err.splitlines() if line.startswith("error: ")]
    assert len(lines) == 1 and "Traceback" not in err, err
    return lines[0]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_srn_fixture(tmp_path_factory.mktemp("srn"), "cars", {"train": 2, "val": 1}, views=3, size=32)


def _checked(*flags: str):
    return check_config(apply_overrides(preset("cpu-cars"), list(flags)))


@pytest.mark.parametrize(("flags", "said"), [
    (("--schedule.lr", "inf"), "--schedule.lr must be a finite number, got inf"),  # was a traceback at step 1
    (("--data.z_far", "1e400"), "--data.z_far must be a finite number, got inf"),
    (("--data.z_near", "2"), "got 2.0, 1.8 (an unset one is the category's SRN value)"),  # trained near > far
    (("--render.sampler.n_coarse", "0"), "--render.sampler.n_coarse must be >= 1, got 0"),  # was a traceback
    (("--render.sampler.n_importance", "-1"), "--render.sampler.n_importance must be >= 0"),  # trained silently
    (("--render.sampler.gaussian_std", "-1"), "--render.sampler.gaussian_std must be >= 0"),
    (("--schedule.foreground_opacity_weight", "-0.1"), "--schedule.foreground_opacity_weight must be >= 0"),
    (("--schedule.foreground_opacity_weight", "nan"), "--schedule.foreground_opacity_weight must be"),
])
def test_nonsense_settings_are_refused_when_the_config_is_built(flags, said):
    with pytest.raises(DepthnerfError, match=None) as err:
        _checked(*flags)
    assert said in str(err.value)


def test_a_zero_near_bound_is_used_not_replaced_by_the_default():
    cfg = _checked("--data.z_near", "0")
    assert z_range(cfg) == (0.0, 1.8) and inference_spec(cfg).z_near == 0.0  # was 0.8: the flag silently ignored
    train = to_dict(cfg)
    spec = spec_from_train_config(train, to_dict(cfg.model), "old.safetensors")  # checkpoints without a spec
    assert spec.z_range == (0.0, 1.8)


@pytest.mark.parametrize(("edit", "said"), [
    (lambda d: d["schedule"].update(lr="x"), "config.json.schedule.lr: expected float, got 'x'"),
    (lambda d: d["schedule"].update(max_steps=6.0), "config.json.schedule.max_steps: expected int, got 6.0"),
    (lambda d: d["schedule"].update(lr_schedule="linear"), "'linear' is not one of exponential, cosine"),
    (lambda d: d["data"].update(num_workers=True), "config.json.data.num_workers: expected int, got True"),
    (lambda d: d["log"].update(val_views=3), "config.json.log.val_views: expected a list, got 3"),
    (lambda d: d.update(model=5), "config.json.model: expected a mapping for PixelNeRFConfig"),
    (lambda d: d.update(prior=[1]), "config.json.prior: expected a mapping for PriorConfig"),
])
def test_a_damaged_run_config_is_one_line(edit, said):
    stored = json.loads(json.dumps(to_dict(preset("cpu-cars"))))
    assert from_dict_config(json.loads(json.dumps(stored))) == preset("cpu-cars")
    edit(stored)
    with pytest.raises(DepthnerfError) as err:
        from_dict_config(stored)
    assert said in str(err.value)
    with pytest.raises(DepthnerfError, match="expected a mapping for TrainConfig"):
        from_dict_config([])


def _tiny_checkpoint(root: Path, step: int, best_step: int | None = None) -> Path:
    torch.manual_seed(step)
    model = torch.nn.Linear(3, 2)
    opt = torch.optim.Adam(model.parameters())
    model(torch.ones(1, 3)).sum().backward()
    opt.step()
    state = ckpt.TrainingState(step=step, best_psnr=12.0, best_step=best_step)
    return ckpt.save_checkpoint(root, model, opt, {"toy": 1}, state, keep_last=5)


@pytest.mark.parametrize("payload", ["{}", "[]", '{"step": "x", "best_psnr": null, "optimizer": {}}',
                                     '{"step": 1, "best_psnr": null, "optimizer": {"param_groups": 3}}'])
def test_a_damaged_training_state_is_one_line(tmp_path, payload):
    saved = _tiny_checkpoint(tmp_path, 1)
    (saved / "state.json").write_text(payload)
    model = torch.nn.Linear(3, 2)
    with pytest.raises(DepthnerfError, match="state.json: unreadable training state|optimizer state does not fit"):
        ckpt.load_checkpoint(saved, model, torch.optim.Adam(model.parameters()), {"toy": 1})


def test_a_full_disk_during_a_checkpoint_write_keeps_the_last_one_and_no_temporary(tmp_path, monkeypatch):
    first = _tiny_checkpoint(tmp_path, 1)

    def full(path, *args, **kwargs):
        (Path(path).parent / "model.safetensors").write_bytes(b"partial")
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(ckpt, "save_weights", full)
    with pytest.raises(DepthnerfError, match=r"step_00000002: could not write the checkpoint \(\[Errno 28\] No sp"):
        _tiny_checkpoint(tmp_path, 2)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["latest", "step_00000001"]  # no .step_*.tmp left
    assert ckpt.latest_checkpoint(tmp_path) == first


def test_out_must_be_a_new_empty_or_run_folder(data, tmp_path, capsys):
    a_file = tmp_path / "a_file"
    a_file.write_text("notes")
    assert main([*BASE, "--data", str(data), "--out", str(a_file), "--max-steps", "1"]) == 2
    assert one_error(capsys) == f"error: {a_file}: --out is a file, not a folder; choose another --out"
    under = a_file / "run" / "x"  # was an OS traceback from the run lock's mkdir
    assert main([*BASE, "--data", str(data), "--out", str(under), "--max-steps", "1"]) == 2
    assert one_error(capsys) == (f"error: {under}: --out lies under {a_file}, which is a file, not a folder; choose "
                                 "another --out")
    run = tmp_path / "store_run"  # a --data.view_store in the way is refused before the run folder is written
    assert main([*BASE, "--data", str(data), "--out", str(run), "--max-steps", "1", "--data.view_store",
                 str(a_file)]) == 2
    assert one_error(capsys) == f"error: {a_file}: --data.view_store is a file, not a folder"
    assert not run.exists()
    other = tmp_path / "papers"
    other.mkdir()
    (other / "config.json").write_text('{"not": "a run"}')
    (other / "draft.tex").write_text("x")
    assert main([*BASE, "--data", str(data), "--out", str(other), "--max-steps", "1"]) == 2
    assert one_error(capsys) == (f"error: {other / 'config.json'}: not a depthnerf run's config, and a run in "
                                 f"{other} would overwrite it; choose another --out")
    assert main([*BASE, "--data", str(data), "--out", str(other), "--max-steps", "1", "--resume"]) == 2
    assert f"{other / 'config.json'}: unknown field(s) not" in one_error(capsys)
    assert (other / "config.json").read_text() == '{"not": "a run"}' and sorted(os.listdir(other)) == [
        "config.json", "draft.tex"]
    odd = tmp_path / "odd"
    odd.mkdir()
    (odd / "checkpoints").write_text("x")
    assert main([*BASE, "--data", str(data), "--out", str(odd), "--max-steps", "1"]) == 2
    assert "checkpoints: is a file" in one_error(capsys)
    logged = tmp_path / "job"  # a cluster job's log redirected into the run folder before training starts
    logged.mkdir()
    (logged / "slurm.log").write_text("starting\n")
    assert main([*BASE, "--data", str(data), "--out", str(logged), "--max-steps", "1", "--resume"]) == 0
    assert (logged / "slurm.log").read_text() == "starting\n" and (logged / "checkpoints").is_dir()


def test_resume_on_other_data_or_beside_a_running_process_is_refused(data, tmp_path, capsys, monkeypatch):
    run = tmp_path / "run"
    assert main([*BASE, "--data", str(data), "--out", str(run), "--max-steps", "1"]) == 0
    capsys.readouterr()
    card = (run / "data_card.json").read_text()
    bigger = make_srn_fixture(tmp_path / "bigger", "cars", {"train": 3}, views=3, size=32)
    assert main(["train", "--out", str(run), "--resume", "--data", str(bigger), "--max-steps", "2"]) == 2
    assert one_error(capsys).endswith(f"data_card.json: the run trained on 2 training objects, but {bigger} holds 3; "
                                      "resume with --data naming the run's own data, or choose another --out for a "
                                      "new run")
    assert (run / "data_card.json").read_text() == card  # the record of what it trained on is kept
    other = make_srn_fixture(tmp_path / "other", "cars", {"train": 2}, views=3, size=32)
    for i, obj in enumerate(sorted((other / "cars_train").iterdir())):  # as many objects, other ids
        obj.rename(obj.with_name(f"other{i}"))
    assert main(["train", "--out", str(run), "--resume", "--data", str(other), "--max-steps", "2"]) == 2
    assert one_error(capsys).endswith(f"data_card.json: the run trained on other training objects (other object "
                                      f"ids) than {other} holds; resume with --data naming the run's own data, or "
                                      "choose another --out for a new run")
    monkeypatch.setattr("depthnerf.train.run_log.LOCK_WAIT_S", 2.0)  # the wait for a crashed node's lease, shortened
    with run_lock(run):  # another process (the lock is per open file, so this process counts as another)
        assert main(["train", "--out", str(run), "--resume", "--max-steps", "2", "--no-progress"]) == 2
    assert one_error(capsys) == f"error: {run}: another process is training this run; wait for it to end (or stop " \
                                "it) before resuming"
    assert main(["train", "--out", str(run), "--resume", "--max-steps", "2", "--no-progress"]) == 0



@pytest.mark.parametrize("record", ["prior.json", "data_card.json"])
def test_a_damaged_run_record_stops_the_resume_it_would_check(data, tmp_path, capsys, record):
    """``prior.json`` (the prior's weights the run trained with) and ``data_card.json`` (its training objects) feed
    resume checks: a damaged one is one line naming it, not taken as absent (the check skipped, the file replaced)."""
    run = tmp_path / "run"
    assert main([*BASE, "--data", str(data), "--out", str(run), "--max-steps", "1"]) == 0
    (run / record).write_text('{"train_objects": 2, ')  # cut short
    capsys.readouterr()
    assert main([*BASE, "--data", str(data), "--out", str(run), "--max-steps", "2", "--resume"]) == 2
    assert one_error(capsys).startswith(f"error: {run / record}: unreadable run record (")
    assert (run / record).read_text() == '{"train_objects": 2, ' and ckpt.latest_checkpoint(run / "checkpoints").name \
        == "step_00000001"
    (run / record).write_text("[2]")
    with pytest.raises(DepthnerfError, match=r"data_card.json|prior.json"):
        read_run_record(run / record)
    assert read_run_record(run / "no_such_record.json") is None  # a run from before the file existed

def test_a_kill_between_a_checkpoint_and_its_best_copy_is_mended_on_resume(data, tmp_path, capsys):
    run = tmp_path / "run"
    args = [*BASE, "--data", str(data), "--out", str(run), "--max-steps", "3", "--checkpoint-every", "2",
            "--log.val_every", "2", "--log.val_objects", "1", "--log.val_views", "1", "--log.keep_last", "1"]
    killed = subprocess.run([sys.executable, "-m", "depthnerf", *args], capture_output=True, text=True,
                            env={**os.environ, "DEPTHNERF_CRASH_AT": "best-copied@2"})
    assert killed.returncode == -9, killed.stderr[-2000:]
    assert not (run / "checkpoints" / "best").exists()  # step 2 improved on nothing, and its copy was cut short
    with pytest.MonkeyPatch.context() as mp:  # validation never improves on step 2 again: only the mend makes best/
        mp.setattr("depthnerf.eval.validation.validate", _worse_validation)
        assert main([*args, "--resume"]) == 0
    assert f"restored {run / 'checkpoints' / 'best'} from step_00000002" in capsys.readouterr().err
    best = run / "checkpoints" / "best"
    assert json.loads((best / "state.json").read_text())["step"] == 2
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["best", "latest", "step_00000003"]


def _worse_validation(*args, **kwargs):
    from depthnerf.eval.validation import ValidationResult

    return ValidationResult(psnr=-1.0, ssim=0.0, images={})


@pytest.mark.parametrize("text", ["", "zzz", "../.."])
def test_a_damaged_latest_pointer_names_what_it_says_and_the_way_out(tmp_path, text):
    _tiny_checkpoint(tmp_path, 1)
    (tmp_path / "latest").write_text(text + "\n")
    with pytest.raises(DepthnerfError) as err:  # was "points at <the checkpoints folder's own name>"
        ckpt.latest_checkpoint(tmp_path)
    assert str(err.value) == (f"{tmp_path / 'latest'}: names {text!r}, which is not a complete checkpoint in "
                              f"{tmp_path}; delete it to use the newest complete one, step_00000001")


def test_a_binary_latest_pointer_is_one_line(tmp_path):
    _tiny_checkpoint(tmp_path, 1)
    (tmp_path / "latest").write_bytes(b"\x00\xff")
    with pytest.raises(DepthnerfError) as err:  # was a UnicodeDecodeError traceback
        ckpt.latest_checkpoint(tmp_path)
    assert str(err.value) == (f"{tmp_path / 'latest'}: not a text file naming a checkpoint folder (corrupt "
                              f"pointer); delete it to use the newest complete one, step_00000001")


def test_a_best_folder_without_its_weights_is_refused_not_skipped(tmp_path):
    from depthnerf.pretrained.load import resolve_checkpoint

    root = tmp_path / "run" / "checkpoints"
    _tiny_checkpoint(root, 1)
    (root / "best").mkdir()
    (root / "best" / "state.json").write_text("{}")
    with pytest.raises(DepthnerfError) as err:  # was: step_00000001's weights, silently
        resolve_checkpoint(tmp_path / "run")
    assert str(err.value) == (f"{root / 'best'}: best checkpoint without model.safetensors; delete it to use the "
                              f"latest checkpoint, step_00000001")


def test_a_training_object_with_one_view_is_one_line(tmp_path, capsys):
    """pixelNeRF's items need a source and a target view: a one-view object stops training before anything is
    written, naming it (it used to fail in a loader worker with an indexing traceback, and then hang)."""
    data = make_srn_fixture(tmp_path / "d", "cars", {"train": 2}, views=3, size=16)
    obj = sorted((data / "cars_train").iterdir())[0]
    for sub in ("rgb", "pose"):
        for f in sorted((obj / sub).iterdir())[1:]:
            f.unlink()
    code = main(["train", "--preset", "cpu-cars", "--data", str(data), "--depth", "none", "--out",
                 str(tmp_path / "r"), "--max-steps", "2", "--device", "cpu", "--log.val_every", "0"])
    err = capsys.readouterr().err
    assert code == 2 and f"{obj}: has 1 view; a training object needs at least 2" in err
    assert not (tmp_path / "r").exists()


@pytest.mark.parametrize(("flags", "says"), [
    (["--log.val_objects", "0"], "--log.val_objects must be >= 1 with --log.val_every > 0"),
    (["--log.val_views", ""], "--log.val_views must name at least one view index >= 0 with --log.val_every > 0"),
    (["--log.val_views", "0,-1"], "--log.val_views must name at least one view index >= 0"),
])
def test_a_validation_that_would_score_nothing_is_refused(tmp_path, capsys, flags, says):
    """Validation over no objects (a numpy warning and a NaN PSNR) or no views (a silent fallback view) is one line
    up front; without validation the same settings are accepted."""
    args = ["train", "--preset", "cpu-cars", "--out", str(tmp_path / "r"), "--print-config", *flags]
    assert main([*args, "--log.val_every", "5"]) == 2
    assert says in one_error(capsys)
    assert main([*args, "--log.val_every", "0"]) == 0


def test_a_resolution_the_encoder_shrinks_to_one_pixel_is_refused(tmp_path, capsys):
    """At 16 px the deepest stage is 1x1, and per-object BatchNorm over one value crashed the first step."""
    args = ["train", "--preset", "cpu-cars", "--out", str(tmp_path / "r"), "--print-config", "--data.resolution"]
    assert main([*args, "16"]) == 2
    assert one_error(capsys) == ("error: --data.resolution must be >= 17 with this encoder, got 16: its deepest "
                                 "stage would be 1x1 pixel, and training normalises each object's features over "
                                 "their pixels (BatchNorm per object)")
    assert main([*args, "17"]) == 0


def test_validation_views_an_object_lacks_are_named_with_what_is_rendered(tmp_path):
    """View 999 of 3-view val objects was dropped and view 1 scored instead, silently; now a note says so."""
    from depthnerf.data.protocol import validation_targets, validation_views_note

    assert validation_targets([1, 999], 3) == [1] and validation_targets([0], 3) == [1]  # view 0: a 3-view input
    assert validation_targets([0, 125, 200], 251) == [0, 125, 200] and validation_targets([64], 251) == [65]
    assert validation_views_note([0, 125, 200], [("a", 251), ("b", 251)]) is None
    assert validation_views_note([1, 999], [("a", 3), ("b", 251), ("c", 3)]) == (  # b lacks view 999 too
        "note: --log.val_views 1,999: a has 3 views, input view 0; validation renders its views 1 (and 2 more val "
        "objects)")
    assert validation_views_note([0], [("a", 3)]) == (
        "note: --log.val_views 0: a has 3 views, input view 0; validation renders its views 1")


@pytest.mark.parametrize("views", ["9999", "1,3"])
def test_validation_views_the_val_objects_lack_are_refused(data, tmp_path, capsys, views):
    """Asked-for views a val object lacks (a config's [9999]) were replaced by another view with only a note; the
    presets' views, meant for SRN's 251-view val objects, still fall back with the note."""
    from depthnerf.data.protocol import check_validation_views

    flags = ["--data", str(data), "--max-steps", "1", "--log.val_every", "1", "--log.val_objects", "1"]
    assert main([*BASE, *flags, "--out", str(tmp_path / "r"), "--log.val_views", views]) == 2
    val = next(p for p in sorted((data / "cars_val").iterdir()) if p.is_dir())
    missing = views.split(",")[-1]
    assert one_error(capsys) == (f"error: --log.val_views {views}: view {missing} does not exist: val object {val} "
                                 "has 3 views (0-2); name views below 3")
    assert not (tmp_path / "r" / "checkpoints").exists()
    check_validation_views([0, 2], [("a", 3), ("b", 251)])  # views every object has: accepted
    with pytest.raises(DepthnerfError, match="val object a has 3 views"):
        check_validation_views([125], [("b", 251), ("a", 3)])  # the object with the fewest is named


def test_the_run_lock_waits_for_a_lock_released_meanwhile(tmp_path):
    """A lock held elsewhere (a crashed node's, until its lease ends) is waited for: released after ~1 s, it is
    taken; held past the wait, one line."""
    import threading

    with run_lock(tmp_path, wait_s=0):
        with pytest.raises(DepthnerfError, match="another process is training this run"):
            with run_lock(tmp_path, wait_s=0):
                pass
    holder = run_lock(tmp_path)
    holder.__enter__()
    threading.Timer(1.0, holder.__exit__, (None, None, None)).start()
    with run_lock(tmp_path, wait_s=10):
        pass


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT])
def test_a_stop_signal_during_the_lock_wait_ends_the_process_with_one_line(tmp_path, capsys, sig):
    """The wait for a held lock is announced; SIGTERM (a cluster cancelling the requeued job) or Ctrl+C during it
    exits with the signal's status (143, 130) and one line, and the process's own handlers come back."""
    import threading

    before = signal.getsignal(sig)
    with run_lock(tmp_path):  # another process's lock (per open file)
        threading.Timer(0.5, os.kill, (os.getpid(), sig)).start()
        with pytest.raises(SystemExit) as stopped:
            with run_lock(tmp_path, wait_s=30):
                pass
    assert stopped.value.code == 128 + sig
    assert capsys.readouterr().err.splitlines() == [
        f"{tmp_path}: another process holds this run's lock; waiting up to 30 s for it",
        f"{tmp_path}: stopped by {signal.Signals(sig).name} while waiting for the run's lock; this process wrote "
        "nothing to the run"]
    assert signal.getsignal(sig) is before


def test_a_step_that_cannot_fit_the_device_is_refused_before_training_starts(data, tmp_path, capsys):
    """Rays are drawn with replacement, so the data bounds nothing; but a step whose sample points alone exceed all
    the device's memory can never run: one line naming the settings with their values, before anything is written
    (it was an out-of-memory traceback from the first step's allocations)."""
    run = tmp_path / "run"
    assert main([*BASE, "--data", str(data), "--out", str(run), "--max-steps", "2",
                 "--schedule.rays_per_object", "1000000000000"]) == 2
    line = one_error(capsys)
    assert line.startswith("error: --schedule.objects_phase1 2 objects x --schedule.rays_per_object 1000000000000 rays "
                           "x 16 samples per ray (--render.sampler.n_coarse 8 + n_importance 4 + n_gaussian 4)"), line
    assert "a step's sample points alone would take 349.2 TiB, more than all the memory of cpu (" in line
    assert not run.exists()


def _raise_torch_cuda_oom():
    raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 0 has a total capacity of "
                                 "79.15 GiB of which 1.06 GiB is free.")


def _raise_cpu_allocator_error():
    torch.empty(1 << 55, dtype=torch.uint8)  # 32 PiB: more than any address space, refused at once


def _raise_memory_error():
    raise MemoryError


@pytest.mark.parametrize(("fail", "said"), [(_raise_torch_cuda_oom, "(could not allocate 2.00 GiB)"),
                                            (_raise_cpu_allocator_error, "(could not allocate 32.0 PiB)"),
                                            (_raise_memory_error, "(MemoryError)")])
def test_out_of_memory_in_a_step_is_one_line_and_the_run_resumes(data, tmp_path, capsys, monkeypatch, fail, said):
    """An allocation that fails in step 1 (torch's CUDA error, the CPU allocator's, Python's) is one line naming the
    settings that size a step and the allocation, exit 2; the checkpoint of step 1 stays the run's last, and --resume
    continues from it (it was a traceback)."""
    import depthnerf.train.loop as loop

    real, calls = loop.train_step, []

    def step_failing_at_1(*args, **kwargs):
        calls.append(1)
        if len(calls) == 2:
            fail()
        return real(*args, **kwargs)

    run = tmp_path / "run"
    args = [*BASE, "--data", str(data), "--out", str(run), "--max-steps", "3", "--checkpoint-every", "1"]
    monkeypatch.setattr(loop, "train_step", step_failing_at_1)
    assert main(args) == 2
    assert one_error(capsys) == (
        f"error: out of memory on cpu {said} at training step 1: a step renders --schedule.objects_phase1 2 objects x "
        "--schedule.rays_per_object 32 rays x 16 samples per ray (--render.sampler.n_coarse 8 + n_importance 4 + "
        "n_gaussian 4), at --data.resolution 32; the run keeps its last checkpoint step_00000001: --resume continues "
        "it on a device with more memory; smaller settings need a new run (another --out)")
    assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["latest", "step_00000001"]
    monkeypatch.setattr(loop, "train_step", real)
    assert main([*args, "--resume"]) == 0
    assert ckpt.latest_checkpoint(run / "checkpoints").name == "step_00000003"


def test_out_of_memory_in_a_loader_worker_or_validation_is_one_line(data, tmp_path, capsys, monkeypatch):
    """The CPU allocator's error in a DataLoader worker (re-raised in the main process with the worker's traceback
    as its text) and an allocation that fails in validation are one line each, naming what ran and its settings."""
    import multiprocessing

    from depthnerf.train.items import TrainItems

    if multiprocessing.get_start_method() == "fork":  # the patch reaches a forked worker
        with monkeypatch.context() as mp:
            mp.setattr(TrainItems, "__getitem__", lambda self, key: _raise_cpu_allocator_error())
            assert main([*BASE, "--data", str(data), "--out", str(tmp_path / "a"), "--max-steps", "2",
                         "--data.num_workers", "1"]) == 2
        line = one_error(capsys)
        assert line.startswith("error: out of memory on cpu (could not allocate 32.0 PiB) at training step 0: a step "
                               "renders --schedule.objects_phase1 2 objects"), line
        assert line.endswith("the run has no checkpoint yet: start it again with smaller settings (without --resume)")
    monkeypatch.setattr("depthnerf.eval.validation.validate", lambda *args, **kwargs: _raise_torch_cuda_oom())
    assert main([*BASE, "--data", str(data), "--out", str(tmp_path / "b"), "--max-steps", "2", "--log.val_every", "2",
                 "--log.val_objects", "1", "--log.val_views", "1", "--checkpoint-every", "1"]) == 2
    assert one_error(capsys).startswith(
        "error: out of memory on cpu (could not allocate 2.00 GiB) validating at step 2: it renders "
        "--log.render_chunk 4096 rays per chunk x 16 samples per ray, at --data.resolution 32; the run keeps its last "
        "checkpoint step_00000001")
