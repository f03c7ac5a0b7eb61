"""Inference speed policy in one place: device -> autocast dtype, ray chunk, field point chunk, torch.compile.

=================  ==========================  ============================================================
setting            CPU (fp32)                  CUDA
=================  ==========================  ============================================================
field precision    fp32                        bf16 autocast (linears in bf16; residual stream, features'
                                               sampling weights and rgb/sigma fp32); ``--fp32`` turns it off
rays per pass      4096 (``CPU_RAY_CHUNK``)    65536 (``CUDA_RAY_CHUNK``): 4 views of 128x128 per pass, so
                                               the views of one object render in large batches
field points       16,384 per chunk            1,048,576 per chunk (``CUDA_POINT_CHUNK``; bounds memory at
                   (``CPU_POINT_CHUNK``)       about 8 KB per point for the paper's d_hidden 512)
torch.compile      off                         off; ``--compile`` compiles the field MLPs (opt-in; one
                                               H100: 230 -> 91 ms per paper-sampler view, docs/speed.md);
                                               ``--compile-mode`` picks inductor's mode (e.g.
                                               ``max-autotune-no-cudagraphs``: Triton matrix products with
                                               the element-wise work fused into them)
residual stream    fp32                        fp32; ``--bf16-residual`` keeps the MLPs' residual stream in
                                               bf16 (opt-in: half its memory traffic, rounded to bf16)
feature gather     before the MLP call         before the MLP call (``grid_sample``); ``--gather inside``:
                   (``embedding_bag``);        in the MLP forward, so in ``--compile``'s graph;
                   ``--gather`` as on CUDA     ``inside-bf16``: from bf16 maps (opt-in;
                                               :data:`~depthnerf.render.config.GATHERS`)
=================  ==========================  ============================================================

The CUDA values are sized from memory arithmetic; their speed on one H100 is in docs/speed.md ("GPU"), with the
profile that shows what bounds a view (the feature gather and the fields' element-wise work, not the matmuls).
The policy is an argument, never state on the model: every inference path (``depthnerf eval``, ``depthnerf
reconstruct``, the Python API ``Reconstructor``, the demo and the app) gets it from its
:class:`~depthnerf.infer.session.InferenceSession`, which builds it once with :func:`inference_policy` for its
device (``--fp32`` / ``--compile`` / ``--compile-mode`` / ``--bf16-residual`` / ``--gather``), turns it once
into the :class:`~depthnerf.model.pixelnerf.FieldRuntime` its field calls take (:func:`field_runtime`: the
compiled MLP forwards are wrappers that it holds) and renders ``ray_chunk`` rays per pass unless ``--chunk`` says
otherwise.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch

from depthnerf.errors import DepthnerfError
from depthnerf.model.pixelnerf import FieldRuntime, PixelNeRF
from depthnerf.render.config import COMPILE_MODES, GATHERS

CPU_RAY_CHUNK = 4096
"""Rays per render pass on the CPU (the value every CPU figure in docs/speed.md was measured with)."""
CPU_POINT_CHUNK = 16384
"""Field points per MLP call on the CPU at inference. The models' own ``chunk_points`` (4096) is slower with two
threads: one photo (``cpu-cars-sym-pp``, 8 views and a 64-sample mesh) took 6.33 s best, 7.42 median with it
against 5.11 / 5.37 s with 16384 on 2 threads, and 8.24 / 8.34 against 7.81 / 8.21 s on one
(``OMP_NUM_THREADS=N python benchmarks/bench_point_chunk.py --rounds 3``; 32768 was no better on 2 threads and
slower on one)."""
CUDA_RAY_CHUNK = 65536
"""Rays per render pass on CUDA."""
CUDA_POINT_CHUNK = 1 << 20
"""Field points per chunk on CUDA at inference."""


@dataclass(frozen=True)
class InferencePolicy:
    """How a model renders without autograd on a device."""

    autocast: torch.dtype | None
    """Autocast dtype of field queries (None = fp32)."""
    ray_chunk: int
    """Default rays per render pass."""
    point_chunk: int | None
    """Field points per chunk (None = the field config's ``chunk_points``)."""
    compile: bool
    """Field MLPs run through ``torch.compile`` wrappers."""
    compile_mode: str = "default"
    """The wrappers' ``torch.compile`` mode (:data:`COMPILE_MODES`)."""
    residual: torch.dtype | None = None
    """Dtype of the MLPs' residual stream (None: fp32; :attr:`FieldRuntime.residual`)."""
    gather: str = "before"
    """Where the features are gathered (:data:`~depthnerf.render.config.GATHERS`, ``--gather``)."""


def check_precision_flags(device: torch.device | str, *, fp32: bool = False, compile_mode: str | None = None,
                          bf16_residual: bool = False, gather: str = "before") -> None:
    """One line naming the flag when a combination cannot run on ``device`` (``--compile-mode`` not one of
    :data:`COMPILE_MODES`, ``--gather`` not one of :data:`GATHERS`; ``--bf16-residual`` without bf16 autocast: on
    the CPU or with ``--fp32``)."""
    if compile_mode is not None and compile_mode not in COMPILE_MODES:
        raise DepthnerfError(f"--compile-mode must be one of {', '.join(COMPILE_MODES)}, got {compile_mode!r}")
    if gather not in GATHERS:
        raise DepthnerfError(f"--gather must be one of {', '.join(GATHERS)}, got {gather!r}")
    if bf16_residual and torch.device(device).type != "cuda":
        raise DepthnerfError(f"--bf16-residual is a CUDA setting (bf16 autocast); on {torch.device(device).type} "
                             "the fields render in fp32")
    if bf16_residual and fp32:
        raise DepthnerfError("--bf16-residual keeps the residual stream in bf16 under bf16 autocast; "
                             "--fp32 turns autocast off: pass one of them")


def inference_policy(device: torch.device | str, *, fp32: bool = False, compile: bool = False,
                     compile_mode: str | None = None, bf16_residual: bool = False,
                     gather: str = "before") -> InferencePolicy:
    """The policy for ``device`` (see the module table). ``compile_mode`` implies ``compile``, and so does a
    gather ``inside`` the MLP forward (written for inductor: run eagerly it materialises every corner read, slower
    than the gather before it); the flags are checked by :func:`check_precision_flags`."""
    check_precision_flags(device, fp32=fp32, compile_mode=compile_mode, bf16_residual=bf16_residual, gather=gather)
    compile = compile or compile_mode is not None or gather != "before"
    mode = compile_mode or "default"
    if torch.device(device).type == "cuda":
        return InferencePolicy(autocast=None if fp32 else torch.bfloat16, ray_chunk=CUDA_RAY_CHUNK,
                               point_chunk=CUDA_POINT_CHUNK, compile=compile, compile_mode=mode,
                               residual=torch.bfloat16 if bf16_residual else None, gather=gather)
    return InferencePolicy(autocast=None, ray_chunk=CPU_RAY_CHUNK, point_chunk=CPU_POINT_CHUNK, compile=compile,
                           compile_mode=mode, gather=gather)


def field_runtime(model: PixelNeRF, policy: InferencePolicy | None) -> FieldRuntime:
    """What ``model.field`` takes to render under ``policy`` (None: the default runtime, as the model is): its
    autocast dtype, point chunk, residual dtype and where the features are gathered (``policy.gather``: the
    runtime's ``gather_inside`` and ``map_dtype``) and, with ``policy.compile``, ``torch.compile`` wrappers of the
    MLPs' forwards, held by the returned runtime (the modules are not changed). Build it once per model and keep
    it: each wrapper compiles on its first calls."""
    if policy is None:
        return FieldRuntime()
    forwards = {}
    if policy.compile:
        compiled = {id(mlp): torch.compile(mlp.forward, dynamic=True, mode=policy.compile_mode)
                    for mlp in (model.coarse, model.fine) if mlp is not None}
        forwards = {which: compiled[id(model.network(which))] for which in ("coarse", "fine")}
    return FieldRuntime(autocast=policy.autocast, chunk_points=policy.point_chunk, residual=policy.residual,
                        gather_inside=policy.gather != "before",
                        map_dtype=torch.bfloat16 if policy.gather == "inside-bf16" else None, forwards=forwards)
