"""Quick CUDA-vs-CPU agreement and timing check for the GPU machine.

Prints agreement of knn / voronoi between devices on fresh random inputs and
CUDA-event timings of the issue's headline sizes. Not a test: it reports.
"""
import argparse
import os
import sys
import time

import torch

import torchvor
from torchvor import samples

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import common  # noqa: E402  (benchmarks/common.py, shared timing helpers)


def cuda_time(fn, repeats=5):
    """Median milliseconds of fn on the GPU (benchmarks/common.py's timer)."""
    return 1e3 * common.time_fn(fn, "cuda", warmup=1, repeats=repeats)


def parity():
    seed = int(time.time())
    for dtype in (torch.float32, torch.float64):
        pts = samples.white_noise(20000, seed=seed, dtype=dtype)
        d_cpu, i_cpu = torchvor.knn(pts, 35)
        d_gpu, i_gpu = torchvor.knn(pts.cuda(), 35)
        print(f"knn {dtype}: idx equal {torch.equal(i_cpu, i_gpu.cpu())}, dist2 equal {torch.equal(d_cpu, d_gpu.cpu())}")
        c_cpu = torchvor.voronoi(pts, ([0, 0, 0], [1, 1, 1]), on_failure="flag")
        c_gpu = torchvor.voronoi(pts.cuda(), ([0, 0, 0], [1, 1, 1]), on_failure="flag")
        rel = ((c_cpu.volume - c_gpu.volume.cpu()).abs().max() / c_cpu.volume.abs().max()).item()
        print(f"voronoi {dtype}: vol sum cpu {c_cpu.volume.sum().item():.12f} gpu {c_gpu.volume.sum().item():.12f} "
              f"max rel diff {rel:.2e} status equal {torch.equal(c_cpu.status, c_gpu.status.cpu())} "
              f"failed gpu {int(((c_gpu.status != 0) & (c_gpu.status != 5)).sum())}")


def timings(sizes):
    box = ([0, 0, 0], [1, 1, 1])
    for n in sizes:
        for kind, gen, k in (("jittered", samples.jittered_grid, 35), ("perturbed", samples.perturbed_grid, 48),
                             ("white", samples.white_noise, 64)):
            pts = gen(n, seed=1, device="cuda")
            t_knn = cuda_time(lambda: torchvor.knn(pts, 35))
            t_vor = cuda_time(lambda: torchvor.voronoi(pts, box, k=k, on_failure="flag"), repeats=3)
            torch.cuda.reset_peak_memory_stats()
            cells = torchvor.voronoi(pts, box, k=k, on_failure="flag")
            peak = torch.cuda.max_memory_allocated() / 2**20
            print(f"n={pts.shape[0]:>9} {kind:9s} knn(k=35) {t_knn:8.2f} ms  voronoi(k0={k}) {t_vor:8.2f} ms  "
                  f"recovered {int((cells.neighbors > k).sum())} failed {int(((cells.status != 0) & (cells.status != 5)).sum())} "
                  f"vol err {abs(cells.volume.double().sum().item() - 1):.1e} peak {peak:.0f} MiB")


if __name__ == "__main__":
    parser = argparse.ArgumentParser()
    parser.add_argument("--sizes", default="100000,1000000")
    args = parser.parse_args()
    print(torch.cuda.get_device_name(), torch.__version__)
    parity()
    timings([int(s) for s in args.sizes.split(",")])
