"""Voronoi cells of inputs whose cells reach into empty space: dense clusters with voids
between them, and points in a box far wider than they are. The radius of security asks
such a cell for every point within twice its farthest vertex (up to the whole cloud);
past 256 neighbours torchvor finishes it by the empty balls of its vertices instead
(csrc/core/vertex_balls.h). White noise in its own cube is the reference row.

    python benchmarks/bench_hard_inputs.py [--device cpu|cuda] [--sizes 50K,1M]
        [--kinds voids,clusters,widebox,white] [--vertex-balls-k default,1000000000]

--vertex-balls-k sets TORCHVOR_VERTEX_BALLS_K for each row (10^9: the radius of security
alone, the behaviour before; at 1M points in voids that did not finish in 400 s on an H100).
"""
from __future__ import annotations

import os
import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
from torchvor import samples  # noqa: E402

WIDE_BOX = ([-1.0, -1.0, -1.0], [2.0, 2.0, 2.0])  # three times the unit cube's width
KINDS = {
    "voids": ("20 clusters of 0.02", common.UNIT_BOX),
    "clusters": ("200 clusters of 0.05", common.UNIT_BOX),
    "widebox": ("white noise, box 3x wide", WIDE_BOX),
    "white": ("white noise", common.UNIT_BOX),
}


def make(kind: str, n: int, seed: int, dtype: torch.dtype, device: torch.device) -> torch.Tensor:
    if kind == "voids":
        return samples.clustered(n, clusters=20, spread=0.02, seed=seed, dtype=dtype, device=device)
    if kind == "clusters":
        return samples.clustered(n, clusters=200, spread=0.05, seed=seed, dtype=dtype, device=device)
    return samples.white_noise(n, seed=seed, dtype=dtype, device=device)


def main() -> None:
    parser = common.base_parser(__doc__.splitlines()[0])
    parser.add_argument("--kinds", default="voids,clusters,widebox,white")
    parser.add_argument("--vertex-balls-k", default="default",
                        help="comma-separated TORCHVOR_VERTEX_BALLS_K settings, one row each "
                             "('default': unset, 256)")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [50_000]
    rows = []
    for n in sizes:
        for kind in args.kinds.split(","):
            label, box = KINDS[kind]
            points = make(kind, n, args.seed, dtype, device)
            for most in args.vertex_balls_k.split(","):
                if most == "default":
                    os.environ.pop("TORCHVOR_VERTEX_BALLS_K", None)
                else:
                    os.environ["TORCHVOR_VERTEX_BALLS_K"] = most
                seconds = common.time_fn(lambda: torchvor.voronoi(points, box), device, args.warmup, args.repeats)
                memory, cells = common.measure_memory(lambda: torchvor.voronoi(points, box), device)
                ok = (cells.status == torchvor.CellStatus.SUCCESS) | (cells.status == torchvor.CellStatus.DUPLICATE)
                box_volume = 1.0
                for lo, hi in zip(*box):
                    box_volume *= hi - lo
                volume_error = abs(cells.volume.double().sum().item() / box_volume - 1.0)
                past = int((cells.neighbors > (256 if most == "default" else int(most))).sum())
                rows.append([common.npoints_label(n), label, most, common.fmt_s(seconds),
                             past, int(cells.neighbors.max()), int((~ok).sum()), f"{volume_error:.1e}",
                             common.fmt_mib(memory.work)])
                common.log(*rows[-1])
    os.environ.pop("TORCHVOR_VERTEX_BALLS_K", None)
    common.print_results(
        f"Voronoi on inputs with empty space ({common.device_name(device)}, {args.dtype})",
        ["points", "input", "vertex balls k", "time", "cells past k", "max neighbours", "failed",
         "|sum V / box - 1|", "work memory"],
        rows,
        ["cells past k: finished by the empty balls of their vertices (their `neighbors` counts "
         "the list of k and their further Voronoi neighbours); max neighbours: the most of any cell",
         "work memory: peak beyond inputs and outputs (see common.MEMORY_NOTE)"])


if __name__ == "__main__":
    main()
