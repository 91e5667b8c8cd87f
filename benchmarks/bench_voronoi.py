"""Voronoi cells (volume, centroid, second moment) of every point in the unit
cube: torchvor.voronoi on white noise, perturbed grid and blue noise, with its
kNN part, recovery and failure counts, volume error, memory, and voro++
(through pyvoro2, CPU only, volumes only) for comparison.

    python benchmarks/bench_voronoi.py [--device cpu|cuda] [--sizes 100K,1M,10M]
                                       [--kinds white,perturbed,blue] [--k 0,64] [--lloyd-iteration]

By default each point set gets two rows: the op's own first-pass k (k=None:
a pilot sample picks it; what a caller who passes no k gets), then a fixed k
by kind (DEFAULT_K), whose rows also time the kNN alone and count the
recovered cells.
"""
from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402

# First-pass k by kind, from the neighbours cells need (50/95/99/100th percentiles at 100K
# points: white 40/68/84/156, perturbed 31/44/51/71, jittered 23/28/30/39; blue noise at
# 20K: 14/16/17/20): about the 95th percentile for white noise, at or above the 99th for
# the others. Sweep with --k on the target machine. Rows at these k show the kNN's share
# and the recovered cells, which the op's own k (its pilot's choice) does not expose.
DEFAULT_K = {"white": 64, "uniform": 64, "perturbed": 48, "jittered": 32, "blue": 24}


def voro_pp(points: torch.Tensor):
    """voro++ via pyvoro2 on the points in the unit cube.

    Returns {"compute": seconds of pyvoro2.compute, "core": seconds of its native
    voro++ call alone, "volume": per-point volumes}, or a string saying why not.
    """
    try:
        import pyvoro2
    except ImportError:
        return "pyvoro2 not importable (pip install pyvoro2)"
    pts = points.detach().cpu().double().numpy()
    hi = float(np.nextafter(1.0, 2.0))  # voro++ wants points in [lo, hi); grids are clamped to 1.0
    bounds = ((0.0, hi),) * 3
    result = {}
    try:
        def compute():
            return pyvoro2.compute(pts, domain=pyvoro2.Box(bounds), return_vertices=False,
                                   return_adjacency=False, return_faces=False, output="cells")

        result["compute"] = common.time_fn(compute, "cpu", 0, 1)
        core = getattr(pyvoro2, "_core", None)
        if core is not None and hasattr(core, "compute_box_standard"):
            # What pyvoro2.compute runs after its Python-side input and duplicate checks,
            # with its default blocks (block edge 2.5 mean spacings).
            blocks = (max(1, int(len(pts) ** (1 / 3) / 2.5)),) * 3
            ids = np.arange(len(pts), dtype=np.int32)
            cells = []

            def native():
                cells[:] = core.compute_box_standard(pts, ids, bounds, blocks, (False,) * 3, 8,
                                                     (False, False, False))

            result["core"] = common.time_fn(native, "cpu", 0, 1)
        else:
            cells = compute()
    except Exception as error:  # noqa: BLE001 - report, don't abort the benchmark
        return f"pyvoro2 failed: {type(error).__name__}: {error}"
    volume = np.full(len(pts), np.nan)
    volume[[c["id"] for c in cells]] = [c["volume"] for c in cells]
    result["volume"] = volume
    return result


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--kinds", default="white,perturbed,blue",
                        help=f"comma-separated point sets from {','.join(common.POINT_KINDS)}")
    parser.add_argument("--k", type=common.parse_ints, default=None,
                        help="first-pass k, comma-separated to sweep; 0 = the library's default (k=None: "
                             "measured on a pilot sample) (default: 0, then by kind: "
                             + ", ".join(f"{kind} {k}" for kind, k in DEFAULT_K.items()) + ")")
    parser.add_argument("--memory-budget-mib", type=int, default=torchvor.ops.DEFAULT_MEMORY_BUDGET >> 20,
                        help="voronoi's memory_budget (default: the op's)")
    parser.add_argument("--no-voro", action="store_true", help="skip the voro++ comparison")
    parser.add_argument("--lloyd-iteration", action="store_true", help="also time one Lloyd iteration")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or ([100_000, 1_000_000, 10_000_000] if device.type == "cuda" else [100_000, 1_000_000])
    budget = args.memory_budget_mib << 20
    with_voro = device.type == "cpu" and not args.no_voro
    notes = [f"unit cube, {args.dtype}; torchvor times are medians of {args.repeats} runs after "
             f"{args.warmup} warm-up run(s) of the whole torchvor.voronoi call (memory_budget "
             f"{args.memory_budget_mib} MiB); knn = torchvor.knn(points, k) alone, an estimate of the kNN part.",
             "k = pilot: the op's default (k=None), its first-pass k picked by a pilot sample; knn and recovery "
             "are then not shown (the op does not report the k it picked).",
             "recovery = cells that needed more than the first-pass k neighbours (neighbors_needed > k), recomputed "
             "by the op; failures = final status not SUCCESS/DUPLICATE; nbrs = 50/99/100th percentiles of "
             "`neighbors_needed`; |Σvol−1| in float64 over non-failed cells.",
             "memory of the first (cold) call, which also gives the statistics: " + common.MEMORY_NOTE[device.type]]
    if with_voro:
        notes.append("voro++ = pyvoro2's native compute_box_standard call (single-threaded, volumes only, "
                     "float64, one run, no warm-up); pyvoro2.compute adds its Python input/duplicate checks. "
                     "Speed-up = voro++ / torchvor. Δvol = max |torchvor − voro++| / mean cell volume.")
    headers = ["kind", "n", "k", "voronoi", "knn", "Mcells/s", "recovery", "failures", "|Σvol−1|",
               "nbrs p50/p99/max", "peak MiB", "work MiB"]
    if args.lloyd_iteration:
        headers.append("1 Lloyd iter")
    if with_voro:
        headers += ["voro++", "pyvoro2.compute", "speed-up vs voro++", "Δvol"]
    rows = []
    for n in sizes:
        for kind in args.kinds.split(","):
            points, label = common.make_points(kind, n, seed=args.seed, dtype=dtype, device=device,
                                               cache_dir=args.cache_dir, blue_iters=args.blue_iters)
            count = points.shape[0]
            voro = voro_pp(points) if with_voro else None
            if isinstance(voro, str):
                notes.append(f"{label} n={count:,}: voro++ skipped: {voro}")
            for k in args.k or [0, DEFAULT_K[kind]]:
                k = k or None  # 0: the op measures its first-pass k on a pilot
                run = lambda: torchvor.voronoi(points, common.UNIT_BOX, k=k, on_failure="flag",  # noqa: E731
                                               memory_budget=budget)
                memory, cells = common.measure_memory(run, device)  # first (cold) call: memory, statistics
                seconds = common.time_fn(run, device, args.warmup, args.repeats)
                knn_seconds = (None if k is None else
                               common.time_fn(lambda: torchvor.knn(points, k), device, args.warmup, args.repeats))
                status = cells.status
                failed = (status != torchvor.CellStatus.SUCCESS) & (status != torchvor.CellStatus.DUPLICATE)
                volume_error = abs(float(cells.volume[~failed].double().sum()) - 1.0)
                recovered = "—" if k is None else int((cells.neighbors_needed > k).sum())
                row = [label, common.npoints_label(count), k or "pilot", common.fmt_s(seconds),
                       common.fmt_s(knn_seconds),
                       f"{count / seconds / 1e6:.2f}", recovered, int(failed.sum()),
                       f"{volume_error:.1e}", "/".join(map(str, common.neighbor_percentiles(cells.neighbors_needed))),
                       common.fmt_mib(memory.peak), common.fmt_mib(memory.work)]
                if args.lloyd_iteration:
                    step = lambda: torchvor.lloyd(points, common.UNIT_BOX, iters=1, k=k)  # noqa: E731
                    row.append(common.fmt_s(common.time_fn(step, device, args.warmup, args.repeats)))
                    notes.append("1 Lloyd iter = torchvor.lloyd(points, box, iters=1, k=k), median like voronoi.")
                if with_voro:
                    if isinstance(voro, dict):
                        core = voro.get("core")
                        ours = cells.volume.double().cpu().numpy()
                        diff = np.nanmax(np.abs(ours - voro["volume"])) * count
                        row += [common.fmt_s(core), common.fmt_s(voro["compute"]),
                                common.fmt_ratio(core / seconds if core else voro["compute"] / seconds),
                                f"{diff:.1e}"]
                    else:
                        row += ["—"] * 4
                rows.append(row)
                common.log(" | ".join(map(str, row)))
                del cells
            points = None  # free before the next point set
    common.print_results("Voronoi cells", headers, rows, notes)


if __name__ == "__main__":
    main()
