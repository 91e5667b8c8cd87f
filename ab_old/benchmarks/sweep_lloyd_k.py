"""One Lloyd iteration on relaxed (blue-noise) points against the first-pass k:
where the adapted k of torchvor.lloyd stands between kNN cost (larger k) and
retried cells (smaller k). Reports only; nothing asserts.

    python benchmarks/sweep_lloyd_k.py --device cuda [--sizes 1M] [--ks 16,18,...] [--timeline]

For each k: the wall time of torchvor.voronoi, the cells it retried with more
neighbours, and the wall time of one torchvor.lloyd iteration at that k (CUDA
events, median of --repeats). Then the k that lloyd adapts to after 5
iterations, and with --timeline the GPU gaps of one iteration at that k.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402


def main() -> None:
    parser = common.base_parser(__doc__)
    parser.add_argument("--ks", type=common.parse_ints, default=[16, 17, 18, 19, 20, 21, 22, 24])
    parser.add_argument("--timeline", action="store_true")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    common.print_header(device)
    box = common.UNIT_BOX
    for n in args.sizes or [1_000_000]:
        blue, _ = common.make_points("blue", n, seed=args.seed, dtype=dtype, device=device,
                                     cache_dir=args.cache_dir, blue_iters=args.blue_iters)
        rows = []
        for k in args.ks:
            cells = torchvor.voronoi(blue, box, k=k, on_failure="flag")
            retried = int((cells.neighbors > k).sum())
            voronoi_s = common.time_fn(lambda: torchvor.voronoi(blue, box, k=k, on_failure="flag"),
                                       device, warmup=2, repeats=args.repeats)
            lloyd_s = common.time_fn(lambda: torchvor.lloyd(blue, box, iters=1, k=k),
                                     device, warmup=2, repeats=args.repeats)
            rows.append([k, common.fmt_s(voronoi_s), retried, common.fmt_s(lloyd_s)])
        _, history = torchvor.lloyd(blue, box, iters=5, return_history=True)
        adapted = history[-1].k
        common.print_results(
            f"Lloyd iteration against k, {common.npoints_label(n)} blue",
            ["k", "voronoi", "cells retried", "1 Lloyd iteration"], rows,
            [f"lloyd's adapted k after 5 iterations: {[h.k for h in history]}; "
             f"seconds per iteration {[round(h.seconds * 1e3, 2) for h in history]} ms"])
        if args.timeline and device.type == "cuda":
            from profile_gpu import timeline

            timeline(f"one Lloyd iteration, {n} blue, k={adapted}",
                     lambda: torchvor.lloyd(blue, box, iters=1, k=adapted))


if __name__ == "__main__":
    main()
