"""``--schedule.freeze``: parameters held fixed in training, their modules in evaluation mode."""

from __future__ import annotations

import os
import subprocess
import sys

import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_checkpoints import cli, final_weights, tiny_config, tiny_model
from fixtures_srn import make_srn_fixture

from depthnerf.errors import DepthnerfError
from depthnerf.train.freeze import freeze_parameters, hold_frozen_modules, trainable_parameters


def test_a_prefix_freezes_exactly_the_parameters_under_it_at_a_dot_boundary():
    model = tiny_model(tiny_config("cars", "none"))
    names = [n for n, _ in model.named_parameters()]
    frozen = freeze_parameters(model, ["encoder", "fine.lin_out"])
    want = [n for n in names if n.startswith("encoder.") or n.startswith("fine.lin_out.")]
    assert frozen == want and want
    assert [n for n, p in model.named_parameters() if not p.requires_grad] == want
    assert [id(p) for p in trainable_parameters(model)] == [id(p) for n, p in model.named_parameters()
                                                             if n not in want]


@pytest.mark.parametrize("prefixes, message", [
    (["fine.lin"], "'fine.lin' names no parameter of this model"),  # a dot boundary: not fine.lin_out, fine.lin_z
    (["encodr"], "'encodr' names no parameter"),
    (["encoder", "coarse", "fine"], "freezes every parameter: nothing would train"),
])
def test_a_prefix_that_names_nothing_or_everything_is_one_line_and_changes_nothing(prefixes, message):
    model = tiny_model(tiny_config("cars", "none"))
    with pytest.raises(DepthnerfError, match=message):
        freeze_parameters(model, prefixes)
    assert all(p.requires_grad for p in model.parameters())


def test_a_frozen_encoder_runs_on_its_running_statistics_and_leaves_them_unchanged():
    """After ``model.train()``, :func:`hold_frozen_modules` switches the frozen encoder (and every module inside it)
    to evaluation mode: a training-mode forward gives the evaluation features and updates no BatchNorm statistic;
    the trainable fields stay in training mode."""
    model = tiny_model(tiny_config("cars", "none"))
    freeze_parameters(model, ["encoder"])
    model.train()
    assert hold_frozen_modules(model) >= 1
    assert not any(m.training for m in model.encoder.modules())
    assert model.training and model.fine.training and model.coarse.training
    before = {k: v.clone() for k, v in model.encoder.state_dict().items()}
    images = torch.rand(2, 3, 32, 32)
    trained = model.encoder(images, None, objects=2)
    assert all(torch.equal(before[k], v) for k, v in model.encoder.state_dict().items())
    with torch.no_grad():
        torch.testing.assert_close(trained, model.eval().encoder(images, None, objects=2), rtol=0, atol=0)


def test_training_with_a_frozen_encoder_keeps_it_bit_for_bit_and_resumes_exactly(tmp_path):
    """A run with ``--schedule.freeze encoder`` (validation included, which must not switch the encoder back to
    training mode) ends with the encoder's weights and running statistics of its ``--init-from`` start bit for bit
    and the fields changed; killed after its first checkpoint and resumed, it ends where the uninterrupted run
    does; a prefix naming nothing is one line, exit 2."""
    data = make_srn_fixture(tmp_path / "srn", "cars", {"train": 3, "val": 1}, views=4, size=32, with_mask=True)
    start = tmp_path / "start"
    cli("train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--out", str(start),
        "--max-steps", "2", "--log.val_every", "0", *TINY)
    args = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--init-from", str(start),
            "--schedule.freeze", "encoder", "--max-steps", "4", "--checkpoint-every", "2", "--log.val_every", "2",
            "--log.val_views", "1", *TINY]
    full = tmp_path / "full"
    said = cli(*args, "--out", str(full)).stderr
    assert "frozen (--schedule.freeze encoder):" in said
    first, last = final_weights(start), final_weights(full)
    encoder = [k for k in first if k.startswith("encoder.")]
    assert any("running_mean" in k for k in encoder)
    assert all(torch.equal(first[k], last[k]) for k in encoder)
    assert any(not torch.equal(first[k], last[k]) for k in first if k.startswith("fine."))
    part = tmp_path / "part"
    cli(*args, "--out", str(part), "--max-steps", "2")
    cli(*args, "--out", str(part), "--resume")
    again = final_weights(part)
    assert all(torch.equal(last[k], again[k]) for k in last)
    bad = cli(*args, "--out", str(tmp_path / "bad"), "--schedule.freeze", "encoder.nothing", check=False)
    assert bad.returncode == 2 and "'encoder.nothing' names no parameter" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1


@pytest.mark.slow
def test_two_process_ddp_with_a_frozen_encoder_keeps_it_bit_for_bit(tmp_path):
    """Under torchrun (gloo, 2 CPU processes) the frozen encoder is left out of DDP's gradient reduction and of the
    BatchNorm merge's updates: its weights and running statistics end as the ``--init-from`` start had them, and
    the fields train."""
    data = make_srn_fixture(tmp_path / "srn", "cars", {"train": 4, "val": 1}, views=4, size=32, with_mask=True)
    start = tmp_path / "start"
    base = ["train", "--preset", "cpu-cars", "--depth", "none", "--data", str(data), "--log.val_every", "0",
            "--device", "cpu", *TINY]
    cli(*base, "--max-steps", "2", "--out", str(start))
    ddp = tmp_path / "ddp"
    proc = subprocess.run([sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node=2",
                           "-m", "depthnerf", *base, "--max-steps", "3", "--init-from", str(start),
                           "--schedule.freeze", "encoder", "--out", str(ddp)], capture_output=True, text=True,
                          env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert proc.returncode == 0, proc.stderr[-3000:]
    first, last = final_weights(start), final_weights(ddp)
    assert all(torch.equal(first[k], last[k]) for k in first if k.startswith("encoder."))
    assert any(not torch.equal(first[k], last[k]) for k in first if k.startswith("fine."))
