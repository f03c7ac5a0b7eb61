"""Paired per-object differences between two methods trained with several seeds each (docs/RESULTS.md, "Seeds").

One training run per arm cannot separate a method's effect from the seed's: on the study's chairs, the same
baseline trained with seed 1 instead of 0 gains +0.24 dB on 35/50 objects. The seed's effect is a shift of the
whole run, so a per-object interval of ONE pair of runs does not contain it. Given each arm's evaluations (one
``depthnerf eval`` folder per training seed, the same objects and views scored the same way), this prints per
metric:

- **seed-averaged, paired per object**: each object's metric averaged over the arm's seeds, then the paired
  difference (method - baseline) with its 95% t-interval over objects and the objects on which the method is no
  worse (as ``paired_difference.py``);
- **every pairing of seeds**: the mean difference of each (method seed, baseline seed) pair, smallest and largest,
  and in how many pairings the per-object 95% interval lies wholly on the better side;
- **run level**: each run's mean over objects; the difference of the two arms' means with a Welch 95% interval over
  runs (so it includes the seed-to-seed spread; needs at least 2 seeds per arm), and each arm's spread (largest
  minus smallest run mean).

    python scripts/seed_paired_difference.py --baseline eval/cars-none eval/cars-none-s1 \
        --method eval/cars-bundled eval/cars-bundled-s1 [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from dataclasses import asdict, dataclass
from pathlib import Path

from paired_difference import METRICS, check_pairable, method_name, read_per_object, same_views, t_interval
from scipy import stats


@dataclass
class SeedStat:
    """One metric of one method (several seeds) against one baseline (several seeds)."""

    metric: str
    objects: int
    baseline_seeds: int
    method_seeds: int
    baseline_mean: float
    method_mean: float
    averaged_diff: float
    """Mean over objects of (method's seed-mean - baseline's seed-mean)."""
    averaged_ci95: tuple[float, float]
    """95% t-interval over objects of the seed-averaged differences."""
    averaged_no_worse: int
    """Objects whose seed-averaged difference is on the better side or zero."""
    pairing_diffs: list[float]
    """Mean difference of every (method seed, baseline seed) pairing, method-major."""
    pairings_better: int
    """Pairings whose per-object 95% interval lies wholly on the better side."""
    run_ci95: tuple[float, float] | None
    """Welch 95% interval of (method's run means) - (baseline's run means); None with fewer than 2 runs a side."""
    baseline_spread: float
    """Largest minus smallest baseline run mean."""
    method_spread: float


def load_arm(folders: list[Path]) -> list[dict[str, dict[str, str]]]:
    """Each folder's per-object rows; every folder must score the same objects on the same views
    (``paired_difference.same_views``), the same way (``paired_difference.check_pairable``)."""
    arms = [read_per_object(f) for f in folders]
    first = arms[0]
    for folder, rows in zip(folders[1:], arms[1:], strict=True):
        check_pairable(folders[0], folder)
        if set(rows) != set(first) or not all(same_views(rows[o], first[o]) for o in first):
            raise SystemExit(f"error: {folder}/per_object.csv: objects or views differ from "
                             f"{folders[0]}/per_object.csv")
    return arms


def welch_interval(a: list[float], b: list[float]) -> tuple[float, float] | None:
    """95% Welch interval of mean(a) - mean(b); None unless both have at least 2 values."""
    if len(a) < 2 or len(b) < 2:
        return None
    ma, mb = sum(a) / len(a), sum(b) / len(b)
    va = sum((x - ma) ** 2 for x in a) / (len(a) - 1) / len(a)
    vb = sum((x - mb) ** 2 for x in b) / (len(b) - 1) / len(b)
    se2 = va + vb
    if se2 == 0.0:
        return ma - mb, ma - mb
    dof = se2 ** 2 / (va ** 2 / (len(a) - 1) + vb ** 2 / (len(b) - 1))
    half = float(stats.t.ppf(0.975, dof)) * math.sqrt(se2)
    return ma - mb - half, ma - mb + half


def seed_paired(baseline: list[Path], method: list[Path]) -> list[SeedStat]:
    """The statistics above for every metric all the evaluations have."""
    arms = load_arm(baseline + method)  # every folder of both arms against the first baseline folder
    base, meth = arms[:len(baseline)], arms[len(baseline):]
    out = []
    for metric, higher in METRICS.items():
        ids = [o for o in sorted(base[0]) if all(r[o].get(metric) for r in base + meth)]
        if len(ids) < 2:
            continue
        b = [[float(r[o][metric]) for o in ids] for r in base]  # [seed][object]
        m = [[float(r[o][metric]) for o in ids] for r in meth]
        b_avg = [sum(col) / len(col) for col in zip(*b, strict=True)]
        m_avg = [sum(col) / len(col) for col in zip(*m, strict=True)]
        diffs = [x - y for x, y in zip(m_avg, b_avg, strict=True)]
        mean, _, half = t_interval(diffs)
        sign = 1.0 if higher else -1.0
        pairing_diffs, better = [], 0
        for mi in m:
            for bi in b:
                d = [x - y for x, y in zip(mi, bi, strict=True)]
                pm, _, ph = t_interval(d)
                pairing_diffs.append(pm)
                better += int(sign * pm - ph > 0)
        b_runs, m_runs = [sum(r) / len(r) for r in b], [sum(r) / len(r) for r in m]
        out.append(SeedStat(
            metric=metric, objects=len(ids), baseline_seeds=len(b), method_seeds=len(m),
            baseline_mean=sum(b_runs) / len(b_runs), method_mean=sum(m_runs) / len(m_runs),
            averaged_diff=mean, averaged_ci95=(mean - half, mean + half),
            averaged_no_worse=sum(1 for x in diffs if sign * x >= 0), pairing_diffs=pairing_diffs,
            pairings_better=better, run_ci95=welch_interval(m_runs, b_runs),
            baseline_spread=max(b_runs) - min(b_runs), method_spread=max(m_runs) - min(m_runs)))
    return out


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--baseline", type=Path, nargs="+", required=True, help="the baseline's eval folders, one per seed")
    parser.add_argument("--method", type=Path, nargs="+", required=True, help="the method's eval folders, one per seed")
    parser.add_argument("--json", type=Path, help="also write the rows as JSON")
    args = parser.parse_args(argv)
    rows = seed_paired(args.baseline, args.method)
    print(f"{method_name(args.method[0])} ({len(args.method)} seeds) against {method_name(args.baseline[0])} "
          f"({len(args.baseline)} seeds)")
    print("| metric | objects | baseline | method | seed-averaged difference | 95% interval | no worse | "
          "pairings: smallest, largest | pairings better (95%) | run level 95% interval | seed spread: baseline, method |")
    print("|---|---|---|---|---|---|---|---|---|---|---|")
    for s in rows:
        dec = 2 if s.metric == "psnr" else 4
        f = f"{{:+.{dec}f}}".format
        run = "n/a" if s.run_ci95 is None else f"[{f(s.run_ci95[0])}, {f(s.run_ci95[1])}]"
        print(f"| {s.metric} | {s.objects} | {s.baseline_mean:.{dec}f} | {s.method_mean:.{dec}f} | "
              f"{f(s.averaged_diff)} | [{f(s.averaged_ci95[0])}, {f(s.averaged_ci95[1])}] | "
              f"{s.averaged_no_worse}/{s.objects} | {f(min(s.pairing_diffs))}, {f(max(s.pairing_diffs))} | "
              f"{s.pairings_better}/{len(s.pairing_diffs)} | {run} | {s.baseline_spread:.{dec}f}, {s.method_spread:.{dec}f} |")
    if args.json:
        args.json.write_text(json.dumps([asdict(s) for s in rows], indent=2) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())
