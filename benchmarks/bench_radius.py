"""The radius graph of every point (self excluded): torchvor.radius_graph against
scipy's cKDTree.query_pairs (build + query, every pair once; torchvor gives both
directions, sorted).

    python benchmarks/bench_radius.py [--device cpu|cuda] [--sizes 100K,1M] [--neighbors 16,64]

r is set so that a point of white noise in the unit cube has about `neighbors`
points within r on average (4/3 pi r^3 n = neighbors).
"""
from __future__ import annotations

import math
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402

try:
    from scipy.spatial import cKDTree
except ImportError:
    cKDTree = None


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--neighbors", type=common.parse_ints, default=[16, 64],
                        help="comma-separated mean neighbour counts (each sets r)")
    parser.add_argument("--baseline-repeats", type=int, default=3, help="timed runs of cKDTree")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [100_000, 1_000_000]
    notes = [f"white noise in the unit cube, {args.dtype}; torchvor: median of {args.repeats} runs after "
             f"{args.warmup} warm-up run(s), both directions of every pair, sorted by centre then distance.",
             f"cKDTree: build + query_pairs(r, output_type='ndarray') on a float64 NumPy copy made before "
             f"timing (one core: query_pairs takes no workers), median of {args.baseline_repeats}; each pair once."]
    rows = []
    for n in sizes:
        points, _ = common.make_points("white", n, seed=args.seed, dtype=dtype, device=device,
                                       cache_dir=args.cache_dir)
        n = points.shape[0]
        points_np = points.cpu().double().numpy() if cKDTree is not None else None
        for neighbors in args.neighbors:
            r = (3 * neighbors / (4 * math.pi * n)) ** (1 / 3)
            times = {"torchvor": common.time_fn(lambda: torchvor.radius_graph(points, r), device, args.warmup,
                                                args.repeats)}
            edges = torchvor.radius_graph(points, r).shape[1]
            common.log(f"n={n} r={r:.4g} ({edges / n:.1f} a point) torchvor {common.fmt_s(times['torchvor'])}")
            if cKDTree is not None:
                times["cKDTree"] = common.time_fn(
                    lambda: cKDTree(points_np).query_pairs(r, output_type="ndarray"), "cpu", 0,
                    args.baseline_repeats)
                common.log(f"n={n} r={r:.4g} cKDTree {common.fmt_s(times['cKDTree'])}")
            base = times.get("cKDTree")
            for method, seconds in times.items():
                rows.append([common.npoints_label(n), f"{r:.4g}", f"{edges / n:.1f}", method, common.fmt_s(seconds),
                             common.fmt_ratio(base / seconds if base else None)])
        points = points_np = None
    common.print_results("Radius graph", ["n", "r", "edges a point", "method", "seconds (median)",
                                          "speed-up vs cKDTree"], rows, notes)


if __name__ == "__main__":
    main()
