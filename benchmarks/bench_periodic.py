"""Periodic boxes against plain ones: torchvor.voronoi and knn of the same points in the
unit cube, with periodic=True and without.

    python benchmarks/bench_periodic.py [--device cpu|cuda] [--sizes 1M,10M] [--kinds blue,white] [--dtype float64]

A periodic call pads the cloud with the images near the box's faces and computes the
padded cloud's cells; the ratio periodic / plain is what the padding and the cells that
reach past it cost.
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torch  # noqa: E402
import torchvor  # noqa: E402

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def profile(points, device, knn_k, label):
    """Print the operators and kernels of one periodic voronoi call (and knn), by self time."""
    calls = [("periodic voronoi", lambda: torchvor.voronoi(points, UNIT, periodic=True))]
    if knn_k:
        calls.append(("periodic knn", lambda: torchvor.knn(points, knn_k, box=UNIT, periodic=True)))
    common.profile_calls(calls, device, label)


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default="blue,white", help="comma-separated: blue, white, perturbed")
    parser.add_argument("--knn-k", type=int, default=16, help="k of the kNN rows (0: no kNN rows)")
    parser.add_argument("--profile", action="store_true",
                        help="profile one periodic voronoi call (and knn) at the largest size of each kind")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [100_000, 1_000_000]
    notes = [f"points in the unit cube, {args.dtype}, default k (the pilot's); median of {args.repeats} runs "
             f"after {args.warmup} warm-up run(s); knn with k={args.knn_k}, the box given in both calls."]
    rows = []
    for kind in args.kinds.split(","):
        for n in sizes:
            points, _ = common.make_points(kind, n, seed=args.seed, dtype=dtype, device=device,
                                           cache_dir=args.cache_dir, blue_iters=args.blue_iters)
            n = points.shape[0]
            timed = {}
            for label, periodic in (("plain", False), ("periodic", True)):
                timed[label] = common.time_fn(lambda: torchvor.voronoi(points, UNIT, periodic=periodic),
                                              device, args.warmup, args.repeats)
                if args.knn_k:
                    timed["knn " + label] = common.time_fn(
                        lambda: torchvor.knn(points, args.knn_k, box=UNIT, periodic=periodic),
                        device, args.warmup, args.repeats)
            volume = torchvor.voronoi(points, UNIT, periodic=True).volume.double().sum().item()
            if args.profile and n >= 0.99 * max(sizes):
                profile(points, device, args.knn_k, f"{kind} n={n}")
            common.log(f"{kind} n={n}: " + ", ".join(f"{k} {common.fmt_s(v)}" for k, v in timed.items())
                       + f"; periodic volume sum - 1 = {volume - 1:.2e}")
            row = [kind, common.npoints_label(n), common.fmt_s(timed["plain"]), common.fmt_s(timed["periodic"]),
                   common.fmt_ratio(timed["periodic"] / timed["plain"])]
            if args.knn_k:
                row += [common.fmt_s(timed["knn plain"]), common.fmt_s(timed["knn periodic"]),
                        common.fmt_ratio(timed["knn periodic"] / timed["knn plain"])]
            rows.append(row)
            points = None
    headers = ["points", "n", "voronoi s", "periodic voronoi s", "periodic / plain"]
    if args.knn_k:
        headers += ["knn s", "periodic knn s", "periodic / plain"]
    common.print_results("Periodic boxes", headers, rows, notes)


if __name__ == "__main__":
    main()
