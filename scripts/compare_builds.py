"""Checks that two builds of torchvor give bit-identical outputs (a refactor's proof).

Runs a fixed battery of inputs (point kinds, dtypes, batches, boxes, duplicates,
and every internal tuning variable) through the ops of the torchvor that is
importable, and saves every output; then compares two such files bit for bit.

    python scripts/compare_builds.py run OUT.pt [--device cuda]
    python scripts/compare_builds.py compare A.pt B.pt
    python scripts/compare_builds.py time POINTS.pt... [--device cuda]   (voronoi_cells, median ms)

To compare against another build, run the first command once with that build
first on PYTHONPATH (e.g. an unpacked checkout with its own built _C).
"""
from __future__ import annotations

import argparse
import os
import sys

import torch

# The internal tuning variables (docs/design.md): each must change no result
# beyond what it is documented to change, and a refactor must change none.
VARIANTS = [
    {},
    {"TORCHVOR_CELLS": "thread"},
    {"TORCHVOR_CELLS": "cooperative"},
    {"TORCHVOR_KNN": "cooperative"},
    {"TORCHVOR_KNN": "thread"},
    {"TORCHVOR_CELL_START": "box"},
    {"TORCHVOR_THREAD_TRIANGLES": "full"},
    {"TORCHVOR_SPECULATIVE_CELLS": "0"},
    {"TORCHVOR_SPECULATIVE_CELLS": "7"},
    {"TORCHVOR_VERTEX_BALLS_K": "24"},
    {"TORCHVOR_PILOT_QUANTILE": "0.5"},
    {"TORCHVOR_POINTS_PER_CELL_SCALE": "2.5"},
    {"TORCHVOR_CPU_ISA": "baseline"},
    {"TORCHVOR_CELL_BLOCKS_PER_SM": "2"},
    {"TORCHVOR_TEST_SCATTER_BYTES": "64"},
    {"TORCHVOR_TEST_UNWRITTEN_CELL": "5"},
]


def point_sets(device):
    from torchvor import samples

    g = torch.Generator().manual_seed(1234)
    sets = {
        "white": samples.white_noise(3000, seed=1, dtype=torch.float64),
        "clusters": samples.clustered(3000, clusters=6, spread=0.01, seed=2, dtype=torch.float64),
        "perturbed": samples.perturbed_grid(2744, seed=3, dtype=torch.float64),
        "lattice": samples.lattice(9),
    }
    clamped = (torch.randn(3000, 3, generator=g, dtype=torch.float64) * 0.3 + 0.5).clamp(0, 1)
    sets["clamped"] = clamped
    dup = torch.rand(800, 3, generator=g, dtype=torch.float64)
    sets["duplicates"] = torch.cat([dup, dup[:200]])
    sets["voids"] = torch.cat([torch.rand(500, 3, generator=g, dtype=torch.float64) * 0.1,
                               torch.rand(500, 3, generator=g, dtype=torch.float64) * 0.1 + 0.9])
    return {name: p.to(device) for name, p in sets.items()}


def run(device: str):
    import torchvor

    print(f"torchvor from {torchvor.__file__}")

    ops = torch.ops.torchvor
    out = {}
    sets = point_sets(device)
    unit = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], dtype=torch.float64, device=device)
    wide = torch.tensor([[[-1.0, -0.5, 0.0], [2.0, 1.5, 3.0]]], dtype=torch.float64, device=device)
    for variant in VARIANTS:
        for key, value in variant.items():
            os.environ[key] = value
        try:
            tag = ",".join(f"{k[9:]}={v}" for k, v in variant.items()) or "default"
            for name, points64 in sets.items():
                for dtype in (torch.float32, torch.float64):
                    points = points64.to(dtype)
                    for box_name, box in (("unit", unit), ("wide", wide)):
                        if box_name == "wide" and name not in ("white", "clusters"):
                            continue
                        b = box.to(dtype)
                        for k in (None, 12):
                            key = f"{tag}/{name}/{dtype}/{box_name}/k={k}"
                            out[key + "/voronoi"] = ops.voronoi_cells(points, b, None, k)
                            if name == "white" and box_name == "unit":
                                out[key + "/grid_order"] = ops.voronoi_cells_grid_order(points, b, None, k)
                                out[key + "/lloyd_step"] = ops.lloyd_step(points, b, None, k, 7, 64)
                    if name in ("white", "duplicates"):
                        out[f"{tag}/{name}/{dtype}/knn"] = ops.knn(points, points, 17, None, None, True)
                        out[f"{tag}/{name}/{dtype}/knn_queries"] = ops.knn(points, points[::3].contiguous() * 0.9,
                                                                          5, None, None, False)
            # Batches of three clouds with their own boxes.
            points = sets["white"].to(torch.float32)
            batch = torch.repeat_interleave(torch.arange(3, device=device), torch.tensor([1000, 1500, 500],
                                                                                          device=device))
            boxes = unit.to(torch.float32).repeat(3, 1, 1)
            out[f"{tag}/batch/voronoi"] = ops.voronoi_cells(points, boxes, batch, None)
            out[f"{tag}/batch/knn"] = ops.knn(points, points, 9, batch, batch, True)
        finally:
            for key in variant:
                del os.environ[key]
    return out


def compare(a_path: str, b_path: str) -> int:
    a = torch.load(a_path)
    b = torch.load(b_path)
    bad = 0
    for key in sorted(set(a) | set(b)):
        if key not in a or key not in b:
            print(f"missing in one file: {key}")
            bad += 1
            continue
        for i, (x, y) in enumerate(zip(a[key], b[key])):
            if x.shape != y.shape or x.dtype != y.dtype:
                print(f"{key}[{i}]: shape/dtype {tuple(x.shape)} {x.dtype} vs {tuple(y.shape)} {y.dtype}")
                bad += 1
            elif x.is_floating_point():
                bits = {4: torch.int32, 8: torch.int64}[x.element_size()]
                if not torch.equal(x.view(bits), y.view(bits)):
                    differ = x.view(bits) != y.view(bits)
                    xs, ys = x[differ].double(), y[differ].double()
                    both = torch.isfinite(xs) & torch.isfinite(ys)
                    relative = ((xs - ys).abs() / ys.abs().clamp_min(1e-300))[both]
                    worst = f", largest relative difference {relative.max().item():.2e}" if relative.numel() else ""
                    print(f"{key}[{i}]: floating bits differ in {int(differ.sum())} of {x.numel()}{worst}")
                    bad += 1
            elif not torch.equal(x, y):
                print(f"{key}[{i}]: values differ")
                bad += 1
    outputs = sum(len(v) for v in a.values())
    print(f"compared {len(a)} calls, {outputs} outputs: {bad} differ")
    return 1 if bad else 0


def time_calls(paths, device: str, repeats: int = 15, dtype: str = "float32") -> None:
    """Median time of a voronoi_cells call (the op's default k) on each saved point set, in `dtype`."""
    import statistics
    import time

    import torchvor

    print(f"torchvor from {torchvor.__file__}")
    for path in paths:
        points = torch.load(path).to(device=device, dtype=getattr(torch, dtype)).contiguous()
        box = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]]], device=device, dtype=points.dtype)
        times = []
        for i in range(repeats + 3):
            if device == "cuda":
                start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
                start.record()
                torch.ops.torchvor.voronoi_cells(points, box, None, None)
                end.record()
                end.synchronize()
                elapsed = start.elapsed_time(end)
            else:
                begin = time.perf_counter()
                torch.ops.torchvor.voronoi_cells(points, box, None, None)
                elapsed = 1e3 * (time.perf_counter() - begin)
            if i >= 3:
                times.append(elapsed)
        print(f"{path} ({dtype}): median {statistics.median(times):.3f} ms, min {min(times):.3f} ms over {repeats}")


def main(argv=None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = parser.add_subparsers(dest="command", required=True)
    r = sub.add_parser("run")
    r.add_argument("out")
    r.add_argument("--device", default="cpu")
    c = sub.add_parser("compare")
    c.add_argument("a")
    c.add_argument("b")
    t = sub.add_parser("time")
    t.add_argument("points", nargs="+")
    t.add_argument("--device", default="cpu")
    t.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    args = parser.parse_args(argv)
    if args.command == "time":
        time_calls(args.points, args.device, dtype=args.dtype)
        return 0
    if args.command == "run":
        outputs = run(args.device)
        torch.save({k: tuple(t.cpu() for t in v) for k, v in outputs.items()}, args.out)
        print(f"{len(outputs)} calls written to {args.out}")
        return 0
    return compare(args.a, args.b)


if __name__ == "__main__":
    sys.exit(main())
