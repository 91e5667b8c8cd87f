"""Where one Lloyd step's wall time goes, without a profiler (GPU machine).

A profiled timeline overstates what each launch costs the host
(benchmarks/NOTES.md, twenty-seventh session), so this script times nested
parts of one Lloyd step on relaxed points in interleaved rounds, each by CUDA
events around it, and reports the medians and their differences:

- ``lloyd``: ``torchvor.lloyd(points, box, iters=1, k=K)``, the benchmarks' step;
- ``step``: one iteration's op (``torchvor::lloyd_step``: the grid-order cells, the
  move and its measures, one read), i.e. without lloyd()'s setup and the final
  return to the caller's order;
- ``cells``: the grid-order voronoi op alone (``_voronoi_in_grid_order``);
- ``late``: the median ``seconds`` of iterations 2.. of one ``lloyd(iters=8)`` run;
- ``launches``: 40 small ATen ops from Python and one read, per op (the host's rate);
- ``busy``: the GPU's activity (kernels, copies, memsets) in one profiled ``lloyd``
  call, whose wall time minus this is the GPU's idle time.

    python benchmarks/lloyd_breakdown.py [--sizes 1M,10M] [--rounds 9] [--k 19]
"""
from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
from ab_env import wall_ms  # noqa: E402  (CUDA events around the call)
from torchvor.lloyd import HISTOGRAM_BINS, QUANTILE_SAMPLE  # noqa: E402
from torchvor.ops import _voronoi_in_grid_order, as_box  # noqa: E402

SIZES = {"100K": 100_000, "1M": 1_000_000, "10M": 10_000_000}


def gpu_busy_ms(fn) -> float:
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    return sum(e.device_time_total for e in prof.key_averages()) / 1e3


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--sizes", default="1M")
    parser.add_argument("--rounds", type=int, default=9)
    parser.add_argument("--k", type=int, default=19)
    args = parser.parse_args()
    print(f"GPU: {torch.cuda.get_device_name()}")
    for tag in args.sizes.split(","):
        points, _ = common.make_points("blue", SIZES[tag], seed=0, dtype=torch.float32,
                                       device=torch.device("cuda"),
                                       cache_dir=Path(__file__).resolve().parent / ".cache")
        box = as_box(points, common.UNIT_BOX)
        _, order = _voronoi_in_grid_order(points, box, None, args.k)
        in_grid_order = points.index_select(0, order)  # as in a run's later iterations
        small = torch.zeros(16, device="cuda")
        stride = max(1, SIZES[tag] // QUANTILE_SAMPLE)  # as torchvor.lloyd samples

        def step():
            return torch.ops.torchvor.lloyd_step.default(in_grid_order, box, None, args.k, stride, HISTOGRAM_BINS)

        def launches():
            for _ in range(40):
                small.add_(1.0)
            small.sum().item()

        parts = {
            "lloyd": lambda: torchvor.lloyd(in_grid_order, box, iters=1, k=args.k),
            "step": step,
            "cells": lambda: _voronoi_in_grid_order(in_grid_order, box, None, args.k),
            "launches": launches,
        }
        for fn in parts.values():  # warm-up
            fn()
        times = {name: [] for name in parts}
        late = []
        for _ in range(args.rounds):
            for name, fn in parts.items():
                times[name].append(wall_ms(fn))
            _, history = torchvor.lloyd(in_grid_order, box, iters=8, k=args.k, return_history=True)
            late += [1e3 * step.seconds for step in history[2:]]
        median = {name: statistics.median(values) for name, values in times.items()}
        median["launches"] /= 41
        median["late"] = statistics.median(late)
        busy = gpu_busy_ms(parts["lloyd"])
        print(f"\n### {tag} blue noise, k={args.k}, {args.rounds} interleaved rounds (medians, ms)")
        print("| part | ms |")
        print("|---|---|")
        for name in ("lloyd", "step", "cells", "late"):
            print(f"| {name} | {median[name]:.3f} |")
        print(f"| lloyd - step (setup, return to the caller's order) | {median['lloyd'] - median['step']:.3f} |")
        print(f"| step - cells (move, measures, histogram, their read) | {median['step'] - median['cells']:.3f} |")
        print(f"| GPU busy in one profiled lloyd call | {busy:.3f} |")
        print(f"| lloyd - busy (GPU idle) | {median['lloyd'] - busy:.3f} |")
        print(f"| one small ATen op from Python (40 and a read) | {1e3 * median['launches']:.1f} us |")


if __name__ == "__main__":
    main()
