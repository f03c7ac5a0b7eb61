"""What a device-tool call would send to a lent GPU machine, summed before the call (no device time spent).

The tool sends the checkout's tracked files, its untracked files that git does not ignore, and the ignored paths
named in ``carry``; it refuses the call when they exceed its limit (64 MiB by its README; a lease refused 66.9 MB
and accepted 61.5 MB, so the check reads it as 64 MB, the stricter reading). Prints each part, the largest files,
and the verdict; exits 1 when the call would be refused.

    python scripts/travel_size.py [CARRY ...]        e.g.  python scripts/travel_size.py .whl
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

LIMIT_BYTES = 64_000_000
"""The travel limit as read here (decimal megabytes: the stricter reading of the tool's 64 MiB)."""


def git_files(root: Path, *args: str) -> list[Path]:
    """Files ``git ls-files ARGS`` lists under ``root`` (those present on disk)."""
    out = subprocess.run(["git", "ls-files", "-z", *args], cwd=root, capture_output=True, check=True).stdout
    return [root / name for name in out.decode().split("\0") if name and (root / name).is_file()]


def carried_files(root: Path, carry: list[str]) -> list[Path]:
    """Every file under the carried paths (a missing one is an error: the tool would remove it there)."""
    files = []
    for name in carry:
        path = root / name
        if not path.exists():
            raise SystemExit(f"error: {path}: a carried path that does not exist")
        files.extend([path] if path.is_file() else sorted(p for p in path.rglob("*") if p.is_file()))
    return files


def travel_parts(root: Path, carry: list[str]) -> dict[str, list[Path]]:
    """The files that would travel, by part: tracked, untracked (not ignored), carried."""
    return {"tracked": git_files(root), "untracked, not ignored": git_files(root, "--others", "--exclude-standard"),
            "carried": carried_files(root, carry)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("carry", nargs="*", help="ignored paths the call would carry (e.g. .whl)")
    parser.add_argument("--root", type=Path, default=Path(__file__).resolve().parent.parent,
                        help="the checkout (default: this one)")
    parser.add_argument("--top", type=int, default=5, help="largest files to list (default 5)")
    args = parser.parse_args(argv)
    parts = travel_parts(args.root, args.carry)
    sizes = {p: p.stat().st_size for files in parts.values() for p in files}
    for name, files in parts.items():
        print(f"{name:24s} {len(files):5d} files {sum(sizes[p] for p in files) / 1e6:8.2f} MB")
    total = sum(sizes.values())
    for path, size in sorted(sizes.items(), key=lambda kv: -kv[1])[:args.top]:
        print(f"  {size / 1e6:6.2f} MB  {path.relative_to(args.root)}")
    verdict = "fits" if total <= LIMIT_BYTES else "would be REFUSED"
    print(f"total {total / 1e6:.2f} MB of {LIMIT_BYTES / 1e6:.0f} MB: {verdict} "
          f"({(LIMIT_BYTES - total) / 1e6:+.2f} MB left)")
    return 0 if total <= LIMIT_BYTES else 1


if __name__ == "__main__":
    sys.exit(main())
