"""Voronoi and kNN time against the grid's density: TORCHVOR_POINTS_PER_CELL_SCALE
multiplies the points per grid cell that ops::points_per_cell_for picks from k
(k / 16, at least 2). CUDA or CPU.

    python benchmarks/sweep_points_per_cell.py --device cuda [--scales 0.5,0.75,1,1.5,2] [--sizes 10M]

Cases at each size: blue noise (k=24, the benchmark's first pass), a perturbed
grid and white noise (k from the pilot), and the public kNN on a jittered grid
(k=35). Each row: the kNN kernels' GPU time per call (profiler, mean of 3; CPU:
none) and the wall time of the call (median of 3).
"""
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
import torchvor.samples  # noqa: E402

VARIABLE = "TORCHVOR_POINTS_PER_CELL_SCALE"


def knn_kernel_ms(call, device):
    if device.type != "cuda":
        return None
    from crossover import kernel_ms
    return kernel_ms(call, "KnnFunctor", repeats=3)


def main():
    parser = common.base_parser(__doc__)
    parser.add_argument("--scales", default="0.5,0.75,1,1.5,2", help="multipliers of the points per cell")
    args = parser.parse_args()
    device, _ = common.setup(args)
    sizes = args.sizes or [1_000_000]
    scales = [float(s) for s in args.scales.split(",")]
    cases = []
    for n in sizes:
        label = common.npoints_label(n)
        blue, _ = common.make_points("blue", n, seed=0, dtype=torch.float32, device=device, cache_dir=args.cache_dir)
        perturbed = torchvor.samples.perturbed_grid(n, device=device)
        white = torchvor.samples.white_noise(n, device=device)
        jittered = torchvor.samples.jittered_grid(n, device=device)
        cases += [
            (f"voronoi blue {label} k=24", lambda p=blue: torchvor.voronoi(p, common.UNIT_BOX, k=24, on_failure="flag")),
            (f"voronoi perturbed {label}", lambda p=perturbed: torchvor.voronoi(p, common.UNIT_BOX, on_failure="flag")),
            (f"voronoi white {label}", lambda p=white: torchvor.voronoi(p, common.UNIT_BOX, on_failure="flag")),
            (f"knn jittered {label} k=35", lambda p=jittered: torchvor.knn(p, 35)),
        ]
    def measure(call):
        kernel = knn_kernel_ms(call, device)
        wall = common.time_fn(call, device, warmup=1, repeats=3)
        return ["-" if kernel is None else f"{kernel:.2f} ms", common.fmt_s(wall)]

    rows = common.sweep_environment(VARIABLE, scales, cases, measure)
    common.print_results("kNN and voronoi against the grid's points per cell (scale of k / 16, at least 1.5)",
                         ["case", "scale", "kNN kernels", "call"], rows)


if __name__ == "__main__":
    main()
