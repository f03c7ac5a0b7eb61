"""Every ``--device`` flag (eval, train, reconstruct, demo, app, depth, depth-eval) and the Python API's ``device``
go through one check (:func:`depthnerf.distributed.pick_device`): a device this process cannot use (another device
type, CUDA without a GPU, ``cuda:N`` past the GPUs it sees) is one line naming the flag and what there is, before
anything loads, not a traceback from the first tensor moved there. Under torchrun it is printed once.

CUDA is simulated (``torch.cuda.is_available`` / ``device_count`` monkeypatched), so these run on a CPU-only
machine; nothing here touches a GPU.
"""

from __future__ import annotations

import importlib.util

import pytest
import torch

from depthnerf.cli import main
from depthnerf.distributed import pick_device, setup
from depthnerf.errors import DepthnerfError, RefusedOnMain
from depthnerf.infer.session import SessionOptions
from depthnerf.pretrained.load import load_pretrained


def gpus(monkeypatch, count: int) -> None:
    """Make torch report ``count`` CUDA devices (none: CUDA unavailable)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: count > 0)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: count)


def test_what_worked_keeps_working(monkeypatch):
    gpus(monkeypatch, 1)
    assert pick_device("cpu") == torch.device("cpu")
    assert pick_device("cuda") == torch.device("cuda")  # as given: torch's current GPU
    assert pick_device("cuda:0") == torch.device("cuda", 0)
    assert pick_device("auto") == torch.device("cuda")
    assert pick_device("cuda", local_rank=0) == pick_device("auto", local_rank=0) == torch.device("cuda", 0)
    assert pick_device(torch.device("cuda", 0), flag="device", auto=False) == torch.device("cuda", 0)
    gpus(monkeypatch, 0)
    assert pick_device("auto") == pick_device("cpu") == torch.device("cpu")


@pytest.mark.parametrize("name, said", [
    ("cuda:3", "--device cuda:3: this machine has 1 visible CUDA device (cuda:0)"),
    ("cuda:1", "--device cuda:1: this machine has 1 visible CUDA device (cuda:0)"),
    ("meta", "--device meta: choose auto, cpu, cuda or cuda:N"),
    ("mps", "--device mps: choose auto, cpu, cuda or cuda:N"),
    ("xla", "--device xla: choose auto, cpu, cuda or cuda:N"),
    ("cuda:-1", "--device cuda:-1: choose auto, cpu, cuda or cuda:N"),
    ("gpu 0", "--device 'gpu 0': choose auto, cpu, cuda or cuda:N"),
])
def test_a_device_this_process_cannot_use_is_one_line(monkeypatch, name, said):
    """``cuda:3`` on a one-GPU machine and ``meta`` / ``mps`` / ``xla`` were accepted, and failed later as a
    traceback (the first tensor moved there, or a meta tensor's missing data)."""
    gpus(monkeypatch, 1)
    with pytest.raises(DepthnerfError) as caught:
        pick_device(name)
    assert str(caught.value) == said


def test_the_visible_gpus_are_listed_and_no_gpu_is_said(monkeypatch):
    gpus(monkeypatch, 2)
    with pytest.raises(DepthnerfError, match=r"^--device cuda:2: this machine has 2 visible CUDA devices "
                                             r"\(cuda:0, cuda:1\)$"):
        pick_device("cuda:2")
    gpus(monkeypatch, 8)
    with pytest.raises(DepthnerfError, match=r"8 visible CUDA devices \(cuda:0 to cuda:7\)$"):
        pick_device("cuda:8")
    gpus(monkeypatch, 0)
    for name in ("cuda", "cuda:0", "cuda:3"):
        with pytest.raises(DepthnerfError, match=rf"^--device {name}: no CUDA GPU is available to this process "
                                                 r"\(torch.cuda.is_available\(\) is False\); use --device cpu$"):
            pick_device(name)


def test_the_python_api_refuses_the_same_way(monkeypatch):
    """``SessionOptions`` and ``load_pretrained`` (the app's model cache loads through it) take no ``auto``."""
    gpus(monkeypatch, 1)
    for make in (lambda d: SessionOptions(device=d), lambda d: load_pretrained("no-such-checkpoint", d)):
        with pytest.raises(DepthnerfError, match=r"^device cuda:3: this machine has 1 visible CUDA device"):
            make("cuda:3")
        with pytest.raises(DepthnerfError, match=r"^device meta: choose cpu, cuda or cuda:N$"):
            make("meta")


def _argv(command: str, tmp_path) -> list[str] | None:
    """The least command line of ``command`` that gets as far as its device (None: not installed here)."""
    (tmp_path / "photo.png").write_bytes(b"")
    return {"eval": ["eval", "--checkpoint", "no-such", "--out", str(tmp_path / "eval")],
            "train": ["train", "--data", str(tmp_path), "--out", str(tmp_path / "run")],
            "reconstruct": ["reconstruct", str(tmp_path / "photo.png"), "--checkpoint", "no-such", "--out",
                            str(tmp_path / "rec")],
            "demo": ["demo", "--out", str(tmp_path / "demo")],
            "app": ["app", "--port", "7987"] if importlib.util.find_spec("gradio") else None,
            "depth": ["depth", "--data", str(tmp_path), "--depth", "bundled"],
            "depth-eval": ["depth-eval", "--data", str(tmp_path), "--depth", "bundled"]}[command]


@pytest.mark.parametrize("command", ["eval", "train", "reconstruct", "demo", "app", "depth", "depth-eval"])
@pytest.mark.parametrize("device, said", [
    ("cuda:3", "error: --device cuda:3: this machine has 1 visible CUDA device (cuda:0)"),
    ("meta", "error: --device meta: choose auto, cpu, cuda or cuda:N"),
])
def test_every_device_flag_is_checked_before_anything_loads(monkeypatch, tmp_path, capsys, command, device, said):
    """Each command's ``--device`` says so in one line, before its checkpoint, photo or data is read (here none
    of them exists: checked later, the line would be about them)."""
    argv = _argv(command, tmp_path)
    if argv is None:
        pytest.skip("needs the [app] extra")
    gpus(monkeypatch, 1)
    assert main([*argv, "--device", device]) == 2
    err = capsys.readouterr().err
    assert err == said + "\n", err


def test_under_torchrun_a_device_refusal_is_printed_once(monkeypatch):
    """Before the process group starts: a wrong name by rank 0 (every rank alike), a device the machine lacks by
    each machine's LOCAL_RANK 0 (its ranks alike), more processes than GPUs by the first rank without one; the
    others exit without a line (:class:`RefusedOnMain`)."""
    gpus(monkeypatch, 2)

    def refusal(device: str, rank: int, local: int) -> DepthnerfError:
        for name, value in (("WORLD_SIZE", 8), ("RANK", rank), ("LOCAL_RANK", local)):
            monkeypatch.setenv(name, str(value))
        with pytest.raises(DepthnerfError) as caught:
            setup(device)
        return caught.value

    assert type(refusal("meta", 0, 0)) is DepthnerfError
    assert isinstance(refusal("meta", 4, 0), RefusedOnMain)  # another machine's first rank: rank 0 says it
    assert type(refusal("cuda:5", 4, 0)) is DepthnerfError  # each machine says what it lacks
    assert isinstance(refusal("cuda:5", 1, 1), RefusedOnMain)
    first = refusal("cuda", 2, 2)
    assert type(first) is DepthnerfError and str(first) == (
        "--device cuda: LOCAL_RANK 2 has no CUDA device of its own: this machine has 2 visible CUDA devices "
        "(cuda:0, cuda:1); launch at most 2 processes per machine")
    assert isinstance(refusal("auto", 3, 3), RefusedOnMain)
