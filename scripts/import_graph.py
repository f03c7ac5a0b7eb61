"""Check that depthnerf's imports follow the one-way chain of docs/architecture.md; print cycles and back-edges.

    python scripts/import_graph.py            # summary; exit status 1 if any cycle or back-edge
    python scripts/import_graph.py --edges    # also list every stage-crossing edge
    python scripts/import_graph.py --root DIR # check another copy of the package (DIR: a folder named depthnerf)

Every ``import``/``from ... import`` of a ``depthnerf`` module anywhere in a file counts as a dependency (top
level, inside functions and under ``TYPE_CHECKING`` alike: a lazy import is still a dependency) for the stage
check and for cycles. Cycles through runtime imports (everything but ``if TYPE_CHECKING:`` blocks) and cycles that
exist only through annotation imports are listed separately, and both fail the check (a type that two modules
both need belongs in a module below both). Modules are grouped into stages by their first package below
``depthnerf`` (:data:`STAGES`); an edge from a stage to a later one, or between the sibling stages ``train``,
``eval`` and ``reconstruct``, is a back-edge. Cycles are strongly connected components of the module graph
(Tarjan).
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections.abc import Iterable
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent / "depthnerf"

STAGES = {
    "": 0, "errors": 0, "files": 0, "config_io": 0, "cpu_runtime": 0, "distributed": 0,
    "bundles": 0, "hub_access": 0, "state_dicts": 0, "crash_hook": 0, "data": 1, "depth": 2, "model": 3, "render": 4, "pretrained": 5, "infer": 6,
    "train": 7, "eval": 7, "reconstruct": 7,
    "commands": 8, "app": 8, "demo": 8, "cli": 9, "__main__": 9,
}
"""Stage of each top-level module/package of depthnerf: imports go from higher to lower (or equal) stages only;
train, eval and reconstruct share a stage but never import each other."""

SIBLINGS = {"train", "eval", "reconstruct"}
"""Stages that must not import one another."""


def module_name(path: Path, root: Path = ROOT) -> str:
    rel = path.relative_to(root.parent).with_suffix("")
    parts = list(rel.parts)
    if parts[-1] == "__init__":
        parts.pop()
    return ".".join(parts)


def _type_checking(node: ast.AST) -> bool:
    test = getattr(node, "test", None)
    return isinstance(node, ast.If) and (
        (isinstance(test, ast.Name) and test.id == "TYPE_CHECKING")
        or (isinstance(test, ast.Attribute) and test.attr == "TYPE_CHECKING"))


def imports_of(path: Path, name: str, runtime_only: bool = False) -> set[str]:
    """depthnerf modules imported by the file ``path`` (module ``name``); ``runtime_only`` skips imports under
    ``if TYPE_CHECKING:`` (annotations only)."""
    tree = ast.parse(path.read_text(), str(path))
    package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
    found: set[str] = set()
    stack: list[ast.AST] = [tree]
    while stack:
        node = stack.pop()
        if runtime_only and _type_checking(node):
            stack.extend(node.orelse)  # type: ignore[attr-defined]
            continue
        stack.extend(ast.iter_child_nodes(node))
        if isinstance(node, ast.Import):
            found.update(a.name for a in node.names if a.name.split(".")[0] == "depthnerf")
        elif isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")
                base = base[: len(base) - node.level + 1]
                mod = ".".join(base + ([node.module] if node.module else []))
            else:
                mod = node.module or ""
            if mod.split(".")[0] != "depthnerf":
                continue
            found.add(mod)
            found.update(f"{mod}.{a.name}" for a in node.names)  # `from pkg import module`
    return found


def build_graph(root: Path = ROOT, runtime_only: bool = False) -> dict[str, set[str]]:
    """Module -> imported depthnerf modules (only names that are modules of the package)."""
    files = {module_name(p, root): p for p in root.rglob("*.py")}
    graph = {}
    for name, path in files.items():
        graph[name] = {m for m in imports_of(path, name, runtime_only) if m in files and m != name}
    return graph


def stage_of(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def back_edges(graph: dict[str, set[str]]) -> list[tuple[str, str]]:
    """Edges that go against the chain (see :data:`STAGES`)."""
    bad = []
    for src, dsts in graph.items():
        s = stage_of(src)
        for dst in dsts:
            d = stage_of(dst)
            if s == d:
                continue
            if STAGES.get(d, 99) > STAGES.get(s, 99) or (s in SIBLINGS and d in SIBLINGS):
                bad.append((src, dst))
    return sorted(bad)


def cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    on_stack: set[str] = set()
    stack: list[str] = []
    out: list[list[str]] = []
    counter = 0
    for start in sorted(graph):
        if start in index:
            continue
        work: list[tuple[str, Iterable[str]]] = [(start, iter(sorted(graph[start])))]
        index[start] = low[start] = counter
        counter += 1
        stack.append(start)
        on_stack.add(start)
        while work:
            node, it = work[-1]
            advanced = False
            for nxt in it:
                if nxt not in index:
                    index[nxt] = low[nxt] = counter
                    counter += 1
                    stack.append(nxt)
                    on_stack.add(nxt)
                    work.append((nxt, iter(sorted(graph[nxt]))))
                    advanced = True
                    break
                if nxt in on_stack:
                    low[node] = min(low[node], index[nxt])
            if advanced:
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                comp = []
                while True:
                    m = stack.pop()
                    on_stack.discard(m)
                    comp.append(m)
                    if m == node:
                        break
                if len(comp) > 1:
                    out.append(sorted(comp))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--edges", action="store_true", help="list every stage-crossing edge")
    parser.add_argument("--root", type=Path, default=ROOT, help="the package folder to check (default: depthnerf/)")
    args = parser.parse_args(argv)
    graph = build_graph(args.root)
    unknown = sorted({stage_of(m) for m in graph} - set(STAGES))
    found_cycles, found_back = cycles(build_graph(args.root, runtime_only=True)), back_edges(graph)
    annotation_cycles = [c for c in cycles(graph) if c not in found_cycles]
    stage_graph = sorted({(stage_of(s) or "depthnerf", stage_of(d) or "depthnerf")
                          for s, ds in graph.items() for d in ds if stage_of(s) != stage_of(d)})
    print(f"{len(graph)} modules, {sum(map(len, graph.values()))} import edges")
    if args.edges:
        print("stage edges: " + ", ".join(f"{a}->{b}" for a, b in stage_graph))
    print(f"import cycles: {len(found_cycles)}")
    for comp in found_cycles:
        print("  cycle: " + " <-> ".join(comp))
    print(f"annotation-only cycles (through `if TYPE_CHECKING:` imports): {len(annotation_cycles)}")
    for comp in annotation_cycles:
        print("  cycle: " + " <-> ".join(comp))
    print(f"back-edges against the chain: {len(found_back)}")
    for src, dst in found_back:
        print(f"  {src} -> {dst}")
    if unknown:
        print(f"modules in no stage: {', '.join(unknown)}")
    return 1 if found_cycles or annotation_cycles or found_back or unknown else 0


if __name__ == "__main__":
    sys.exit(main())
