"""Kernel time of one pass against its size, for the two implementations of
each pass: one thread per item, or one warp per item (cooperative). CUDA only.
The backend's defaults switch from warp to thread above
CudaExec::kCooperativeCellsUpTo cells and kCooperativeQueriesUpTo queries;
these tables are where those numbers come from.

    python benchmarks/crossover.py [--op cells|knn|k|all] [--k 48] [--knn-k 28]

cells (TORCHVOR_CELLS): the clip kernel of a voronoi call on a jittered grid
of that many points, k large enough that every cell succeeds in the first
pass, so the kernel time is that of one pass.
knn (TORCHVOR_KNN): the kNN kernel of torchvor.knn(points, k, queries) with
that many queries (points of the set itself) in a fixed 1M jittered grid, as
a retry pass inside voronoi searches a few cells of a large grid.
k (TORCHVOR_CELLS): the wall time of a whole voronoi call on 1M points of
each kind against its first-pass k (median of 5, CUDA events): how the cost
of a cell by either implementation grows with its neighbours.
kinds (TORCHVOR_CELLS): clip kernel and wall time of a voronoi call, thread
against warp cells, on many kinds of point sets (grids jittered by several
amplitudes, clusters, Lloyd's early iterates of white noise) at the k the
op's pilot would pick, beside statistics of the neighbours their cells need
as the pilot sees them (about 1024 cells, capped at the pilot's k = 64):
which statistic tells the sets that favour warps from the others.
"""
import argparse
import os
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
import torchvor.samples  # noqa: E402

SIZES = [64, 256, 1024, 4096, 16384, 65536, 262144, 1048576]


def kernel_ms(call, kernel_name, repeats=5):
    """GPU time of the kernels whose name has `kernel_name`, per call."""
    call()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(repeats):
            call()
        torch.cuda.synchronize()
    total = sum(e.device_time_total for e in prof.key_averages() if kernel_name in e.key)
    return total / 1e3 / repeats


def table(title, variable, sizes, call_for, kernel_name):
    print(f"\n### {title}")
    print("| size | thread (ms) | cooperative (ms) | ratio |")
    print("|---|---|---|---|")
    for n in sizes:
        call = call_for(n)
        times = {}
        for impl in ("thread", "cooperative"):
            os.environ[variable] = impl
            times[impl] = kernel_ms(call, kernel_name)
        os.environ.pop(variable)
        print(f"| {n} | {times['thread']:.3f} | {times['cooperative']:.3f} | "
              f"{times['thread'] / times['cooperative']:.2f} |", flush=True)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--op", choices=["cells", "knn", "k", "kinds", "all"], default="all")
    parser.add_argument("--sizes", type=common.parse_sizes, default=[1 << 20],
                        help="point counts of the kinds table (e.g. 1M,10M)")
    parser.add_argument("--kinds", type=lambda text: text.split(","), default=list(KIND_NAMES),
                        help="comma-separated point sets of the kinds table (above 1M only those of LARGE_KINDS)")
    parser.add_argument("--k", type=int, default=48, help="neighbours per cell (cells)")
    parser.add_argument("--knn-k", type=int, default=28, help="neighbours per query (knn)")
    args = parser.parse_args()
    if not torch.cuda.is_available():
        sys.exit("crossover.py needs CUDA")
    common.print_header(torch.device("cuda"))
    if args.op in ("cells", "all"):
        def cells_call(n):
            points = torchvor.samples.jittered_grid(n, device="cuda", seed=1)
            return lambda: torchvor.voronoi(points, ([0, 0, 0], [1, 1, 1]), k=args.k, on_failure="flag")
        table(f"Clip kernel time against pass size (k={args.k}, jittered grid)", "TORCHVOR_CELLS",
              SIZES, cells_call, "ClipFunctor")
    if args.op in ("knn", "all"):
        grid = torchvor.samples.jittered_grid(1 << 20, device="cuda", seed=2)
        order = torch.randperm(grid.shape[0], device="cuda", generator=torch.Generator("cuda").manual_seed(3))

        def knn_call(n):
            queries = grid[order[:n]]
            return lambda: torchvor.knn(grid, args.knn_k, queries)
        table(f"kNN kernel time against queries (k={args.knn_k}, 1M jittered grid)", "TORCHVOR_KNN",
              SIZES, knn_call, "KnnFunctor")
    if args.op in ("k", "all"):
        k_table()
    if args.op in ("kinds", "all"):
        for n in args.sizes:
            kinds_table(n, args.kinds if n <= 1 << 20 else [name for name in args.kinds if name in LARGE_KINDS])


def k_table():
    print("\n### voronoi wall time against first-pass k (1M points)")
    print("| points | k | thread (ms) | cooperative (ms) | ratio |")
    print("|---|---|---|---|---|")
    box = ([0, 0, 0], [1, 1, 1])
    sets = {"white": torchvor.samples.white_noise(1 << 20, device="cuda", seed=4),
            "perturbed": torchvor.samples.perturbed_grid(1 << 20, device="cuda", seed=4),
            "blue": torchvor.samples.blue_noise(1 << 20, device="cuda", seed=4)}
    for kind, points in sets.items():
        for k in (24, 32, 40, 48, 56, 64, 80):
            times = {}
            for impl in ("thread", "cooperative"):
                os.environ["TORCHVOR_CELLS"] = impl
                call = lambda: torchvor.voronoi(points, box, k=k, on_failure="flag")
                times[impl] = 1e3 * common.time_fn(call, torch.device("cuda"), warmup=1, repeats=5)
            os.environ.pop("TORCHVOR_CELLS")
            print(f"| {kind} | {k} | {times['thread']:.2f} | {times['cooperative']:.2f} | "
                  f"{times['thread'] / times['cooperative']:.2f} |", flush=True)


LARGE_KINDS = ("white", "perturbed", "jittered 0.6", "jittered 0.8", "lloyd 1")  # the only ones above 1M
KIND_NAMES = ("white", "perturbed", "jittered 0.25", "jittered 0.35", "jittered 0.45", "jittered 0.6",
              "jittered 0.8", "jittered 1.0", "clustered 200 x 0.05", "clustered 1000 x 0.05",
              "clustered 200 x 0.1", "lloyd 1", "lloyd 2", "lloyd 4", "lloyd 8", "blue")


def point_set(name, n):
    """The named set of about n points on the GPU: the benchmark kinds and kinds in between
    (jittered by an amplitude in grid spacings, Gaussian clusters of a spread, white noise
    after a few Lloyd iterations). Clusters of 0.02 are left out: their cells in the voids
    need thousands of neighbours (benchmarks/NOTES.md)."""
    from torchvor.lloyd import lloyd

    samples = torchvor.samples
    kind, _, rest = name.partition(" ")
    if kind == "white":
        return samples.white_noise(n, device="cuda", seed=4)
    if kind == "perturbed":
        return samples.perturbed_grid(n, device="cuda", seed=4)
    if kind == "jittered":
        return samples.jittered_grid(n, amplitude=float(rest), device="cuda", seed=4)
    if kind == "clustered":
        clusters, _, spread = rest.partition(" x ")
        return samples.clustered(n, clusters=int(clusters), spread=float(spread), device="cuda", seed=4)
    iters = 100 if kind == "blue" else int(rest)
    return lloyd(samples.white_noise(n, device="cuda", seed=5), common.UNIT_BOX, iters=iters)


def pilot_statistics(needed, cap=64, quantile=0.98):
    """What the op's pilot sees: every (n // 1024)-th cell's neighbours needed, capped at its k;
    k is the op's choice from them (voronoi.h's run_pilot: the `quantile` share plus 2; the
    tables in RESULTS.md up to 05fc6fc used the 90th percentile, as the op did then)."""
    sample = needed[:: max(1, needed.numel() // 1024)].clamp(max=cap).float()
    q = torch.quantile(sample, torch.tensor([0.25, 0.5, 0.75, 0.9, quantile], device=sample.device)).tolist()
    return {"p25": q[0], "p50": q[1], "p75": q[2], "p90": q[3], "k": min(256, max(8, int(q[4]) + 2)),
            "p90/p50": q[3] / q[1], "p75/p25": q[2] / q[0], "cv": (sample.std() / sample.mean()).item()}


def kinds_table(n, names):
    print(f"\n### thread against warp cells by kind of point set ({n} points, the pilot's k)")
    print("| points | p25/p50/p75/p90 | p90/p50 | p75/p25 | cv | k | clip thread / warp (ms) | ratio "
          "| voronoi thread / warp (ms) | ratio |")
    print("|---|---|---|---|---|---|---|---|---|---|")
    box = common.UNIT_BOX
    device = torch.device("cuda")
    for name in names:
        points = point_set(name, n)
        needed = torchvor.voronoi(points, box, on_failure="flag").neighbors
        stats = pilot_statistics(needed)
        clip, wall = {}, {}
        for impl in ("thread", "cooperative"):
            os.environ["TORCHVOR_CELLS"] = impl
            call = lambda: torchvor.voronoi(points, box, k=stats["k"], on_failure="flag")  # noqa: E731
            clip[impl] = kernel_ms(call, "ClipFunctor", repeats=3)
            wall[impl] = 1e3 * common.time_fn(call, device, warmup=1, repeats=5)
        os.environ.pop("TORCHVOR_CELLS")
        print(f"| {name} | {stats['p25']:.0f}/{stats['p50']:.0f}/{stats['p75']:.0f}/{stats['p90']:.0f} "
              f"| {stats['p90/p50']:.2f} | {stats['p75/p25']:.2f} | {stats['cv']:.3f} | {stats['k']} "
              f"| {clip['thread']:.2f} / {clip['cooperative']:.2f} | {clip['thread'] / clip['cooperative']:.2f} "
              f"| {wall['thread']:.2f} / {wall['cooperative']:.2f} | {wall['thread'] / wall['cooperative']:.2f} |",
              flush=True)
        del points


if __name__ == "__main__":
    main()
