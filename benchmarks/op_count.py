"""Counting the aten operators a block of code dispatches, by phase, operator, module, source line and autograd
node: the CPU proxy for CUDA kernel launches of ``benchmarks/bench_gpu.py`` (docs/speed.md, "CPU op-count proxy
for kernel launches")."""

from __future__ import annotations

import sys
from collections import Counter

import torch
from torch.nn.modules.module import register_module_forward_hook, register_module_forward_pre_hook
from torch.optim.optimizer import register_optimizer_step_post_hook, register_optimizer_step_pre_hook
from torch.utils._python_dispatch import TorchDispatchMode

NO_KERNEL = {"_unsafe_view", "empty", "empty_like", "empty_strided", "new_empty", "new_empty_strided",
             "_record_function_enter_new", "_record_function_exit"}
"""aten ops that launch no GPU kernel besides views (``OpOverload.is_view``): allocations, profiler markers."""


class CountOps(TorchDispatchMode):
    """Counts every aten operator dispatched inside the block; with ``breakdown`` also attributes each one to a
    phase (forward, backward: inside the autograd engine, optimiser: inside ``Optimizer.step``), its aten name,
    and where it came from (forward and optimiser: the innermost module and the innermost ``depthnerf`` frame;
    backward: the autograd node running it)."""

    def __init__(self, breakdown: bool = False, names: dict[int, str] | None = None) -> None:
        """``names``: ``id(module)`` -> its qualified name in the model (for the by-module table)."""
        super().__init__()
        self.count = 0
        self.no_kernel = 0
        """Of ``count``: views and allocations (no kernel on a GPU)."""
        self.breakdown = breakdown
        self.names = names or {}
        self.rows: list[tuple] = []  # (phase, aten op, module class, module, source, launches no kernel)
        self._modules: list[str] = []
        self._in_optimiser = False
        self._hooks: list = []

    def __enter__(self):
        if self.breakdown:
            def pre(module, args):
                name = self.names.get(id(module), type(module).__name__)  # e.g. the loss module around the model
                self._modules.append((type(module).__name__, ".".join(name.split(".")[:2])))

            def post(module, args, out):
                self._modules.pop()

            def opt_flag(value):
                def hook(*_):
                    self._in_optimiser = value
                return hook
            self._hooks = [register_module_forward_pre_hook(pre), register_module_forward_hook(post),
                           register_optimizer_step_pre_hook(opt_flag(True)),
                           register_optimizer_step_post_hook(opt_flag(False))]
        return super().__enter__()

    def __exit__(self, *exc):
        for h in self._hooks:
            h.remove()
        self._hooks = []
        return super().__exit__(*exc)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.count += 1
        free = bool(func.is_view or func.overloadpacket.__name__ in NO_KERNEL)
        self.no_kernel += free
        if self.breakdown:
            self.rows.append((*self._attribute(func), free))
        return func(*args, **(kwargs or {}))

    def _attribute(self, func) -> tuple[str, str, str, str, str]:
        op = func.overloadpacket.__name__
        node = torch._C._current_autograd_node()
        if node is not None:
            return "backward", op, "-", "-", node.name()
        phase = "optimiser" if self._in_optimiser else "forward"
        frame, source = sys._getframe(2), "-"
        while frame is not None:
            path = frame.f_code.co_filename.replace("\\", "/")
            if "/depthnerf/" in path and "/torch/" not in path:
                source = f"{path.rsplit('/depthnerf/', 1)[1]}:{frame.f_code.co_name}"
                break
            frame = frame.f_back
        cls, name = self._modules[-1] if self._modules else ("-", "-")
        return phase, op, cls, name, source

    def report(self, top: int) -> None:
        """Print the count by phase, and within each phase by aten op and by origin."""
        phases = Counter(r[0] for r in self.rows)
        views = Counter(r[0] for r in self.rows if r[5])
        print("op count by phase: " + ", ".join(f"{k} {v} ({views[k]} without a kernel)" for k, v in phases.items())
              + f" (total {self.count})")
        for phase in phases:
            rows = [r for r in self.rows if r[0] == phase]
            for title, key in (("aten op", 1), ("module class", 2), ("module", 3), ("source", 4)):
                if phase == "backward" and title.startswith("module"):
                    continue
                if phase == "backward" and title == "source":
                    title = "autograd node"
                counts = Counter(r[key] for r in rows).most_common()
                shown = counts[:top]
                rest = sum(c for _, c in counts[top:])
                print(f"-- {phase}, by {title} ({len(counts)} distinct)")
                for name, c in shown:
                    print(f"  {c:6d}  {name}")
                if rest:
                    print(f"  {rest:6d}  ({len(counts) - top} others)")
