"""k nearest neighbours of every point (self excluded): torchvor.knn against
scipy's cKDTree (workers=-1) and a chunked torch.cdist + topk.

    python benchmarks/bench_knn.py [--device cpu|cuda] [--sizes 100K,1M] [--k 35,90]
                                   [--points uniform|jittered] [--methods torchvor,ckdtree,cdist]
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402

try:
    import numpy as np
    from scipy.spatial import cKDTree
except ImportError:
    cKDTree = None

CDIST_MAX_N = 1_000_000  # O(n^2): skipped above this unless --with-cdist


def ckdtree_knn(points_np, k):
    """Same work as torchvor.knn(points, k): build, query k+1, drop the first column (self)."""
    dist, idx = cKDTree(points_np).query(points_np, k=k + 1, workers=-1)
    return dist[:, 1:], idx[:, 1:]


def cdist_knn(points, k, chunk_bytes):
    """Brute force in query chunks of at most chunk_bytes of distances (and 4096 rows)."""
    n = points.shape[0]
    rows = max(1, min(4096, chunk_bytes // (n * points.element_size())))
    dist2 = points.new_empty(n, k)
    idx = torch.empty(n, k, dtype=torch.int64, device=points.device)
    for start in range(0, n, rows):
        stop = min(n, start + rows)
        d = torch.cdist(points[start:stop], points)
        local = torch.arange(stop - start, device=points.device)
        d[local, local + start] = float("inf")  # exclude self
        values, idx[start:stop] = d.topk(k, dim=1, largest=False)
        dist2[start:stop] = values.square()
    return dist2, idx


def count_mismatches(pts, tree, idx, k, sample, seed, rtol):
    """(rows whose index set differs from cKDTree's, rows where that is not explained by ties)
    on ``sample`` random rows; distances recomputed in float64 from the points ``pts``."""
    rows = np.random.default_rng(seed).choice(len(pts), size=min(sample, len(pts)), replace=False)
    _, ref = tree.query(pts[rows], k=k + 1)
    ref = np.array([[j for j in r if j != i][:k] for r, i in zip(ref, rows)])  # drop self
    ours = idx[torch.as_tensor(rows, device=idx.device)].cpu().numpy()
    differ = [set(a) != set(b) for a, b in zip(ours, ref)]
    d_ours = np.sort(((pts[ours] - pts[rows, None]) ** 2).sum(-1), axis=1)
    d_ref = np.sort(((pts[ref] - pts[rows, None]) ** 2).sum(-1), axis=1)
    tol = rtol * d_ref[:, -1:]
    unexplained = np.abs(d_ours - d_ref).max(axis=1) > tol[:, 0]
    return int(np.sum(differ)), int(np.sum(np.array(differ) & unexplained)), len(rows)


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--k", type=common.parse_ints, default=[35, 90], help="comma-separated k values")
    parser.add_argument("--points", choices=("uniform", "jittered"), default="uniform")
    parser.add_argument("--methods", default="torchvor,ckdtree,cdist",
                        help="comma-separated subset of torchvor,ckdtree,cdist")
    parser.add_argument("--with-cdist", action="store_true", help=f"run cdist+topk also above n={CDIST_MAX_N:,}")
    parser.add_argument("--cdist-chunk-mib", type=int, default=1024, help="distance memory per cdist chunk")
    parser.add_argument("--baseline-repeats", type=int, default=3, help="timed runs of cKDTree and cdist+topk")
    parser.add_argument("--check-rows", type=int, default=2000, help="rows compared with cKDTree (0: no check)")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    sizes = args.sizes or [100_000, 1_000_000]
    methods = set(args.methods.split(","))
    notes = [f"points: {args.points} in the unit cube, {args.dtype}; self excluded. torchvor: median of "
             f"{args.repeats} runs after {args.warmup} warm-up run(s); baselines: median of {args.baseline_repeats}.",
             "cKDTree: build + query(k+1, workers=-1) + drop self, on a float64 NumPy copy made before timing "
             "(CPU, all cores); no warm-up."]
    if "cdist" in methods:
        notes.append("cdist+topk: torch.cdist on query chunks of at most --cdist-chunk-mib of distances "
                     "(≤ 4096 rows), self masked, topk(k) smallest; warm-up on the first 4096 rows.")
    if cKDTree is None:
        notes.append("scipy not importable: cKDTree column and index check skipped.")
        methods.discard("ckdtree")
    rows, checks = [], []
    for n in sizes:
        points, _ = common.make_points("white" if args.points == "uniform" else "jittered", n, seed=args.seed,
                                       dtype=dtype, device=device, cache_dir=args.cache_dir)
        n = points.shape[0]
        check = cKDTree is not None and "torchvor" in methods and args.check_rows > 0
        points_np = points.cpu().double().numpy() if "ckdtree" in methods or check else None
        tree = cKDTree(points_np) if check else None
        for k in args.k:
            times = {}
            if "torchvor" in methods:
                times["torchvor"] = common.time_fn(lambda: torchvor.knn(points, k), device, args.warmup,
                                                   args.repeats)
                common.log(f"n={n} k={k} torchvor.knn {common.fmt_s(times['torchvor'])}")
            if "ckdtree" in methods:
                times["cKDTree"] = common.time_fn(lambda: ckdtree_knn(points_np, k), "cpu", 0,
                                                  args.baseline_repeats)
                common.log(f"n={n} k={k} cKDTree {common.fmt_s(times['cKDTree'])}")
            if "cdist" in methods and n > CDIST_MAX_N and not args.with_cdist:
                notes.append(f"cdist+topk skipped at n={n:,} (O(n²); --with-cdist forces it).")
            elif "cdist" in methods:
                chunk = args.cdist_chunk_mib << 20
                cdist_knn(points[:4096], k, chunk)  # warm-up on a small input
                repeats = 1 if n >= CDIST_MAX_N else args.baseline_repeats
                times["cdist+topk"] = common.time_fn(lambda: cdist_knn(points, k, chunk), device, 0, repeats)
                common.log(f"n={n} k={k} cdist+topk {common.fmt_s(times['cdist+topk'])}")
                if repeats == 1:
                    notes.append(f"cdist+topk at n ≥ {CDIST_MAX_N:,}: one timed run.")
            base = times.get("cKDTree")
            for method, seconds in times.items():
                rows.append([common.npoints_label(n), k, method, common.fmt_s(seconds),
                             common.fmt_ratio(base / seconds if base else None)])
            if check:
                idx = torchvor.knn(points, k).idx
                rtol = 1e-5 if dtype == torch.float32 else 1e-12
                differ, unexplained, total = count_mismatches(points_np, tree, idx, k, args.check_rows,
                                                              args.seed, rtol)
                checks.append(f"n={n:,} k={k}: {differ}/{total} sampled rows differ from cKDTree's index set, "
                              f"{unexplained} not explained by distance ties")
                common.log("check " + checks[-1])
                del idx
        points = points_np = tree = None  # free before the next size
    common.print_results("kNN", ["n", "k", "method", "seconds (median)", "speed-up vs cKDTree"], rows,
                         notes + [f"index check: {line}" for line in checks])


if __name__ == "__main__":
    main()
