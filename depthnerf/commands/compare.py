"""``depthnerf compare RUN_OR_SUMMARY ... [--reference paper] [--out PATH]``: a Table-1 style Markdown table.

Each argument is a ``summary.json`` written by ``depthnerf eval``, an eval output directory holding one, or a run
directory holding ``eval/*/summary.json`` (all of them). Rows are methods (the summaries' ``method``), column
groups the categories (Chairs PSNR, SSIM, Cars PSNR, SSIM, ...), plus Chamfer-L1 / F-score / LPIPS columns when
present (marked ``(N/M meshes empty)`` where predicted meshes were empty: worst-case values, not measured); see
:mod:`depthnerf.eval.table` for the summary contract. ``--reference paper`` adds the paper's Table 1
rows, labelled as reported in the paper on the real SRN data. The table goes to stdout, and to ``--out`` too.

Summaries scored with different protocol choices (SSIM variant, 8-bit or float renders, an object one left out
that another scored; :mod:`depthnerf.eval.config`) are refused with one line saying which differ; with
``--mixed-protocols`` the table is printed anyway, under a warning line that says the same. Rows of one category
scored on different samples (other numbers of objects or views, other objects, another split, ``--views-stride``
or ``--resolution``) are printed with a warning on stderr: their means are not over the same views
(:func:`depthnerf.eval.table.sample_warnings`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from depthnerf.errors import DepthnerfError
from depthnerf.eval.config import protocol_mismatch
from depthnerf.eval.table import find_summaries, load_summary, markdown_table, sample_warnings
from depthnerf.files import folder_problem, make_folder, write_text_atomic


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("paths", nargs="+", type=Path, metavar="RUN_OR_SUMMARY",
                        help="summary.json, an eval output dir, or a run dir with eval/*/summary.json")
    parser.add_argument("--reference", choices=["paper"], default=None,
                        help="also list the paper's Table 1 rows (reported on real SRN, not measured here)")
    parser.add_argument("--out", type=Path, default=None, help="also write the Markdown table to this file")
    parser.add_argument("--mixed-protocols", action="store_true",
                        help="print the table even when the summaries were scored with different protocol choices "
                             "(--ssim, --scored, --objects of depthnerf eval), under a warning")


def run(args: argparse.Namespace) -> int:
    if args.out is not None:  # before any reading: a path the table cannot go to is one line, not a late OSError
        if args.out.is_dir():
            raise DepthnerfError(f"{args.out}: --out is a folder; name the Markdown file to write")
        problem = None if args.out.exists() else folder_problem(args.out, "--out")
        if problem is not None:
            raise DepthnerfError(problem)
        make_folder(args.out.parent, "--out's folder")
    files: list[Path] = []
    for path in args.paths:
        files += [f for f in find_summaries(path) if f.resolve() not in {g.resolve() for g in files}]
    summaries = [load_summary(f) for f in files]
    mismatch = protocol_mismatch([s.choices for s in summaries if s.choices is not None])
    if mismatch and not args.mixed_protocols:
        raise DepthnerfError(f"{mismatch}: not comparable; re-evaluate with the same choices, or pass "
                             "--mixed-protocols")
    for line in sample_warnings(summaries):
        print(line, file=sys.stderr)
    table = markdown_table(summaries, reference=args.reference == "paper")
    if mismatch:
        table = f"**WARNING: mixed protocol choices, the rows are not comparable: {mismatch}.**\n\n{table}"
    elif summaries and all(s.choices.ssim and s.choices.scored for s in summaries):
        first = summaries[0].choices
        skipped = sorted({i for s in summaries for i in s.choices.skipped})
        table += (f"\nProtocol choices of every measured row: SSIM {first.ssim}, {first.scored} renders scored"
                  + (f", left out (pixelNeRF cannot load them): {', '.join(skipped)}" if skipped else "") + ".\n")
    print(table, end="")
    if args.out is not None:
        try:
            write_text_atomic(args.out, table)
        except OSError as err:
            raise DepthnerfError(f"{args.out}: cannot write the table ({err.strerror or err})") from None
    return 0
