"""Clip kernel time against how many blocks of one-thread-per-cell clipping
stay resident on an SM (TORCHVOR_CELL_BLOCKS_PER_SM; CudaExec::for_each_cell
picks a default from the kernel's stack frame and the pass's k: three
quarters as many from k = 28). CUDA only.

    python benchmarks/sweep_cell_residency.py [--blocks 1,2,3,4,5,6,8] [--sizes 1M,10M]  (default 1M)

Cases: blue noise in float32 (k=24) at each size, blue noise in float64 and
a jittered grid (k=32) at the first size: every first pass there runs one
thread per cell (k < CudaExec::kCooperativeCellsFromK). Each row: the clip
kernels' GPU time per call (profiler, mean of 5) and the wall time of the
voronoi call (CUDA events, median of 5); "default" is the cap the backend
chooses.
"""
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
from crossover import kernel_ms  # noqa: E402
import torchvor  # noqa: E402
import torchvor.samples  # noqa: E402

VARIABLE = "TORCHVOR_CELL_BLOCKS_PER_SM"


def main():
    parser = common.base_parser(__doc__)
    parser.add_argument("--blocks", default="1,2,3,4,5,6,8", help="settings to sweep besides the default")
    args = parser.parse_args()
    device, _ = common.setup(args)
    assert device.type == "cuda", "the residency cap exists on CUDA only"
    sizes = args.sizes or [1_000_000]
    settings = [None] + common.parse_ints(args.blocks)
    cases = []
    for i, n in enumerate(sizes):
        blue, _ = common.make_points("blue", n, seed=0, dtype=torch.float32, device=device, cache_dir=args.cache_dir)
        cases.append((f"blue {common.npoints_label(n)} float32", blue, 24))
        if i == 0:
            cases.append((f"blue {common.npoints_label(n)} float64", blue.double(), 24))
            jittered = torchvor.samples.jittered_grid(n, device=device)
            cases.append((f"jittered {common.npoints_label(n)} float32", jittered, 32))

    def measure(call):
        clip = kernel_ms(call, "ClipFunctor")
        return [f"{clip:.2f} ms", common.fmt_s(common.time_fn(call, device, warmup=1, repeats=5))]

    calls = [(name, lambda p=points, k=k: torchvor.voronoi(p, common.UNIT_BOX, k=k, on_failure="flag"))
             for name, points, k in cases]
    rows = common.sweep_environment(VARIABLE, settings, calls, measure)
    common.print_results("Clip kernel against resident blocks of 128 threads per SM",
                         ["case", "blocks / SM", "clip kernels", "voronoi"], rows)


if __name__ == "__main__":
    main()
