"""``depthnerf compare RUN_OR_SUMMARY ... [--reference paper] [--out PATH]``: a Table-1 style Markdown table.

Each argument is a ``summary.json`` written by ``depthnerf eval``, an eval output directory holding one, or a run
directory holding ``eval/*/summary.json`` (all of them). Rows are methods (the summaries' ``method``), column
groups the categories (Chairs PSNR, SSIM, Cars PSNR, SSIM, ...), plus Chamfer-L1 / F-score / LPIPS columns when
present; see :mod:`depthnerf.eval.table` for the summary contract. ``--reference paper`` adds the paper's Table 1
rows, labelled as reported in the paper on the real SRN data. The table goes to stdout, and to ``--out`` too.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.eval.table import find_summaries, load_summary, markdown_table
from depthnerf.files import write_text_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", type=Path, metavar="RUN_OR_SUMMARY",
                        help="summary.json, an eval output dir, or a run dir with eval/*/summary.json")
    parser.add_argument("--reference", choices=["paper"], default=None,
                        help="also list the paper's Table 1 rows (reported on real SRN, not measured here)")
    parser.add_argument("--out", type=Path, default=None, help="also write the Markdown table to this file")


def run(args: argparse.Namespace) -> int:
    files: list[Path] = []
    for path in args.paths:
        files += [f for f in find_summaries(path) if f.resolve() not in {g.resolve() for g in files}]
    table = markdown_table([load_summary(f) for f in files], reference=args.reference == "paper")
    print(table, end="")
    if args.out is not None:
        try:
            args.out.parent.mkdir(parents=True, exist_ok=True)
            write_text_atomic(args.out, table)
        except OSError as err:
            raise DepthnerfError(f"{args.out}: cannot write the table ({err.strerror or err})") from None
    return 0
