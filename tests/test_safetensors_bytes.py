""":func:`depthnerf.state_dicts.safetensors_bytes`: the same tensors and metadata give the same bytes in every
process (safetensors alone writes its metadata in a per-process hash order), and the file reads back as written."""

from __future__ import annotations

import hashlib
import json
import struct
import subprocess
import sys

import torch
from safetensors.torch import load, safe_open

from depthnerf.state_dicts import safetensors_bytes

WRITE = """
import hashlib, sys, torch
from depthnerf.state_dicts import safetensors_bytes
from safetensors.torch import save
tensors = {"b.weight": torch.arange(6, dtype=torch.float16).reshape(2, 3), "a.bias": torch.ones(5),
           "c.count": torch.tensor(7, dtype=torch.int64)}
meta = {f"key{i}": f"value {i}" for i in range(12)}
print(hashlib.sha256(safetensors_bytes(tensors, meta)).hexdigest(), hashlib.sha256(save(tensors, metadata=meta)).hexdigest())
"""


def test_same_content_same_bytes_in_every_process():
    runs = [subprocess.run([sys.executable, "-c", WRITE], capture_output=True, text=True, check=True).stdout.split()
            for _ in range(4)]
    assert len({ours for ours, _ in runs}) == 1  # (safetensors' own, the second hash, varies: 0.8.0)


def test_the_file_reads_back_as_written(tmp_path):
    tensors = {"w": torch.randn(3, 4), "h": torch.randn(7).half(), "n": torch.tensor([1, 2, 3])}
    meta = {"z": "last", "a": "first", "json": json.dumps({"x": [1, 2]})}
    data = safetensors_bytes(tensors, meta)
    size = struct.unpack("<Q", data[:8])[0]
    assert size % 8 == 0 and list(json.loads(data[8:8 + size])["__metadata__"]) == ["a", "json", "z"]
    back = load(data)
    assert back.keys() == tensors.keys()
    for name, tensor in tensors.items():
        assert back[name].dtype == tensor.dtype and torch.equal(back[name], tensor)
    (tmp_path / "f.safetensors").write_bytes(data)
    with safe_open(tmp_path / "f.safetensors", "pt") as f:
        assert f.metadata() == meta
    assert hashlib.sha256(safetensors_bytes(tensors)).digest() == hashlib.sha256(safetensors_bytes(tensors)).digest()
