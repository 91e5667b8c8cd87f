"""Where a kernel's time goes, instruction by instruction: reads an Nsight
Compute report (taken with --set full --import-source yes), exports its SASS
source page as CSV and prints the instructions and the 25-instruction windows
with the most warp stall samples, with how often each ran.

    python benchmarks/ncu_source.py REPORT.ncu-rep [--top 40] [--csv-dir DIR]

(--csv-dir keeps the raw CSV: one row per instruction after a kernel-name row.)
"""
from __future__ import annotations

import argparse
import csv
import io
import subprocess
import sys
from pathlib import Path

STALLS = "Warp Stall Sampling (All Samples)"
EXECUTED = "Instructions Executed"
THREADS = "Avg. Threads Executed"


def export(report: Path) -> str:
    command = ["ncu", "--import", str(report), "--page", "source", "--csv", "--print-source", "sass"]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        sys.exit(f"{' '.join(command)} failed ({result.returncode}):\n{result.stderr[-2000:]}")
    return result.stdout


def parse(text: str) -> list[dict]:
    """Rows of the SASS source page, one dict per instruction."""
    rows = [r for r in csv.reader(io.StringIO(text)) if r]
    header = next(i for i, r in enumerate(rows) if r[0] == "Address")
    names = rows[header]
    return [dict(zip(names, r)) for r in rows[header + 1:] if r[0].startswith("0x")]


def number(text) -> float:
    try:
        return float(str(text).replace(",", ""))
    except ValueError:
        return 0.0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("report", type=Path)
    parser.add_argument("--top", type=int, default=40)
    parser.add_argument("--csv-dir", type=Path, default=None, help="also write <report>_sass.csv here")
    args = parser.parse_args()
    text = export(args.report)
    if args.csv_dir is not None:
        (args.csv_dir / f"{args.report.stem}_sass.csv").write_text(text)
    rows = parse(text)
    stalls = [number(r[STALLS]) for r in rows]
    total = sum(stalls) or 1.0
    executed = sum(number(r[EXECUTED]) for r in rows)
    print(f"{len(rows)} instructions, {total:,.0f} stall samples, {executed:,.0f} warp instructions executed")
    print(f"\n### top {args.top} instructions by stall samples (index | % | executed | threads | SASS)")
    for i in sorted(range(len(rows)), key=lambda i: stalls[i], reverse=True)[:args.top]:
        r = rows[i]
        print(f"{i:5d} | {100 * stalls[i] / total:4.1f}% | {number(r[EXECUTED]):12,.0f} | {number(r[THREADS]):4.1f} | "
              f"{r['Source'].strip()}")
    print("\n### 25-instruction windows with at least 1% of the samples (first index | % | most executed)")
    for start in range(0, len(rows), 25):
        share = sum(stalls[start:start + 25]) / total
        if share >= 0.01:
            most = max(number(r[EXECUTED]) for r in rows[start:start + 25])
            print(f"{start:5d} | {100 * share:4.1f}% | {most:12,.0f}")


if __name__ == "__main__":
    main()
