"""What README.md and docs/*.md name beyond their command lines (``tests/test_docs_commands.py`` checks those):
links and repository paths resolve, every subcommand has its row in README's "Command reference", every flag of a
subcommand is named where that subcommand is (a doc command of it, or a paragraph or table row that names it), a
default written beside a flag is the parser's, the Python the docs show imports what exists and passes keywords the
API takes, and the paper presets' default data root is the folder the docs pass as ``--data``.

A paragraph names subcommand S when it says ``depthnerf S`` or has a code span that starts with S (`` `S` ``,
`` `S --flag` ``); its section heading counts as part of it. Nothing runs but the parsers and imports.
"""

from __future__ import annotations

import argparse
import ast
import dataclasses
import importlib
import inspect
import re
from functools import cache
from pathlib import Path

import pytest
from test_docs_commands import COMMANDS, DOC_FILES, ROOT, flags

from depthnerf.cli import SUBCOMMANDS, build_parser

USER_DOCS = [ROOT / "README.md", *sorted(p for p in (ROOT / "docs").glob("*.md")
                                        if p.name not in ("RESULTS.md", "speed.md"))]
"""The user documentation (the two lab notebooks are left out: they quote commands as they ran)."""
REPO_PATH = re.compile(r"(?<![\w/.-])((?:depthnerf|tests|scripts|benchmarks|docs|\.ci)/[\w./-]*\w)(?![\w{*<$])")
"""A repository path (one that goes on as a pattern, ``docs/figures/farside_{cars,chairs}.png``, is left out)."""
FENCE = re.compile(r"^\s*```")


def rel(path: Path) -> str:
    return path.relative_to(ROOT).as_posix()


def prose_blocks(text: str) -> list[str]:
    """The doc's paragraphs and table rows, code blocks left out, each with its section heading in front."""
    blocks, current, heading, fenced = [], [], "", False

    def close():
        if current:
            blocks.append(heading + "\n" + "\n".join(current))
            current.clear()
    for line in text.splitlines():
        if FENCE.match(line):
            close()
            fenced = not fenced
        elif fenced:
            continue
        elif line.startswith("#"):
            close()
            heading = line
        elif line.lstrip().startswith("|"):
            close()
            blocks.append(heading + "\n" + line)
        elif not line.strip():
            close()
        else:
            current.append(line)
    close()
    return blocks


@cache
def subparser(name: str) -> argparse.ArgumentParser:
    top = build_parser([name])
    return next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices[name]


def names(block: str, sub: str) -> bool:
    """Whether a paragraph names subcommand ``sub`` (``depthnerf sub`` or a code span starting with it)."""
    flat = re.sub(r"\s*\n\s*", " ", block)
    return bool(re.search(rf"depthnerf {re.escape(sub)}(?![\w-])|`{re.escape(sub)}(?=[` ])", flat))


BLOCKS = {rel(p): prose_blocks(p.read_text()) for p in USER_DOCS}


# --- links and paths ---------------------------------------------------------------------------------------------

def reference_problems(text: str, folder: Path) -> list[str]:
    """Markdown links to local files, and ``depthnerf/``, ``tests/``, ``scripts/``, ``benchmarks/``, ``docs/``
    paths, that do not exist (from the repository root or ``folder``; ``module.function`` counts when the
    module's file does)."""
    missing = []
    for target in re.findall(r"\]\(([^)#\s]+)(?:#[^)]*)?\)", text):
        if not re.match(r"\w+://", target) and not (folder / target).exists():
            missing.append(f"link {target}")
    for path in REPO_PATH.findall(text):
        base = re.sub(r"\.(?!py$|sh$|md$|json$|png$|safetensors$)\w+$", "", path)  # train/batching.check_...
        if not any((where / p).exists() for where in (ROOT, folder) for p in (path, base, base + ".py")):
            missing.append(f"path {path}")
    return missing


@pytest.mark.parametrize("doc", DOC_FILES, ids=rel)
def test_links_and_repository_paths_resolve(doc: Path):
    assert not reference_problems(doc.read_text(), doc.parent), rel(doc)


def test_a_missing_link_or_path_is_caught():
    text = "[page](nothere.md), [ok](training.md), `depthnerf/nothere.py`, `depthnerf/train/batching.check_world_split`"
    assert reference_problems(text, ROOT / "docs") == ["link nothere.md", "path depthnerf/nothere.py"]


# --- subcommands and their flags -----------------------------------------------------------------------------------

def test_every_subcommand_has_a_row_in_readme_command_reference():
    section = (ROOT / "README.md").read_text().split("## Command reference", 1)[1].split("\n## ", 1)[0]
    rows = {m[1] for m in re.finditer(r"^\| `depthnerf ([\w-]+)", section, re.M)}
    assert rows == set(SUBCOMMANDS)


def undocumented_flags(sub: str) -> list[str]:
    """The flags of ``sub`` no doc command of it shows and no paragraph naming it mentions (any alias counts)."""
    shown = {f for c in COMMANDS if c.argv[:2] == ("depthnerf", sub) for f in flags(c.argv[2:])}
    mentioned = " ".join(b for blocks in BLOCKS.values() for b in blocks if names(b, sub))
    missing = []
    for action in subparser(sub)._actions:
        options = [o for o in action.option_strings if o.startswith("--") and o != "--help"]
        if options and not any(o in shown or re.search(rf"(?<![\w-]){re.escape(o)}(?![\w-])", mentioned)
                               for o in options):
            missing.append(options[0])
    return missing


@pytest.mark.parametrize("sub", SUBCOMMANDS)
def test_every_flag_is_documented_where_its_subcommand_is(sub: str):
    assert not undocumented_flags(sub), f"depthnerf {sub}: flags no doc names: {undocumented_flags(sub)}"


def test_an_undocumented_flag_is_caught(monkeypatch):
    import test_docs_references as this

    monkeypatch.setattr(this, "COMMANDS", [])
    monkeypatch.setattr(this, "BLOCKS", {"x.md": ["`depthnerf checkpoints` lists them"]})
    assert undocumented_flags("checkpoints") == ["--json"]
    monkeypatch.setattr(this, "BLOCKS", {"x.md": ["`depthnerf checkpoints --json` lists them"]})
    assert undocumented_flags("checkpoints") == []


def test_a_flag_mentioned_only_beside_another_subcommand_does_not_count():
    """reconstruct's ``--framing`` is not documented by a paragraph about ``depthnerf synth --framing``."""
    assert names("`depthnerf synth --framing legacy` keeps ...", "synth")
    assert not names("`depthnerf synth --framing legacy` keeps ...", "reconstruct")
    assert not names("the `depth-eval` command", "depth") and names("`depth` and `depth-eval`", "depth")


DEFAULT_BESIDE = re.compile(r"`(--[\w-]+)(?: ([^`\s]+))?` \((?:the )?default(?: ([^),;]+))?[),;]")


def stated_defaults() -> list[tuple[str, str, str, tuple[str, ...]]]:
    """(doc, flag, value, subcommands) for each ``--flag`` (default X)`` or ``--flag X`` (the default)`` in a
    paragraph naming subcommands that have that flag."""
    found = []
    for doc, blocks in BLOCKS.items():
        for block in blocks:
            for flag, value_in_span, value_after in DEFAULT_BESIDE.findall(re.sub(r"\s*\n\s*", " ", block)):
                subs = tuple(s for s in SUBCOMMANDS if names(block, s) and flag in subparser(s)._option_string_actions)
                if subs and (value_after or value_in_span).strip():
                    found.append((doc, flag, (value_after or value_in_span).strip(), subs))
    return found


def parser_default(sub: str, flag: str) -> str:
    """The flag's default as a doc writes it (a default filled in later is read from its help: ``default 90``)."""
    action = subparser(sub)._option_string_actions[flag]
    if action.default is argparse.SUPPRESS:
        return re.search(r"default ([^\s,;)]+)", action.help)[1]
    return f"{action.default:g}" if isinstance(action.default, float) else str(action.default)


@pytest.mark.parametrize("doc, flag, value, subs", stated_defaults())
def test_a_default_stated_beside_a_flag_is_the_parsers(doc: str, flag: str, value: str, subs: tuple[str, ...]):
    """A paragraph naming several subcommands with the flag (the app's ``--views`` beside ``reconstruct``'s) needs
    the value to be one of theirs."""
    defaults = {sub: parser_default(sub, flag) for sub in subs}
    assert value in defaults.values(), f"{doc}: {flag} (default {value}); the parsers': {defaults}"


def test_stated_defaults_are_found_and_a_wrong_one_is_caught(monkeypatch):
    import test_docs_references as this

    assert {(f, v) for _, f, v, _ in stated_defaults()} >= {("--views", "36"), ("--elevation", "20")}
    monkeypatch.setattr(this, "BLOCKS", {"x.md": ["`depthnerf reconstruct`: `--views` (default 12), `--facing 90`"
                                                  " (the default)"]})
    assert stated_defaults() == [("x.md", "--views", "12", ("reconstruct",)),
                                 ("x.md", "--facing", "90", ("reconstruct",))]
    assert [parser_default("reconstruct", f) for f in ("--views", "--facing")] == ["36", "90"]


# --- Python ------------------------------------------------------------------------------------------------------

def python_blocks() -> list[tuple[str, str]]:
    found = []
    for doc in USER_DOCS:
        for number, block in enumerate(re.findall(r"```python\n(.*?)```", doc.read_text(), re.S)):
            found.append((f"{rel(doc)}#{number}", block))
    return found


def keyword_calls(tree: ast.AST) -> list[tuple[str, list[str]]]:
    """(called name, keyword names) for every call in ``tree``."""
    calls = []
    for node in ast.walk(tree):
        if isinstance(node, ast.Call):
            func = node.func.attr if isinstance(node.func, ast.Attribute) else getattr(node.func, "id", "")
            calls.append((func, [k.arg for k in node.keywords if k.arg]))
    return calls


def accepted_keywords() -> dict[str, set[str]]:
    """The keywords each public call the docs show takes."""
    from depthnerf import Reconstructor
    from depthnerf.infer.session import SessionOptions
    from depthnerf.reconstruct.reconstructor import ReconstructConfig

    def params(fn) -> set[str]:
        return set(inspect.signature(fn).parameters) - {"self", "cls", "options"}
    options = {f.name for f in dataclasses.fields(SessionOptions)}
    return {"ReconstructConfig": {f.name for f in dataclasses.fields(ReconstructConfig)},
            "from_pretrained": params(Reconstructor.from_pretrained) | options,
            "reconstruct": params(Reconstructor.reconstruct), "save": params(Reconstructor.save)}


def python_problems(code: str) -> list[str]:
    """Names a doc's Python imports from depthnerf that do not exist, and keywords its calls pass that the API
    does not take."""
    tree, found, accepted = ast.parse(code), [], accepted_keywords()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom) and (node.module or "").split(".")[0] == "depthnerf":
            module = importlib.import_module(node.module)
            found += [f"{node.module}.{a.name}" for a in node.names if not hasattr(module, a.name)]
    for func, keywords in keyword_calls(tree):
        found += [f"{func}({k}=)" for k in keywords if k not in accepted.get(func, set(keywords))]
    return found


@pytest.mark.parametrize("where, code", python_blocks(), ids=[w for w, _ in python_blocks()])
def test_python_blocks_import_what_exists_and_pass_keywords_the_api_takes(where: str, code: str):
    assert not python_problems(code), where


def test_a_wrong_python_block_is_caught():
    code = ("from depthnerf import Reconstructor, Reconstructer\n"
            "rec = Reconstructor.from_pretrained('cpu-cars-sym-pp', fp16=True, chunk=4096)\n"
            "rec.reconstruct('car.png', config=ReconstructConfig(views=8, mesh_res=64))\n")
    assert sorted(python_problems(code)) == ["ReconstructConfig(mesh_res=)", "depthnerf.Reconstructer",
                                             "from_pretrained(fp16=)"]


def test_inline_api_keywords_exist():
    """``ReconstructConfig(a=..., b=...)`` spans, and ``name=value`` spans in a paragraph about
    ``from_pretrained`` (its session options), name fields that exist."""
    accepted, bad = accepted_keywords(), []
    for doc, blocks in BLOCKS.items():
        for block in blocks:
            flat = re.sub(r"\s*\n\s*", " ", block)
            for args in re.findall(r"ReconstructConfig\(([^)`]*)\)", flat):
                bad += [f"{doc}: ReconstructConfig({k}=)" for k in re.findall(r"(\w+)=", args)
                        if k not in accepted["ReconstructConfig"]]
            if "from_pretrained" in flat:
                bad += [f"{doc}: from_pretrained({k}=)" for k in re.findall(r"`([a-z_]\w*)=[^`]*`", flat)
                        if k not in accepted["from_pretrained"] | accepted["ReconstructConfig"]]
    assert not bad


# --- defaults the docs rely on ---------------------------------------------------------------------------------------

def test_paper_presets_default_to_the_data_root_the_docs_pass():
    """README's "Data layout": one folder holds ``cars_*`` and ``chairs_*``; every paper-preset command passes it."""
    from depthnerf.train.config import preset

    roots = {c.argv[c.argv.index("--data") + 1] for c in COMMANDS if c.argv[:2] == ("depthnerf", "train")
             and "--data" in c.argv and any(w.startswith("paper-") for w in c.argv)}
    assert roots and {preset(f"paper-{cat}").data.root for cat in ("cars", "chairs")} == roots
