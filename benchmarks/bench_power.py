"""Power diagrams: torchvor.power_weights (every cell the same volume, to 1e-6), then
torchvor.voronoi with those weights against the plain Voronoi call on the same points.

    python benchmarks/bench_power.py [--device cpu|cuda] [--sizes 100K,1M] [--kinds blue,white] [--dtype float64]

The power call walks a grid of the points from each cell's own and clips in float64
(csrc/ops/power.h); the plain call is the tuned Voronoi path.
"""
from __future__ import annotations

import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torch  # noqa: E402
import torchvor  # noqa: E402

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default="blue,white", help="comma-separated: blue, white, perturbed")
    parser.add_argument("--tol", type=float, default=1e-6, help="power_weights' relative volume tolerance")
    parser.add_argument("--profile", action="store_true",
                        help="profile one power voronoi call and one power_weights call at the largest size of "
                             "each kind")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [100_000]
    notes = [f"points in the unit cube, {args.dtype}; power_weights to tol={args.tol:g} with equal volumes, "
             f"timed once after a warm-up call on a hundredth of the points; voronoi: median of {args.repeats} runs "
             f"after {args.warmup} warm-up run(s)."]
    rows = []
    for kind in args.kinds.split(","):
        for n in sizes:
            points, _ = common.make_points(kind, n, seed=args.seed, dtype=dtype, device=device,
                                           cache_dir=args.cache_dir, blue_iters=args.blue_iters)
            n = points.shape[0]
            if args.warmup:  # the kernels' first launches, cuSPARSE's handle: on a share of the points
                torchvor.power_weights(points[: max(1, n // 100)], UNIT, tol=args.tol)
            common.synchronize(device)
            start = time.perf_counter()
            solved = torchvor.power_weights(points, UNIT, tol=args.tol)
            common.synchronize(device)
            solve_s = time.perf_counter() - start
            weights = solved.weights
            plain = common.time_fn(lambda: torchvor.voronoi(points, UNIT), device, args.warmup, args.repeats)
            power = common.time_fn(lambda: torchvor.voronoi(points, UNIT, weights=weights), device, args.warmup,
                                   args.repeats)
            if args.profile and n >= 0.99 * max(sizes):
                common.profile_calls([("power voronoi", lambda: torchvor.voronoi(points, UNIT, weights=weights)),
                                      ("power_weights", lambda: torchvor.power_weights(points, UNIT, tol=args.tol))],
                                     device, f"{kind} n={n}", rows=20)
            empty = int((torchvor.voronoi(points, UNIT, weights=weights).status == torchvor.CellStatus.EMPTY).sum())
            common.log(f"{kind} n={n}: power_weights {common.fmt_s(solve_s)} ({solved.iterations} iterations, "
                       f"error {solved.error:.2e}); voronoi {common.fmt_s(plain)}, power {common.fmt_s(power)}, "
                       f"{empty} empty cells")
            rows.append([kind, common.npoints_label(n), common.fmt_s(solve_s), str(solved.iterations),
                         f"{solved.error:.1e}", common.fmt_s(plain), common.fmt_s(power),
                         common.fmt_ratio(power / plain)])
            points = weights = solved = None
    headers = ["points", "n", "power_weights s", "Newton iterations", "error", "voronoi s", "power voronoi s",
               "power / plain"]
    common.print_results("Power diagrams", headers, rows, notes)


if __name__ == "__main__":
    main()
