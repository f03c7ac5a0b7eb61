"""A validation that a stop signal skipped or abandoned is run by the resume: the resumed run's validation records
(``metrics.jsonl``), best step and ``best/`` equal an uninterrupted run's (:mod:`depthnerf.train.stop`; the
checkpoint's ``validation_due``)."""

from __future__ import annotations

import json
import signal
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_checkpoints import cli
from fixtures_srn import make_srn_fixture

from depthnerf.train import checkpoint as ckpt
from depthnerf.train.run_log import read_metrics

ARGS = ["train", "--preset", "cpu-cars", "--depth", "none", "--max-steps", "6", "--checkpoint-every", "3",
        "--log.val_every", "2", "--log.val_objects", "1", "--log.keep_last", "2", *TINY,
        *(["--deterministic"] if torch.cuda.is_available() else [])]
"""Validations at steps 2, 4 and 6; checkpoints at 3 and 6 (and at a stop, and at each better validation)."""


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("srn")
    return make_srn_fixture(root, "cars", {"train": 4, "val": 1}, views=4, size=32, with_depth=True, with_mask=True)


@pytest.fixture(scope="module")
def uninterrupted(data, tmp_path_factory) -> Path:
    run = tmp_path_factory.mktemp("full") / "run"
    cli(*ARGS, "--data", str(data), "--out", str(run))
    return run


def validations(run: Path) -> list[tuple[int, float, float]]:
    """The run's validation records: (step, PSNR, SSIM), in the order logged."""
    return [(m["step"], m["val_psnr"], m["val_ssim"]) for m in read_metrics(run) if "val_psnr" in m]


def best_steps(run: Path) -> tuple[int | None, int | None]:
    """The best step the last checkpoint records and the step ``best/`` holds."""
    root = run / "checkpoints"
    state = json.loads((ckpt.latest_checkpoint(root) / "state.json").read_text())
    return state["best_step"], json.loads((root / "best" / "state.json").read_text())["step"]


@pytest.mark.parametrize("hook, code", [("sigterm-validation@4", 143), ("sigint-validation@2", 130),
                                        ("sigterm-step@4", 143), ("sigterm-validation@6", 143)])
def test_a_validation_lost_to_a_stop_signal_runs_on_resume(data, uninterrupted, tmp_path, hook, code):
    """A signal as a validation starts (it is abandoned; at step 2 the resumed one is the best so far), just before
    it (it is skipped), or as the last step's validation starts: the stop checkpoints that step, and ``--resume``
    validates it before training on, so the validation records, the best step and ``best/`` equal the uninterrupted
    run's."""
    run = tmp_path / "stopped"
    step = int(hook.rsplit("@", 1)[1])
    stopped = cli(*ARGS, "--data", str(data), "--out", str(run), check=False, env={"DEPTHNERF_CRASH_AT": hook})
    assert stopped.returncode == code, stopped.stderr[-2000:]
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{step:08d}"
    assert [v[0] for v in validations(run)] == list(range(2, step, 2))
    resumed = cli(*ARGS, "--data", str(data), "--out", str(run), "--resume")
    assert validations(run) == validations(uninterrupted)
    assert best_steps(run) == best_steps(uninterrupted)
    assert same_best_weights(run, uninterrupted)
    assert f"validating step {step} first" in resumed.stderr


def same_best_weights(run: Path, reference: Path) -> bool:
    ref = ckpt.read_weights(reference / "checkpoints" / "best" / "model.safetensors")[0]
    got = ckpt.read_weights(run / "checkpoints" / "best" / "model.safetensors")[0]
    return ref.keys() == got.keys() and all(torch.equal(ref[k], got[k]) for k in ref)


@pytest.mark.parametrize("second, code, logged", [("sigterm-validation@2", 128 + signal.SIGTERM, []),
                                                  ("best-copied@2", -signal.SIGKILL, [2])])
def test_a_resume_stopped_during_its_own_validation_resumes_exactly(data, uninterrupted, tmp_path, second, code,
                                                                    logged):
    """The resume's validation of the step is itself stopped (nothing is trained or written, the validation stays
    due) or killed while it copies the step to ``best/`` (the state already records it): a third launch ends like
    the uninterrupted run, no validation record twice."""
    run = tmp_path / "twice"
    cli(*ARGS, "--data", str(data), "--out", str(run), check=False, env={"DEPTHNERF_CRASH_AT": "sigterm-validation@2"})
    again = cli(*ARGS, "--data", str(data), "--out", str(run), "--resume", check=False,
                env={"DEPTHNERF_CRASH_AT": second})
    assert again.returncode == code, again.stderr[-2000:]
    assert ckpt.latest_checkpoint(run / "checkpoints").name == f"step_{2:08d}"
    assert max(m["step"] for m in read_metrics(run)) == 2 and [v[0] for v in validations(run)] == logged
    cli(*ARGS, "--data", str(data), "--out", str(run), "--resume")
    assert validations(run) == validations(uninterrupted)
    assert best_steps(run) == best_steps(uninterrupted)
    assert same_best_weights(run, uninterrupted)
