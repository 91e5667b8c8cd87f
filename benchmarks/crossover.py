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
import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
import torchvor.samples  # noqa: E402

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
    if not torch.cuda.is_available():
        sys.exit("cells_crossover.py needs CUDA")
    common.print_header(torch.device("cuda"))
    print(f"\n### Clip kernel time against pass size (k={args.k}, jittered grid)")
    print("| cells | thread (ms) | cooperative (ms) | ratio |")
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
