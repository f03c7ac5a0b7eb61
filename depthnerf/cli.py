"""The ``depthnerf`` command line: a thin dispatcher over ``depthnerf.commands``.

Each subcommand lives in ``depthnerf/commands/<module>.py`` and exposes ``add_arguments(parser)`` and
``run(args) -> int``; modules are imported lazily so ``depthnerf --help`` stays fast. A
:class:`~depthnerf.errors.DepthnerfError` becomes one line ``error: ...`` on stderr and exit status 2, and so
does a flag the parser refuses (:class:`OneLineParser`). In a torchrun job every rank parses the same command
line, so rank 0 alone prints a refused flag, and a :class:`~depthnerf.errors.RefusedOnMain` (a refusal rank 0 prints)
ends a rank with status 2 and no line. Data and usage warnings are printed by rank 0 alone too: every rank indexes
the same splits and loads the same checkpoint, so each would print the same lines.
"""

from __future__ import annotations

import argparse
import contextlib
import importlib
import os
import sys
import warnings
from pathlib import Path

from depthnerf import __version__
from depthnerf.cpu_runtime import configure_process
from depthnerf.errors import (
    DataWarning,
    DepthnerfError,
    RefusedOnMain,
    UsageWarning,
    format_data_warning,
    launch_rank,
)

SUBCOMMANDS: dict[str, tuple[str, str]] = {
    "synth": ("synth", "generate the synthetic SRN-protocol benchmark (cars or chairs)"),
    "inspect": ("inspect", "validate an SRN-format dataset folder and summarise it"),
    "depth": ("depth", "precompute monocular depth priors into the cache"),
    "depth-eval": ("depth_eval", "evaluate a depth estimator (AbsRel, delta<1.25) against ground truth"),
    "train": ("train", "train a (depth-aware) pixelNeRF preset"),
    "eval": ("evaluate", "evaluate a run or checkpoint by the SRN protocol"),
    "compare": ("compare", "print a Table-1 style Markdown table from runs or eval summaries"),
    "reconstruct": ("reconstruct", "reconstruct one photo: depth, novel views, turntable, mesh"),
    "checkpoints": ("checkpoints", "list the shipped checkpoints"),
    "fit-facing": ("fit_facing", "fit a mirror model's facing head (the plane's angle from the photo) into a checkpoint"),
    "demo": ("demo", "one-command demo: synthesise an unseen car and chair, reconstruct each from one view"),
    "app": ("app", "serve the local web page: one photo in, novel views, mesh and point cloud out (needs [app])"),
}


class OneLineParser(argparse.ArgumentParser):
    """An argument parser whose errors are one line like every other error of the package (``error: PROG:
    message``, exit status 2), pointing to ``--help`` instead of printing the usage block; in a torchrun job, whose
    ranks all parse the same command line, rank 0 alone prints it. Flags are taken as spelled in full only
    (``allow_abbrev=False``, also for the subcommands' parsers): argparse's prefix matching ran ``depthnerf eval
    --views 8`` as ``--views-stride 8``, where ``reconstruct --views`` means another thing."""

    def __init__(self, *args, **kwargs) -> None:
        kwargs.setdefault("allow_abbrev", False)
        super().__init__(*args, **kwargs)

    def error(self, message: str):
        line = f"error: {self.prog}: {message} ({self.prog} --help lists its options)\n"
        self.exit(2, line if launch_rank() == 0 else None)


def _refusing_empty(convert, flag: str):
    """``convert`` (an argparse ``type``) for ``flag`` that first refuses an empty value in one line (``--out ''``
    would otherwise be ``Path('')``, the current folder)."""
    def checked(value: str):
        if not value:
            raise argparse.ArgumentError(None, f"{flag} is empty")  # not caught by argparse: the line as it is
        return convert(value)
    return checked


PATH_FLAGS = ("--out", "--data", "--checkpoint", "--depth-checkpoint", "--init-from", "--for", "--config",
              "--background-model")
"""Options that name a path, a checkpoint or weights in every subcommand that has them, also where it takes them as
strings (an empty one would be ``Path('')``, the current folder: ``--checkpoint ''`` would load the run folder the
command was started in)."""


def refuse_empty_paths(parser: argparse.ArgumentParser) -> None:
    """Make every option of ``parser`` that names a path (``type=Path``, and :data:`PATH_FLAGS`) refuse an empty
    value: ``error: PROG: --out is empty``, before any command runs (an option with aliases is named by its first
    long name)."""
    for action in parser._actions:
        if action.option_strings and (action.type is Path or set(PATH_FLAGS) & set(action.option_strings)):
            name = next(s for s in action.option_strings if s.startswith("--"))
            action.type = _refusing_empty(action.type or str, name)


def _command_module(name: str):
    module, _ = SUBCOMMANDS[name]
    return importlib.import_module(f"depthnerf.commands.{module}")


def build_parser(argv: list[str]) -> argparse.ArgumentParser:
    """The top-level parser; only the selected subcommand's module is imported."""
    parser = OneLineParser(prog="depthnerf", description="Single-image 3D object reconstruction with a depth-aware "
                           "pixelNeRF. Start with `depthnerf demo`; `depthnerf COMMAND --help` for each command.")
    parser.add_argument("--version", action="version", version=f"depthnerf {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    chosen = next((a for a in argv if not a.startswith("-")), None)
    for name, (_, help_text) in SUBCOMMANDS.items():
        p = sub.add_parser(name, help=help_text, description=help_text)
        if name == chosen:
            _command_module(name).add_arguments(p)
            refuse_empty_paths(p)
            p.set_defaults(subcommand_parser=p)  # an error about its arguments names it
    return parser


def _data_warning_printer(fallback):
    """A ``warnings.showwarning`` that prints data warnings as one line ``warning: ...`` / ``note: ...`` on stderr
    and hands any other warning to ``fallback``."""
    def show(message, category, filename, lineno, file=None, line=None) -> None:
        text = format_data_warning(message, category)
        if text is None:
            fallback(message, category, filename, lineno, file, line)
        else:
            print(text, file=sys.stderr, flush=True)
    return show


def main(argv: list[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    configure_process()  # OpenMP wait policy (before torch is imported) and glibc malloc; see cpu_runtime
    parser = build_parser(argv)
    args, extra = parser.parse_known_args(argv)
    if args.command is None:
        parser.print_help()
        return 2
    module = _command_module(args.command)
    command_parser = vars(args).pop("subcommand_parser", parser)
    if extra and not getattr(module, "ACCEPTS_OVERRIDES", False):
        command_parser.error(f"unrecognized arguments: {' '.join(extra)}")
    args.overrides = extra
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("always", DataWarning)  # every object's warning, even when repeated in-process
            if launch_rank() != 0:  # the same lines as rank 0's (module docstring)
                warnings.simplefilter("ignore", DataWarning)
                warnings.simplefilter("ignore", UsageWarning)
            warnings.showwarning = _data_warning_printer(warnings.showwarning)
            return int(module.run(args) or 0)
    except RefusedOnMain:
        return 2  # rank 0 prints the same line
    except DepthnerfError as err:
        print(f"error: {err}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("interrupted", file=sys.stderr)
        return 130
    except BrokenPipeError:  # the reader of stdout went away (`depthnerf ... | head`): stop quietly, as on SIGPIPE
        with contextlib.suppress(OSError, ValueError, AttributeError):  # no second error when Python flushes stdout
            os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
        return 141
