"""Tiny randomly initialised checkpoints and run folders for export and demo tests (no training, CPU, < 1 s).

:func:`tiny_config` is the ``cpu-<category>`` preset shrunk (resnet18 trunk with 2 feature stages, 2-block MLPs
of width 16, 8 + 4 + 2 samples, ``resolution`` px) with the given depth prior; ``bundled`` uses a tiny random
bundled depth network written by :func:`tiny_bundled`. :func:`tiny_run` writes a run folder the way training
does (``checkpoints/step_*``, ``best``, ``latest``, ``data_card.json``, ``prior.json``). For tests that do train:
:func:`cli` runs ``depthnerf`` in a subprocess (with :data:`TINY_TRAIN_FLAGS` a run takes seconds) and
:func:`final_weights` reads a run's last checkpoint.
"""

from __future__ import annotations

import dataclasses
import json
import os
import subprocess
import sys
from pathlib import Path

import torch

from depthnerf.config_io import apply_overrides, to_dict
from depthnerf.depth.bundled import BundledDepthNet, BundledNetConfig, save_bundled
from depthnerf.model.pixelnerf import PixelNeRF
from depthnerf.train import checkpoint as ckpt
from depthnerf.train.config import TrainConfig, preset, with_prior

TINY_TRAIN_FLAGS = ["--data.resolution", "32", "--data.num_workers", "0", "--model.encoder.backbone", "resnet18",
                    "--model.coarse.d_hidden", "32", "--model.fine.d_hidden", "32", "--render.sampler.n_coarse", "8",
                    "--render.sampler.n_importance", "4", "--render.sampler.n_gaussian", "4",
                    "--schedule.bbox_steps", "3", "--schedule.objects_phase1", "2", "--schedule.objects_phase2", "2",
                    "--schedule.rays_per_object", "32", "--log.log_every", "1", "--no-progress"]
"""``depthnerf train`` flags that shrink the ``cpu-cars`` preset to seconds per run on 32 px data (the training
tests' and ``scripts/determinism_probe.py``'s runs)."""



def cli(*args: str, check: bool = True, env: dict | None = None) -> subprocess.CompletedProcess:
    """``python -m depthnerf ARGS`` with ``env`` added to the environment; with ``check``, an AssertionError
    carrying the end of stderr when it fails."""
    proc = subprocess.run([sys.executable, "-m", "depthnerf", *args], capture_output=True, text=True,
                          env={**os.environ, **(env or {})})
    if check and proc.returncode != 0:
        raise AssertionError(f"depthnerf {' '.join(args)} failed:\n{proc.stderr[-3000:]}")
    return proc


def final_weights(run: Path) -> dict[str, torch.Tensor]:
    """The network weights of a run folder's latest checkpoint."""
    return ckpt.read_weights(ckpt.latest_checkpoint(run / "checkpoints") / "model.safetensors")[0]

def tiny_bundled(path: Path, input_size: int = 16) -> Path:
    """A random bundled depth network small enough for 16 px images."""
    torch.manual_seed(1)
    save_bundled(BundledDepthNet(BundledNetConfig(widths=(8, 8), input_size=input_size, unshuffle=1)), path)
    return path


def tiny_config(category: str, estimator: str, depth_weights: Path | None = None, resolution: int = 16
                ) -> TrainConfig:
    """The shrunken ``cpu-<category>`` preset (see the module docstring)."""
    cfg = with_prior(preset(f"cpu-{category}"), estimator, str(depth_weights) if depth_weights else None)
    return apply_overrides(cfg, [
        "--data.resolution", str(resolution), "--model.encoder.backbone", "resnet18",
        "--model.encoder.num_layers", "2", "--model.encoder.depth_hidden", "8", "--model.encoder.depth_channels", "8",
        "--model.coarse.d_hidden", "16", "--model.coarse.combine_layer", "1", "--model.coarse.n_blocks", "2",
        "--model.fine.d_hidden", "16", "--model.fine.combine_layer", "1", "--model.fine.n_blocks", "2",
        "--render.sampler.n_coarse", "8", "--render.sampler.n_importance", "4", "--render.sampler.n_gaussian", "2"])


def tiny_model(cfg: TrainConfig, seed: int = 0) -> PixelNeRF:
    """A random model of ``cfg`` whose BatchNorm buffers are not the defaults (so a lost buffer shows)."""
    torch.manual_seed(seed)
    model = PixelNeRF(cfg.model, depth_aware=cfg.prior.enabled)
    with torch.no_grad():
        for name, buf in model.named_buffers():
            if name.endswith("running_mean"):
                buf.uniform_(-0.1, 0.1)
            elif name.endswith("running_var"):
                buf.uniform_(0.8, 1.2)
            elif name.endswith("num_batches_tracked"):
                buf.fill_(1234)
    return model.eval()


def save_tiny(path: Path, cfg: TrainConfig, seed: int = 0, step: int = 7) -> Path:
    """A weights file as training writes it (fp32, model config + train config + step)."""
    ckpt.save_weights(path, tiny_model(cfg, seed), to_dict(cfg.model), step=step,
                      extra={"train_config": json.dumps(to_dict(cfg), sort_keys=True)})
    return path


def tiny_run(run: Path, cfg: TrainConfig, seed: int = 0, steps: tuple[int, ...] = (5, 10), best: int | None = 5,
             max_steps: int | None = None) -> Path:
    """A run folder with checkpoints at ``steps`` (different weights each) and ``best`` = the one at ``best``, of a
    run configured for ``max_steps`` (default the last of ``steps``: a finished run)."""
    cfg = dataclasses.replace(cfg, schedule=dataclasses.replace(cfg.schedule, max_steps=max_steps or max(steps)))
    run.mkdir(parents=True)
    for k, step in enumerate(steps):
        model = tiny_model(cfg, seed + k)
        opt = torch.optim.Adam(model.parameters())
        state = ckpt.TrainingState(step=step, best_psnr=10.0 + k)
        path = ckpt.save_checkpoint(run / "checkpoints", model, opt, to_dict(cfg.model), state, keep_last=5,
                                    train_config=to_dict(cfg))
        if step == best:
            ckpt.mark_best(run / "checkpoints", path)
    card = {"generator": "depthnerf-synth-1/test", "category": cfg.data.category, "seed": 0,
            "counts": {"train": 3, "val": 1, "test": 2}, "resolution": cfg.data.resolution,
            "protocol": {"train_views": 50}}
    (run / "data_card.json").write_text(json.dumps({"root": "/data/synth", "category": cfg.data.category,
                                                    "train_objects": 3, "resolution": cfg.data.resolution,
                                                    "dataset_card": card}))
    (run / "prior.json").write_text(json.dumps({"estimator": cfg.prior.estimator, "weights_hash": "ab" * 32,
                                                "licence": "MIT"}))
    return run
