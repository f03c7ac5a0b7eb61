"""Multi-process training and evaluation (2 gloo processes on the CPU, launched by hand: ``RANK`` /
``WORLD_SIZE`` / ``MASTER_ADDR`` / ``MASTER_PORT``, so each process can get its own crash hook).

BatchNorm running statistics (what evaluation normalises with) must not depend on the number of ranks: 2 ranks x
1 object per step equal 1 process x 2 objects to float rounding (DDP alone kept rank 0's, of its share only:
resuming a run with another world size moved evaluation by 0.25 dB). A rank that stops (killed, or its own error)
must stop the other rank with one line, not a gloo traceback.
"""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from fixtures_checkpoints import TINY_TRAIN_FLAGS as TINY
from fixtures_checkpoints import save_tiny, tiny_config
from fixtures_srn import make_srn_fixture

from depthnerf.distributed import DistInfo, peer_failure
from depthnerf.errors import DepthnerfError
from depthnerf.train import checkpoint as ckpt

ROOT = Path(__file__).resolve().parent.parent


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def two_ranks(args: list[str], env: tuple[dict, dict] = ({}, {}), launch: tuple[str, ...] = ("-m", "depthnerf")
              ) -> list[subprocess.CompletedProcess]:
    """``python -m depthnerf ARGS`` as ranks 0 and 1 of one gloo job (``env``: each rank's extra variables;
    ``launch``: what runs instead of ``-m depthnerf``)."""
    port = str(free_port())
    procs = [subprocess.Popen([sys.executable, *launch, *map(str, args)], cwd=ROOT, text=True,
                              stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                              env={**os.environ, "OMP_NUM_THREADS": "1", "PYTHONPATH": str(ROOT), "RANK": str(r),
                                   "LOCAL_RANK": str(r), "WORLD_SIZE": "2", "LOCAL_WORLD_SIZE": "2",
                                   "MASTER_ADDR": "127.0.0.1", "MASTER_PORT": port, **env[r]})
             for r in (0, 1)]
    outs = []
    for p in procs:
        out, err = p.communicate(timeout=120)  # a hang fails the test
        outs.append(subprocess.CompletedProcess(p.args, p.returncode, out, err))
    return outs


def error_lines(stderr: str) -> list[str]:
    return [line for line in stderr.splitlines() if line.strip() and "Warning" not in line
            and not line.startswith(("started a new run", "  "))]


@pytest.fixture(scope="module")
def data(tmp_path_factory) -> Path:
    return make_srn_fixture(tmp_path_factory.mktemp("srn"), "cars", {"train": 4, "test": 3}, views=4, size=32)


def train_args(data: Path, out: Path) -> list[str]:
    return ["train", "--preset", "cpu-cars", "--depth", "none", "--data", data, "--max-steps", "2",
            "--log.val_every", "0", "--device", "cpu", *TINY, "--schedule.step_shape", "per-object", "--out", out]


def test_batchnorm_statistics_of_two_ranks_equal_one_process(data, tmp_path):
    single = subprocess.run([sys.executable, "-m", "depthnerf", *map(str, train_args(data, tmp_path / "one"))],
                            cwd=ROOT, capture_output=True, text=True, env={**os.environ, "OMP_NUM_THREADS": "1"})
    assert single.returncode == 0, single.stderr[-2000:]
    ranks = two_ranks(train_args(data, tmp_path / "two"))
    assert all(r.returncode == 0 for r in ranks), ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    one, two = (ckpt.read_weights(ckpt.latest_checkpoint(tmp_path / run / "checkpoints") / "model.safetensors")[0]
                for run in ("one", "two"))
    stats = [k for k in one if "running_" in k or "num_batches" in k]
    assert stats
    for key in stats:  # before: rank 0's share alone (20-80% apart, half the update count)
        assert torch.allclose(one[key].double(), two[key].double(), rtol=1e-5, atol=1e-6), key


def test_a_killed_rank_stops_the_other_training_rank_with_one_line(data, tmp_path):
    rank0, rank1 = two_ranks(train_args(data, tmp_path / "run"), env=({}, {"DEPTHNERF_CRASH_AT": "step@1"}))
    assert rank1.returncode == -9
    assert rank0.returncode == 2, rank0.stderr[-2000:]
    lines = error_lines(rank0.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: rank 0 of 2: another rank stopped while this one was "
                                                   "training"), rank0.stderr[-2000:]


def test_a_killed_rank_stops_the_other_evaluating_rank_with_one_line(data, tmp_path):
    weights = save_tiny(tmp_path / "tiny.safetensors", tiny_config("cars", "none", resolution=16))
    args = ["eval", "--checkpoint", weights, "--data", data, "--no-mesh", "--no-progress", "--device", "cpu",
            "--out", tmp_path / "eval"]
    rank0, rank1 = two_ranks(args, env=({"DEPTHNERF_CRASH_AT": "eval-object@1"}, {}))
    assert rank0.returncode == -9
    assert rank1.returncode == 2, rank1.stderr[-2000:]
    lines = error_lines(rank1.stderr)
    assert len(lines) == 1 and lines[0].startswith("error: rank 1 of 2: another rank stopped while this one was "
                                                   "evaluating"), rank1.stderr[-2000:]


def test_peer_failure_turns_only_backend_failures_into_one_line():
    info = DistInfo(rank=1, world=2, device=torch.device("cpu"))
    gloo = ("[/pytorch/third_party/gloo/gloo/transport/tcp/pair.cc:561] Connection closed by peer [127.0.0.1]:1. "
            "This is typically caused by a remote worker crashing.")
    with pytest.raises(DepthnerfError, match=r"^rank 1 of 2: .* \(Connection closed by peer \[127.0.0.1\]:1\)$"):
        with peer_failure(info, "training"):
            raise RuntimeError(gloo)
    with pytest.raises(RuntimeError, match="a bug"):  # not a backend's failure: the traceback stays
        with peer_failure(info, "training"):
            raise RuntimeError("a bug")
    with pytest.raises(RuntimeError, match="gloo"):  # one process: nothing to blame on another rank
        with peer_failure(DistInfo(rank=0, world=1, device=torch.device("cpu")), "training"):
            raise RuntimeError(gloo)


def all_error_lines(ranks: list[subprocess.CompletedProcess]) -> list[tuple[int, str]]:
    """Every ``error:`` line of the ranks' combined output, with the rank that printed it."""
    return [(r, line) for r, done in enumerate(ranks) for line in (done.stdout + done.stderr).splitlines()
            if line.startswith("error:")]


@pytest.mark.parametrize(("flags", "said"), [
    (["--max-steps", "x"], "error: depthnerf train: argument --max-steps: invalid int value: 'x'"),  # the parser's
    (["--schedule.lr", "inf"], "error: --schedule.lr must be a finite number, got inf"),  # the config's
    (["--schedule.rays_per_object", "1000000000000"], "error: --schedule.objects_phase1 2 objects (1 per rank; one "
                                                      "at a time: --schedule.step_shape per-object) x "
                                                      "--schedule.rays_per_object 1000000000000 rays"),  # agreed
    (["--data", "MISSING"], "error: "),  # the data's, agreed by the ranks after the process group started
])
def test_a_refusal_every_rank_reaches_is_printed_once(data, tmp_path, flags, said):
    """Two ranks refusing alike (a bad flag or value, settings no step can hold, missing data) print one line, rank
    0's, and both exit 2 (each rank printed it: the line twice)."""
    flags = [str(tmp_path / "missing") if f == "MISSING" else f for f in flags]
    ranks = two_ranks([*train_args(data, tmp_path / "run"), *flags])
    assert [r.returncode for r in ranks] == [2, 2], ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    lines = all_error_lines(ranks)
    assert len(lines) == 1 and lines[0][0] == 0 and lines[0][1].startswith(said), lines
    assert not any("Traceback" in r.stderr for r in ranks)


OOM_ON_RANK_1 = """
import os, sys
from depthnerf.cli import main
import torch
import depthnerf.train.loop as loop

def out_of_memory(*args, **kwargs):
    raise torch.OutOfMemoryError("CUDA out of memory. Tried to allocate 2.00 GiB. GPU 1 has a total capacity of 8 GiB")

if os.environ["RANK"] == "1":
    loop.train_step = out_of_memory
sys.exit(main(sys.argv[1:]))
"""


def test_out_of_memory_on_one_rank_is_printed_by_that_rank(data, tmp_path):
    """A failure of one rank alone (out of memory in its step) is still that rank's line, naming it; the other rank
    says it stopped because another did."""
    ranks = two_ranks(train_args(data, tmp_path / "run"), launch=("-c", OOM_ON_RANK_1))
    assert [r.returncode for r in ranks] == [2, 2], ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    lines = dict(all_error_lines(ranks))
    assert len(all_error_lines(ranks)) == 2, lines
    assert lines[1].startswith("error: rank 1 of 2: out of memory on cpu (could not allocate 2.00 GiB) at training "
                               "step 0: a step renders --schedule.objects_phase1 2 objects (1 per rank; one at a "
                               "time: --schedule.step_shape per-object) x --schedule.rays_per_object 32 rays"), lines
    assert lines[0].startswith("error: rank 0 of 2: another rank stopped while this one was training"), lines


FAILS_ON_RANK_1 = """
import os, sys
from depthnerf.cli import main
from depthnerf.errors import DepthnerfError
import depthnerf.reconstruct.exports as exports

def full(out, overwrite=False):
    raise DepthnerfError(f"{out}: cannot write the output folder (No space left on device)")

def unreadable(self, record):
    raise DepthnerfError(f"{record.path}: rgb/000000.png: unreadable image (truncated)")

if os.environ["RANK"] == "1":
    if os.environ["FAIL"] == "out":
        exports.check_output_dir = full
    else:
        import depthnerf.eval.protocol as protocol
        protocol._Evaluator.__call__ = unreadable
sys.exit(main(sys.argv[1:]))
"""


@pytest.fixture(scope="module")
def tiny_weights(tmp_path_factory) -> Path:
    return save_tiny(tmp_path_factory.mktemp("tiny") / "tiny.safetensors", tiny_config("cars", "none", resolution=16))


def eval_args(weights: Path, data: Path, out: Path) -> list:
    return ["eval", "--checkpoint", weights, "--data", data, "--no-mesh", "--no-progress", "--device", "cpu",
            "--out", out]


@pytest.mark.parametrize(("bad", "said"), [
    ({"--pixel-center": "2"}, "error: --pixel-center must be in [0, 1)"),  # a flag beyond the parser's
    ({"--checkpoint": "MISSING/none.safetensors"}, "error: MISSING/none.safetensors"),  # agreed by the ranks
    ({"--out": "FILE"}, "error: FILE: --out is a file, not a folder"),
    ({"--data": "MISSING"}, "error: MISSING"),  # the data's, checked in the protocol
    ({"--device": "meta"}, "error: --device meta: choose auto, cpu, cuda or cuda:N"),  # before the process group
])
def test_an_eval_refusal_every_rank_reaches_is_printed_once(data, tiny_weights, tmp_path, bad, said):
    """Two evaluating ranks refusing alike (a flag, a checkpoint that is not there, a file as --out, missing data,
    a device) print one line, rank 0's, and both exit 2 (each rank printed it: the line twice)."""
    (tmp_path / "file").write_text("x")

    def placed(text: str) -> str:
        return text.replace("MISSING", str(tmp_path / "missing")).replace("FILE", str(tmp_path / "file"))

    args = [str(a) for a in eval_args(tiny_weights, data, tmp_path / "eval")]
    for flag, value in bad.items():  # the later of two equal flags wins
        args += [flag, placed(value)]
    ranks = two_ranks(args)
    assert [r.returncode for r in ranks] == [2, 2], ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    lines = all_error_lines(ranks)
    expected = placed(said)
    assert len(lines) == 1 and lines[0][0] == 0 and lines[0][1].startswith(expected), lines
    assert not any("Traceback" in r.stderr for r in ranks)


def test_an_eval_failure_of_one_rank_alone_is_printed(data, tiny_weights, tmp_path):
    """Rank 1 alone cannot write the output folder (its own disk): an agreed check, printed once, naming rank 1.
    Rank 1 alone fails while scoring: its own line, and rank 0 says another rank stopped."""
    args = eval_args(tiny_weights, data, tmp_path / "eval")
    ranks = two_ranks(args, env=({"FAIL": "out"}, {"FAIL": "out"}), launch=("-c", FAILS_ON_RANK_1))
    assert [r.returncode for r in ranks] == [2, 2], ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    lines = all_error_lines(ranks)
    assert lines == [(0, f"error: {tmp_path / 'eval'}: cannot write the output folder (No space left on device) "
                         "(rank 1)")], lines
    ranks = two_ranks(args, env=({"FAIL": "scoring"}, {"FAIL": "scoring"}), launch=("-c", FAILS_ON_RANK_1))
    assert [r.returncode for r in ranks] == [2, 2], ranks[0].stderr[-2000:] + ranks[1].stderr[-2000:]
    lines = dict(all_error_lines(ranks))
    assert len(all_error_lines(ranks)) == 2 and lines[1].endswith("rgb/000000.png: unreadable image (truncated)")
    assert lines[0].startswith("error: rank 0 of 2: another rank stopped while this one was evaluating"), lines
