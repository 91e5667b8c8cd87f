"""The Voronoi graph and the cells' backward against the cells alone: torchvor.voronoi_graph,
voronoi, and the backward of voronoi(...).volume.sum(), on the same points.

    python benchmarks/bench_graph.py [--device cpu|cuda] [--sizes 100K,1M] [--kinds blue,white] [--voro] [--profile]

--voro also times voro++ (pyvoro2, one core, float64) computing each cell's faces: their
neighbours and vertices (voro++ gives no face areas through pyvoro2; computing them from
the vertices is not charged to it). --profile prints where one voronoi_graph call and one
backward spend their time (torch.profiler, the largest size of each kind).
"""
from __future__ import annotations

import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torch  # noqa: E402
import torchvor  # noqa: E402

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def voro_faces(points):
    """Seconds of voro++ (pyvoro2's native call, one run) computing every cell's
    faces (neighbours and vertices) in the unit cube, or None without pyvoro2."""
    try:
        import numpy as np
        from pyvoro2 import _core as core
    except ImportError:
        return None
    pts = points.detach().cpu().double().numpy()
    hi = float(np.nextafter(1.0, 2.0))  # voro++ wants points in [lo, hi)
    bounds = ((0.0, hi),) * 3
    blocks = (max(1, int(len(pts) ** (1 / 3) / 2.5)),) * 3
    ids = np.arange(len(pts), dtype=np.int32)
    return common.time_fn(lambda: core.compute_box_standard(pts, ids, bounds, blocks, (False,) * 3, 8,
                                                            (True, True, True)), "cpu", 0, 1)


def profile(points, leaf, device, label):
    """Print the operators and kernels of one voronoi_graph call and one backward, by self time."""
    from torch.profiler import ProfilerActivity, profile as torch_profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    for name, fn in (("voronoi_graph", lambda: torchvor.voronoi_graph(points, UNIT)),
                     ("backward", lambda: torch.autograd.grad(torchvor.voronoi(leaf, UNIT).volume.sum(), leaf))):
        with torch_profile(activities=activities) as prof:
            fn()
            if device.type == "cuda":
                torch.cuda.synchronize()
        common.log(f"profile of {name}, {label}:\n" + prof.key_averages().table(sort_by=sort, row_limit=18,
                                                                                 max_name_column_width=70))


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default="blue,white", help="comma-separated: blue, white, perturbed")
    parser.add_argument("--voro", action="store_true", help="also time voro++ (pyvoro2) computing the faces")
    parser.add_argument("--profile", action="store_true", help="profile one graph and one backward call")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [100_000, 1_000_000]
    notes = [f"points in the unit cube, {args.dtype}, default k (the pilot's); median of {args.repeats} runs "
             f"after {args.warmup} warm-up run(s). backward: forward + backward of volume.sum() "
             f"(centroid backward: of centroid.sum()), less the forward's median."]
    rows = []
    for kind in args.kinds.split(","):
        for n in sizes:
            points, _ = common.make_points(kind, n, seed=args.seed, dtype=dtype, device=device,
                                           cache_dir=args.cache_dir)
            n = points.shape[0]
            cells = common.time_fn(lambda: torchvor.voronoi(points, UNIT), device, args.warmup, args.repeats)
            graph = common.time_fn(lambda: torchvor.voronoi_graph(points, UNIT), device, args.warmup, args.repeats)
            edges = torchvor.voronoi_graph(points, UNIT).edge_index.shape[1]
            leaf = points.detach().requires_grad_()
            backward = common.time_fn(lambda: torch.autograd.grad(torchvor.voronoi(leaf, UNIT).volume.sum(), leaf),
                                      device, args.warmup, args.repeats) - cells
            # the centroid's gradient needs the faces' moments too
            centroid_backward = common.time_fn(
                lambda: torch.autograd.grad(torchvor.voronoi(leaf, UNIT).centroid.sum(), leaf),
                device, args.warmup, args.repeats) - cells
            common.log(f"{kind} n={n}: voronoi {common.fmt_s(cells)}, voronoi_graph {common.fmt_s(graph)}, "
                       f"backward of volume.sum() {common.fmt_s(backward)}, "
                       f"of centroid.sum() {common.fmt_s(centroid_backward)}")
            if args.profile and n >= 0.99 * max(sizes):
                profile(points, leaf, device, f"{kind} n={n}")
            voro = voro_faces(points) if args.voro else None
            if voro is not None:
                common.log(f"{kind} n={n}: voro++ faces {common.fmt_s(voro)}")
            rows.append([kind, common.npoints_label(n), f"{edges / n:.2f}", common.fmt_s(cells), common.fmt_s(graph),
                         common.fmt_ratio(graph / cells), common.fmt_s(backward), common.fmt_ratio(backward / cells),
                         common.fmt_s(centroid_backward), common.fmt_ratio(centroid_backward / cells),
                         common.fmt_s(voro), common.fmt_ratio(voro / graph if voro else None)])
            points = None
    common.print_results("Voronoi graph", ["points", "n", "edges a point", "voronoi s", "voronoi_graph s",
                                           "graph / cells", "backward s", "backward / cells",
                                           "centroid backward s", "centroid backward / cells", "voro++ faces s",
                                           "graph speed-up vs voro++"], rows, notes)


if __name__ == "__main__":
    main()
