"""Every command line README.md and docs/*.md show parses, and every script, flag and variable they name exists.

Commands come from shell blocks (read as a shell would: ``\\`` lines joined, comments dropped, split on ``;`` ``&&``
``|``, loops, functions and variables expanded) and from inline spans. Nothing runs. ``depthnerf SUB`` (also under
``torchrun -m``): SUB exists, each flag is SUB's spelled in full (argparse would take ``--views`` for
``--views-stride``), the real parser accepts the line, and train's flags and ``--section.field`` overrides resolve
on the preset (``resolve_config``). ``python scripts|benchmarks/X.py``: it exists; where ``parse_args``/``main``
only builds a parser before parsing (checked on its syntax tree), that parser, captured there, accepts the line;
else each ``--flag`` is in its source. ``bash scripts/X.sh``: it exists and reads each variable the doc sets for it.

An upper-case word (``DIR``, ``N``), an unset ``$VAR`` or ``<name>`` is a placeholder: a path stays, a flag with
choices or a type gets a value it takes. An inline span is a fragment: it may leave out required arguments and a
last flag's value, and ``...`` stands for elided words; one with ``[optional]`` parts or ``a|b`` alternatives is a
synopsis: its flags and each alternative are checked, the line is not parsed.
"""

from __future__ import annotations

import argparse
import ast
import contextlib
import dataclasses
import importlib.util
import inspect
import io
import itertools
import re
import shlex
import sys
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from unittest import mock

import pytest

from depthnerf.cli import SUBCOMMANDS, _command_module, build_parser
from depthnerf.errors import DepthnerfError

ROOT = Path(__file__).resolve().parent.parent
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")),
             *sorted((ROOT / "depthnerf" / "checkpoints").rglob("*.md"))]  # the model cards' reproduce commands
SHELL_FENCES = {"", "bash", "sh", "shell", "console"}
INLINE_SPAN = re.compile(r"(?<!`)`((?:[^`\n]|\n(?!\s*\n))+)`(?!`)")  # one paragraph at most
INLINE_START = re.compile(r"^(\w+=(\"[^\"]*\"|\S+) )*(depthnerf |python (scripts|benchmarks)/|bash scripts/)")
ASSIGNMENT = re.compile(r"^[A-Za-z_]\w*=")
PLACEHOLDER = re.compile(r"^([A-Z][A-Z0-9_]*|\$\{?\w+\}?|<[^>]+>)$")
REQUIRED_MISSING = re.compile(r"the following arguments are required|one of the arguments .* is required")
SEPARATORS = {";", "&&", "||", "|", "&"}
ENV_COMMANDS = {"TRAIN_ARGS": "train", "EVAL_ARGS": "eval"}
"""Script variables whose value is extra ``depthnerf`` flags (scripts/run_gpu_study.sh passes them on)."""
NOT_FLAGS = {"--section.field": "README's train synopsis: the override syntax itself, not a field"}
"""Words that look like flags in a doc command but stand for something else, each with the reason."""


@dataclass(frozen=True)
class DocCommand:
    """One command line a doc shows, from ``depthnerf``/``python``/``bash`` on, variables substituted."""

    where: str
    argv: tuple[str, ...]
    env: tuple[str, ...] = ()  # the environment variables the doc sets for it
    fragment: bool = False  # an inline span: may leave out required arguments and a last flag's value
    synopsis: bool = False  # [optional] parts or a|b alternatives: flags and choices checked, not parsed


# --- extraction --------------------------------------------------------------------------------------------------

def doc_commands(text: str, rel: str) -> list[DocCommand]:
    """Every command line of one Markdown file: its shell blocks' and its inline spans' (which may wrap lines)."""
    commands, block, fence, prose = [], None, None, []
    for number, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            if fence is None:
                fence, block = line.strip()[3:].strip(), []
            else:
                commands += block_commands(block, rel) if fence in SHELL_FENCES else []
                fence = None
        elif fence is not None:
            block.append((number, line))
        prose.append(line if fence is None and not line.lstrip().startswith("```") else "")
    prose_text = "\n".join(prose)
    for span in INLINE_SPAN.finditer(prose_text):
        number = prose_text.count("\n", 0, span.start()) + 1
        commands += inline_commands(re.sub(r"\s*\n\s*", " ", span[1]), number, rel)
    return commands


def block_commands(lines: list[tuple[int, str]], rel: str) -> list[DocCommand]:
    """The commands of one shell block (lines numbered), read as a shell would, statefully."""
    shell, commands, start, joined = _Shell(), [], None, ""
    for number, line in lines:
        start = start or number
        if line.rstrip().endswith("\\"):
            joined += line.rstrip()[:-1] + " "
            continue
        lexer = shlex.shlex(re.sub(r"<[^<>]*>", "PLACEHOLDER", joined + line), posix=True, punctuation_chars=True)
        lexer.whitespace_split = True
        for separator, words in itertools.groupby(lexer, key=lambda word: word in SEPARATORS):
            commands += [] if separator else shell.feed(list(words), f"{rel}:{start}")
        start, joined = None, ""
    return commands


@dataclass
class _Shell:
    """What a block has set so far: variables, exported names, enclosing ``for`` loops, functions."""

    variables: dict[str, str] = field(default_factory=dict)
    exported: set[str] = field(default_factory=set)
    loops: list[tuple[str, list[str]]] = field(default_factory=list)
    functions: dict[str, list[str]] = field(default_factory=dict)

    def feed(self, words: list[str], where: str) -> list[DocCommand]:
        words = words[1:] if words[0] == "do" else words  # `for ...; do CMD`
        if words[:1] == ["done"]:
            self.loops.pop()
        if not words or words[0] in ("}", "done"):
            return []
        if words[0] == "for" and len(words) > 2 and words[2] == "in":
            self.loops.append((words[1], words[3:]))
            return []
        if len(words) > 2 and words[1:3] == ["()", "{"]:  # NAME() { BODY "$@"; }
            self.functions[words[0]] = [w for w in words[3:] if w != "$@"]
            return []
        words = self.functions.get(words[0], words[:1]) + words[1:]
        exported = words[0] == "export"
        words = words[1:] if exported else words
        env = dict(w.split("=", 1) for w in itertools.takewhile(ASSIGNMENT.match, words))
        words = words[len(env):]
        if exported or not words:  # `S=study`, `export DEPTH_WEIGHTS=...`
            self.variables.update(env)
            self.exported |= set(env) if exported else set()
            return []
        names = [name for name, _ in self.loops]
        commands = []
        for values in itertools.product(*(values for _, values in self.loops)):
            bound = {**self.variables, **dict(zip(names, values, strict=True))}
            argv = unwrap([substitute(w, bound) for w in words])
            if argv:
                commands.append(DocCommand(where, tuple(argv), tuple(sorted(self.exported | set(env)))))
                commands += [DocCommand(where, ("depthnerf", sub, *shlex.split(substitute(env[name], bound))),
                                        fragment=True) for name, sub in ENV_COMMANDS.items() if name in env]
        return list(dict.fromkeys(commands))


def substitute(word: str, variables: dict[str, str]) -> str:
    """``$NAME`` / ``${NAME}`` replaced where the block set NAME; others stay (a placeholder)."""
    return re.sub(r"\$\{?(\w+)\}?", lambda m: variables.get(m[1], m[0]), word)


def unwrap(argv: list[str]) -> list[str] | None:
    """The command from ``depthnerf``/``python``/``bash`` on (``timeout N``, ``torchrun ... -m``, ``$PY`` and
    ``source`` unwrapped), or None for any other command (``pip``, ``git``, ``python -m pytest``, ...)."""
    while argv:
        if argv[0] == "timeout":
            argv = argv[2:]
        elif argv[0] == "torchrun" or argv[:2] == ["python", "-m"]:
            at = argv.index("-m")
            argv = ["depthnerf", *argv[at + 2:]] if argv[at + 1:at + 2] == ["depthnerf"] else []
        elif argv[0] in ("$PY", "python3", "source", "."):
            argv = ["bash" if argv[0] in ("source", ".") else "python", *argv[1:]]
        else:
            break
    ours = re.match(r"depthnerf \S|python (scripts|benchmarks)/|bash scripts/", " ".join(argv[:2]))
    return argv if ours else None


def inline_commands(span: str, number: int, rel: str) -> list[DocCommand]:
    """The commands of an inline backtick span (a bare ``scripts/X.py --flag`` read as ``python scripts/X.py``);
    none when it shows no command of ours."""
    text = span.strip().replace("\\|", "|")
    if re.match(r"(scripts|benchmarks)/\w+\.(py|sh)( |$)", text):
        text = ("bash " if text.split()[0].endswith(".sh") else "python ") + text
    ours = INLINE_START.match(text)
    if ours and re.search(r"[\[\]{}|]|\(--", text):  # a synopsis
        words = [w for w in re.sub(r"[\[\]()]", " ", text).split() if w != "|"]
        env = [w.split("=")[0] for w in itertools.takewhile(ASSIGNMENT.match, words)]
        return [DocCommand(f"{rel}:{number}", tuple(words[len(env):]), tuple(env), fragment=True, synopsis=True)]
    try:  # any span: `pip install ... && depthnerf demo` shows one too
        return [dataclasses.replace(c, fragment=True) for c in block_commands([(number, text)], rel)]
    except ValueError:  # not shell (an unclosed quote in prose)
        if ours:
            raise
        return []


# --- checks ------------------------------------------------------------------------------------------------------

def problems(command: DocCommand) -> list[str]:
    """What is wrong with one doc command (empty: nothing)."""
    kind, target, *words = command.argv
    if kind == "depthnerf":
        return cli_problems(command)
    path = ROOT / target
    if not path.is_file():
        return [f"no such file {target}"]
    if kind == "bash":  # a name may be built: GPU_CHECK_TIMEOUT_{name.upper()} reads GPU_CHECK_TIMEOUT_BENCH
        source = script_source(path)
        return [f"{target} never reads {name} (the doc sets it)" for name in command.env
                if not re.search(rf"\b{name}\b", source) and not any(re.search(
                    rf"\b{name[:i + 1]}[{{$]", source) for i, c in enumerate(name) if c == "_")]
    if (parser := script_parser(path)) is None:
        return [f"{target} has no flag {flag}" for flag in flags(words)
                if not re.search(rf"(?<![\w-]){re.escape(flag)}(?![\w-])", path.read_text())]
    return parser_problems(parser, words, command, target)


def cli_problems(command: DocCommand) -> list[str]:
    """A ``depthnerf`` command: subcommand, flags, the parse, and train's flags and ``--section.field`` overrides
    resolved on the command's preset as a new run would (an unknown field or a bad value is refused there;
    ``--resume`` off: no run folder is read)."""
    sub, *words = command.argv[1:]
    if sub not in SUBCOMMANDS:
        return [f"depthnerf has no subcommand {sub!r}"]
    top = build_parser(command.argv[1:])
    parser = next(a for a in top._actions if isinstance(a, argparse._SubParsersAction)).choices[sub]
    overrides = getattr(_command_module(sub), "ACCEPTS_OVERRIDES", False)
    name = f"depthnerf {sub}"
    found = parser_problems(parser, words, command, name, overrides, top)
    if overrides and not found and not command.synopsis:
        from depthnerf.commands.train import resolve_config

        words = fill_placeholders(words, parser, command.fragment)
        fields = config_fields()  # an override's placeholder value: the field's default
        words = [fields.get(flag[2:].replace("-", "_"), word) if PLACEHOLDER.match(word) else word
                 for flag, word in zip(["", *words], words, strict=False)]
        args, extra = top.parse_known_args([sub, *words])
        args.overrides, args.resume = extra, False
        try:
            resolve_config(args)
        except DepthnerfError as err:
            found.append(f"{name}: {err}")
    return found


def parser_problems(parser: argparse.ArgumentParser, words: list[str], command: DocCommand, name: str,
                    overrides: bool = False, top: argparse.ArgumentParser | None = None) -> list[str]:
    """Flags ``parser`` lacks (with ``overrides``: that name no config field either); then, for a synopsis,
    alternatives its flags do not take, else what the parser (a subcommand's: through ``top``) says of the line."""
    known = parser._option_string_actions
    found = [f"{name} has no flag {flag}" + (" (and the train config no such field)" if "." in flag else "")
             for flag in flags(words) if flag not in known and flag not in NOT_FLAGS
             and not (overrides and flag[2:].replace("-", "_") in config_fields())]
    if found or command.synopsis:
        return found or synopsis_problems(known, words, name)
    words = fill_placeholders(words, parser, command.fragment)
    error, extra = parse(top or parser, [command.argv[1], *words] if top else words)
    if error and not (command.fragment and REQUIRED_MISSING.search(error)):
        return [error]
    return [f"{name}: unrecognized arguments: {' '.join(extra)}"] if extra and not overrides else []


def synopsis_problems(known: dict[str, argparse.Action], words: list[str], name: str) -> list[str]:
    """Alternatives a synopsis lists for a flag (``--depth none|bundled``, ``--facing DEG|none``) that the flag
    does not take: not one of its choices, or refused by its type."""
    found = []
    for flag, word in zip(words, words[1:], strict=False):
        if (action := known.get(flag)) is None or not re.search(r"[|{]", word):
            continue
        for alt in re.split(r"[|,]", word.strip("{}")):
            if not PLACEHOLDER.match(alt) and stand_in(action, alt) != alt:
                found.append(f"{name} {flag}: it does not take {alt!r}")
    return found


def flags(words: list[str] | tuple[str, ...]) -> list[str]:
    """The option words of a command line (``--a=b`` as ``--a``; negative numbers are values)."""
    return [w.split("=", 1)[0] for w in words if w.startswith("-") and len(w) > 1 and not re.match(r"-[\d.]", w)]


@cache
def config_fields() -> dict[str, str]:
    """The train config's fields as ``--section.field`` overrides name them (``model.mirror``), each with its
    default preset's value as an override would spell it (a stand-in for a placeholder value)."""
    from depthnerf.commands.train import DEFAULT_PRESET
    from depthnerf.config_io import flat_keys
    from depthnerf.train.config import preset

    return {k: str(v) for k, v in flat_keys(dataclasses.asdict(preset(DEFAULT_PRESET))).items()}


def fill_placeholders(words: list[str], parser: argparse.ArgumentParser, fragment: bool) -> list[str]:
    """Placeholders replaced by values their flag takes. An elided word (``...``; in a fragment also a bare
    ``$VAR``, e.g. ``$T`` for some flags) stands for a flag's value after a flag, and is dropped elsewhere; a
    fragment's last flag is given a value when it has none."""
    known = parser._option_string_actions

    def takes_value(word: str) -> bool:  # a flag that needs a value (a --section.field override does)
        action = known.get(word)
        return action.nargs not in (0, "?", "*") if action else bool(re.match(r"--\w+\.", word))
    words = [w for i, w in enumerate(words) if not (w == "..." or fragment and re.fullmatch(r"\$\{?\w+\}?", w))
             or (i and takes_value(words[i - 1]))]
    words += ["VALUE"] if fragment and words and takes_value(words[-1]) else []
    for i in range(1, len(words)):
        action = known.get(words[i - 1])
        if action is not None and (PLACEHOLDER.match(words[i]) or words[i] == "..."):
            words[i] = stand_in(action, words[i])
    return words


def stand_in(action: argparse.Action, word: str) -> str:
    """``word`` where ``action`` takes it, else a value it takes (its first choice, a number), else ``word``."""
    if action.choices:
        return word if word in map(str, action.choices) else str(next(iter(action.choices)))
    for value in (word, "1", "0.5"):
        with contextlib.suppress(Exception):
            (action.type or str)(value)
            return value
    return word


def parse(parser: argparse.ArgumentParser, words: list[str]) -> tuple[str | None, list[str]]:
    """(the parser's error line or None, the words it left over); nothing printed, nothing run."""
    err = io.StringIO()
    with contextlib.redirect_stderr(err), contextlib.redirect_stdout(io.StringIO()):
        try:
            return None, parser.parse_known_args(words)[1]
        except SystemExit as stop:
            return (err.getvalue().strip().splitlines() or ["exit"])[-1] if stop.code else None, []


@cache
def script_parser(path: Path) -> argparse.ArgumentParser | None:
    """The script's parser, captured at its parse call, or None when neither ``parse_args`` nor ``main`` only
    builds a parser first (syntax-checked: calling it would do more)."""
    tree = ast.parse(path.read_text())
    functions = {f.name: f for f in tree.body if isinstance(f, ast.FunctionDef)}
    name = next((n for n in ("parse_args", "main") if n in functions and parses_first(functions[n])), None)
    if name is None:
        return None
    spec = importlib.util.spec_from_file_location(path.stem, path)
    module = importlib.util.module_from_spec(spec)
    sys.modules[path.stem] = module  # dataclasses look their module up there
    with mock.patch.object(sys, "path", [str(path.parent), *sys.path]):
        try:
            spec.loader.exec_module(module)
        except ImportError:  # an optional dependency this machine lacks: the flags are checked on the source
            return None
    function = getattr(module, name)

    class Captured(Exception):  # raised at the parse call; args[0] is the parser
        pass

    def capture(parser, *args, **kwargs):
        raise Captured(parser)

    with mock.patch.object(argparse.ArgumentParser, "parse_args", capture), \
            mock.patch.object(argparse.ArgumentParser, "parse_known_args", capture), \
            mock.patch.object(sys, "argv", [str(path)]):
        try:
            function([]) if inspect.signature(function).parameters else function()
        except Captured as got:
            return got.args[0]
    return None


def parses_first(function: ast.FunctionDef) -> bool:
    """True when ``function`` only imports and builds an argparse parser before its first parse call."""
    def building(node: ast.AST) -> bool:
        if isinstance(node, ast.Expr | ast.Assign) and isinstance(node.value, ast.Call):
            called = node.value.func
            called = called.attr if isinstance(called, ast.Attribute) else getattr(called, "id", "")
            return called == "ArgumentParser" or called.startswith("add_") or called == "set_defaults"
        return isinstance(node, ast.Import | ast.ImportFrom) or (
            isinstance(node, ast.For) and all(map(building, node.body))) or (
            isinstance(node, ast.Expr) and isinstance(node.value, ast.Constant))  # a docstring
    for statement in function.body:
        if re.search(r"\.parse_(known_)?args\(", ast.unparse(statement)):
            return True
        if not building(statement):
            return False
    return False


def script_source(path: Path, seen: frozenset[Path] = frozenset()) -> str:
    """A shell script's code (comment lines dropped) and, recursively, that of the scripts it names."""
    code = "\n".join(line for line in path.read_text().splitlines() if not line.lstrip().startswith("#"))
    named = {ROOT / "scripts" / m for m in re.findall(r"scripts/(\w+\.(?:sh|py))", code)} - seen - {path}
    return code + "".join(script_source(p, seen | named | {path}) for p in sorted(named) if p.is_file())


# --- tests -------------------------------------------------------------------------------------------------------

COMMANDS = [c for path in DOC_FILES for c in doc_commands(path.read_text(), path.relative_to(ROOT).as_posix())]


def test_every_doc_with_a_shell_block_yields_commands_of_each_kind():
    """A broken extractor would pass every check below vacuously."""
    shown = {path.relative_to(ROOT).as_posix() for path in DOC_FILES if "```bash\ndepthnerf" in path.read_text()}
    assert shown <= {c.where.split(":")[0] for c in COMMANDS} and len(shown) > 3
    assert {c.argv[0] for c in COMMANDS} == {"depthnerf", "python", "bash"}


@pytest.mark.parametrize("command", COMMANDS, ids=lambda c: c.where)
def test_doc_command(command: DocCommand):
    found = problems(command)
    assert not found, f"{command.where}: {shlex.join(command.argv)}\n  " + "\n  ".join(found)


def test_a_shell_block_is_read_as_a_shell_would():
    """Loops run over their values, functions expand, variables and exports carry, wrappers unwrap."""
    block = ["S=study; export W=x", "f() { depthnerf train --seed 0 \"$@\"; }", "for c in cars chairs; do",
             "  f --out $S/$c  # a comment", "done", "timeout 9 torchrun --nproc_per_node=2 -m depthnerf eval \\",
             "    --run R", "pip install x && A=1 bash scripts/run_study.sh $S"]
    got = [(c.where, c.argv, c.env) for c in block_commands(list(enumerate(block, 1)), "x.md")]
    assert got == [("x.md:4", ("depthnerf", "train", "--seed", "0", "--out", "study/cars"), ("W",)),
                   ("x.md:4", ("depthnerf", "train", "--seed", "0", "--out", "study/chairs"), ("W",)),
                   ("x.md:6", ("depthnerf", "eval", "--run", "R"), ("W",)),
                   ("x.md:8", ("bash", "scripts/run_study.sh", "study"), ("A", "W"))]


@pytest.mark.parametrize("line, bad", [
    ("depthnerf evaluate --run R", "'evaluate'"),  # no such subcommand
    ("depthnerf eval --run R --views 8", "--views"),  # an abbreviation argparse would take
    ("depthnerf train --model.mirrored true", "--model.mirrored"),  # no such config field
    ("`depthnerf train [--model.mirrored true]`", "--model.mirrored"),  # nor in a synopsis
    ("`depthnerf train --schedule.lr $LR --seed x`", "'x'"),  # after a placeholder override value
    ("depthnerf train --schedule.lr fast", "fast"),  # a value the field does not take
    ("depthnerf eval --run R --ssim box", "box"),  # not a choice
    ("`depthnerf train [--depth none\\|midas] [--seed S]`", "'midas'"),  # an inline synopsis's alternative
    ("`depthnerf reconstruct IMAGE --view 8`", "--view"),  # an inline fragment
    ("python scripts/paired_difference.py --baseline A --methods B", "--methods"),
    ("python scripts/no_such_script.py", "no_such_script"),
    ("NO_SUCH_VAR=1 bash scripts/run_study.sh DIR", "NO_SUCH_VAR"),
])
def test_a_wrong_command_is_caught_naming_the_bad_word(line: str, bad: str):
    """The check can fail: each of these lines, in a shell block (or `inline`), is refused naming the bad word."""
    commands = doc_commands(line if line.startswith("`") else f"```bash\n{line}\n```", "x.md")
    assert len(commands) == 1 and bad in "\n".join(problems(commands[0]))
