"""Where a kernel's time goes, by source line: reads an Nsight Compute report
(taken with --set full --import-source yes, from a build with -lineinfo),
exports its source page as CSV and prints the lines with the most warp stall
samples and the most executed instructions.

    python benchmarks/ncu_source.py REPORT.ncu-rep [--top 40] [--csv-dir DIR]
"""
from __future__ import annotations

import argparse
import csv
import io
import subprocess
import sys
from pathlib import Path


def export(report: Path, view: str) -> list[dict]:
    """The source page of `report` in `view` (cuda or sass) as CSV rows."""
    command = ["ncu", "--import", str(report), "--page", "source", "--csv", "--print-source", view]
    result = subprocess.run(command, capture_output=True, text=True)
    if result.returncode != 0:
        print(f"{' '.join(command)} failed ({result.returncode}):\n{result.stderr[-2000:]}", file=sys.stderr)
        return []
    text = result.stdout
    start = text.find('"')  # skip any banner lines before the CSV header
    return list(csv.DictReader(io.StringIO(text[start:])))


def number(text: str) -> float:
    try:
        return float(text.replace(",", ""))
    except (AttributeError, ValueError):
        return 0.0


def column(rows: list[dict], *words: str) -> str | None:
    """The first column whose name contains every word (case-insensitive)."""
    for name in rows[0].keys():
        if all(w.lower() in name.lower() for w in words):
            return name
    return None


def summarize(rows: list[dict], view: str, top: int) -> None:
    if not rows:
        return
    print(f"## {view}: {len(rows)} rows; columns: {', '.join(rows[0].keys())}")
    stall = column(rows, "Warp Stall Sampling", "All") or column(rows, "Stall Sampling")
    executed = column(rows, "Instructions Executed") or column(rows, "Warp Instructions")
    text = column(rows, "Source")
    where = column(rows, "Line") or column(rows, "Address") or column(rows, "#")
    for metric in (stall, executed):
        if metric is None:
            continue
        total = sum(number(r[metric]) for r in rows) or 1.0
        print(f"\n### top {top} by {metric} (total {total:,.0f})")
        ranked = sorted(rows, key=lambda r: number(r[metric]), reverse=True)[:top]
        for r in ranked:
            share = 100.0 * number(r[metric]) / total
            other = executed if metric == stall else stall
            extra = f" | {other}: {number(r[other]):,.0f}" if other else ""
            source = (r.get(text) or "").strip()[:110] if text else ""
            print(f"{share:5.1f}% | {r.get(where, '') if where else ''} | {source}{extra}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("report", type=Path)
    parser.add_argument("--top", type=int, default=40)
    parser.add_argument("--csv-dir", type=Path, default=None, help="also write <report>_<view>.csv here")
    args = parser.parse_args()
    for view in ("cuda", "sass"):
        rows = export(args.report, view)
        if args.csv_dir is not None and rows:
            path = args.csv_dir / f"{args.report.stem}_{view}.csv"
            with open(path, "w", newline="") as handle:
                writer = csv.DictWriter(handle, fieldnames=list(rows[0].keys()))
                writer.writeheader()
                writer.writerows(rows)
        summarize(rows, view, args.top if view == "cuda" else args.top // 2)


if __name__ == "__main__":
    main()
