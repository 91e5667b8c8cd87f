"""What the first pass's thread cells do, clip by clip, on the development
machine (no GPU; needs g++): neighbours read, clips, planes that miss the
cell, triangles at a clip, triangles a clip removes, and a model of a warp of
32 consecutive cells in lockstep against lanes that take new cells as they
finish (benchmarks/NOTES.md, twenty-eighth session); then lockstep on warps of
alike cells (windows of cells sorted by their start tetrahedron's radius);
then the clips in grid-shell order (candidates from a grid, not the kNN list).

    python benchmarks/clip_shape.py [--size 100K] [--kind blue] [--k 19]

The points are put in the op's grid order (torchvor's own), their k nearest
neighbours come from torchvor.knn, and benchmarks/clip_shape.cpp runs
core::compute_cell on every cell with a counting cell type.
"""
import argparse
import subprocess
import sys
import tempfile
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
from torchvor.ops import _voronoi_in_grid_order, as_box  # noqa: E402

HERE = Path(__file__).resolve().parent


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--size", type=common.parse_size, default=100_000)
    parser.add_argument("--kind", default="blue", choices=("blue", "white", "perturbed", "jittered"))
    parser.add_argument("--k", type=int, default=19, help="the first pass's k (the pilot's on blue noise: ~19)")
    args = parser.parse_args()

    points, label = common.make_points(args.kind, args.size, seed=0, dtype=torch.float32,
                                       device=torch.device("cpu"), cache_dir=HERE / ".cache")
    n = points.shape[0]
    _, order = _voronoi_in_grid_order(points, as_box(points, common.UNIT_BOX), k=args.k)
    in_grid_order = points[order].contiguous()
    neighbors = torchvor.knn(in_grid_order, args.k).idx.to(torch.int32).contiguous()
    common.log(f"{label}, {n} points, k={args.k}")
    with tempfile.TemporaryDirectory() as work:
        in_grid_order.numpy().tofile(f"{work}/points.bin")
        neighbors.numpy().tofile(f"{work}/neighbors.bin")
        program = f"{work}/clip_shape"
        subprocess.run(["g++", "-O2", "-std=c++17", f"-I{HERE.parent / 'csrc'}", "-o", program,
                        str(HERE / "clip_shape.cpp")], check=True)
        subprocess.run([program, work, str(n), str(args.k)], check=True)


if __name__ == "__main__":
    main()
