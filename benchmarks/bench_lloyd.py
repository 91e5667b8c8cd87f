"""Lloyd relaxation in the unit cube (torchvor.lloyd): one iteration on relaxed
(blue-noise) points, and N iterations from white noise (total and
per-iteration times).

    python benchmarks/bench_lloyd.py [--device cpu|cuda] [--sizes 1M,10M] [--iters 100]
"""
from __future__ import annotations

import statistics
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402


def adapted_k(points) -> int:
    """First-pass k a long Lloyd run settles on for these points: 99th percentile of the
    neighbours their cells need, plus 2 (torchvor.lloyd's rule)."""
    cells = torchvor.voronoi(points, common.UNIT_BOX, k=64, on_failure="flag")
    return common.neighbor_percentiles(cells.neighbors_needed, (0.99,))[0] + 2


def one_iteration(args, device, dtype, n):
    """Row of the one-iteration table: blue points, adapted (or --k) first-pass k."""
    points, label = common.make_points("blue", n, seed=args.seed, dtype=dtype, device=device,
                                       cache_dir=args.cache_dir, blue_iters=args.blue_iters)
    k = args.k or adapted_k(points)
    seconds = common.time_fn(lambda: torchvor.lloyd(points, common.UNIT_BOX, iters=1, k=k), device,
                             args.warmup, args.repeats)
    cells_only = common.time_fn(lambda: torchvor.voronoi(points, common.UNIT_BOX, k=k, on_failure="flag"),
                                device, args.warmup, args.repeats)
    row = [label, common.npoints_label(points.shape[0]), k, common.fmt_s(seconds), common.fmt_s(cells_only),
           common.fmt_s(seconds - cells_only)]
    common.log(" | ".join(map(str, row)))
    return row


def relaxation(args, device, dtype, n, iters):
    """Row of the N-iteration table: white noise relaxed by ``iters`` iterations."""
    points, _ = common.make_points("white", n, seed=args.seed, dtype=dtype, device=device, cache_dir=args.cache_dir)
    torchvor.lloyd(points, common.UNIT_BOX, iters=1)  # warm-up
    common.synchronize(device)
    watch = common.Stopwatch(device)
    watch.mark()
    _, history = torchvor.lloyd(points, common.UNIT_BOX, iters=iters, k=args.k, return_history=True)
    watch.mark()
    total = watch.steps()[0]
    steps = [h.seconds for h in history]
    ks = [h.k for h in history]
    energy = (history[0].energy, history[-1].energy)
    failed = sum(h.failed for h in history)
    common.log(f"n={n:,} per-iteration seconds: " + " ".join(f"{s:.3g}" for s in steps))
    if len(set(ks)) > 1:
        common.log(f"n={n:,} per-iteration k: " + " ".join(map(str, ks)))
    row = [common.npoints_label(points.shape[0]), len(steps), common.fmt_s(total),
           common.fmt_s(statistics.median(steps)), common.fmt_s(steps[0]), common.fmt_s(steps[-1]),
           f"{common.fmt_s(min(steps))} / {common.fmt_s(max(steps))}", f"{ks[0]}→{ks[-1]}",
           f"{energy[0]:.4e}→{energy[1]:.4e}", failed]
    common.log(" | ".join(map(str, row)))
    return row


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--iters", type=int, default=None,
                        help="iterations from white noise (default 100 on cuda, 10 on cpu)")
    parser.add_argument("--k", type=int, default=None,
                        help="fixed first-pass k (default: adapted, as torchvor.lloyd does)")
    parser.add_argument("--skip-one", action="store_true", help="skip the one-iteration (blue noise) table")
    parser.add_argument("--skip-relax", action="store_true", help="skip the N-iteration (white noise) table")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [1_000_000]
    iters = args.iters or (100 if device.type == "cuda" else 10)
    timing = f"{args.dtype}, unit cube; medians of {args.repeats} runs after {args.warmup} warm-up run(s)"
    if not args.skip_one:
        rows = [one_iteration(args, device, dtype, n) for n in sizes]
        common.print_results(
            "One Lloyd iteration on blue noise",
            ["points", "n", "k", "1 iteration", "voronoi alone", "Lloyd overhead"], rows,
            [f"{timing}. blue = white noise after {args.blue_iters} Lloyd iterations (cached).",
             "1 iteration = torchvor.lloyd(points, box, iters=1, k=k); "
             f"k = {'--k' if args.k else '99th percentile of neighbours needed + 2'}; "
             "voronoi alone = torchvor.voronoi at the same k; overhead = the difference."])
    if not args.skip_relax:
        rows = [relaxation(args, device, dtype, n, iters) for n in sizes]
        common.print_results(
            f"{iters} Lloyd iterations from white noise",
            ["n", "iterations", "total", "per iteration (median)", "first", "last", "min / max",
             "k first→last", "energy first→last", "failed cells"], rows,
            [f"{args.dtype}, unit cube; one timed run after a 1-iteration warm-up.",
             "torchvor.lloyd(iters=N, return_history=True); per-iteration times from its history; "
             "k adapts per iteration unless --k is given.",
             "energy = CVT energy before the first / last move."])


if __name__ == "__main__":
    main()
