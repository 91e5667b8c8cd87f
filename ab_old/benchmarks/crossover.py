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
    parser.add_argument("--op", choices=["cells", "knn", "k", "all"], default="all")
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


if __name__ == "__main__":
    main()
