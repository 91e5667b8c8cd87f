"""Clip kernel time of one pass against its number of cells, for the two
cell implementations (TORCHVOR_CELLS=thread: one thread per cell;
=cooperative: one warp per cell). CUDA only. The backend's default switches
from the second to the first above CudaExec::kCooperativeCellsUpTo cells;
this table is where that number comes from.

    python benchmarks/cells_crossover.py [--k 48]

Points: a jittered grid (blue-noise-like cells), k large enough that every
cell succeeds in the first pass, so the kernel time is that of one pass.
"""
import argparse
import os

import torch
import torchvor
import torchvor.samples
from torch.profiler import ProfilerActivity, profile

SIZES = [64, 256, 1024, 4096, 16384, 65536, 262144, 1048576]


def clip_ms(points, k, repeats=5):
    call = lambda: torchvor.voronoi(points, ([0, 0, 0], [1, 1, 1]), k=k, on_failure="flag")
    call()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        for _ in range(repeats):
            call()
        torch.cuda.synchronize()
    total = sum(e.device_time_total for e in prof.key_averages() if "ClipFunctor" in e.key)
    return total / 1e3 / repeats


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--k", type=int, default=48)
    args = parser.parse_args()
    print(f"| cells | thread (ms) | cooperative (ms) | ratio |  (k={args.k}, "
          f"{torch.cuda.get_device_name()})")
    print("|---|---|---|---|")
    for n in SIZES:
        points = torchvor.samples.jittered_grid(n, device="cuda", seed=1)
        times = {}
        for impl in ("thread", "cooperative"):
            os.environ["TORCHVOR_CELLS"] = impl
            times[impl] = clip_ms(points, args.k)
        os.environ.pop("TORCHVOR_CELLS")
        print(f"| {n} | {times['thread']:.3f} | {times['cooperative']:.3f} | "
              f"{times['thread'] / times['cooperative']:.2f} |", flush=True)


if __name__ == "__main__":
    main()
