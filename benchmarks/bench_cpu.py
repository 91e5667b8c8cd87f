"""The CPU's targets in one run: torchvor against its CPU peers on the same
points, in rounds that alternate which of the two runs first.

    python benchmarks/bench_cpu.py [--rounds 3] [--sizes 100K,1M] [--only voronoi,knn,float64]

- voronoi: volumes and centroids of white noise and of blue noise (30 Lloyd
  iterations of white noise) against voro++ computing volumes (pyvoro2's
  native call, one core, float64); targets 6x (white) and 10x (blue);
- knn: the k=35 neighbours of 1M white-noise points against scipy's cKDTree
  (build and query, workers=-1); target 8x;
- float64: voronoi on the same points in float64 against float32; target 1.2x.

torchvor runs on every thread torch has (as a user runs it). Each round
times each side once (torchvor: the fastest of --repeats calls after a
warm-up; the peer: one call), so a ratio compares runs minutes apart at
most; the table gives each target's ratio of the sides' fastest runs and the
range of the rounds' ratios.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
import torchvor.samples  # noqa: E402
from bench_knn import cKDTree, ckdtree_knn  # noqa: E402
from bench_voronoi import voro_pp  # noqa: E402

TARGETS = {"white": 6.0, "blue": 10.0, "knn": 8.0, "float64": 1.2}
KNN_K = 35
KNN_N = 1_000_000
BLUE_ITERS = 30


def fastest(fn, repeats: int) -> float:
    """The fastest of `repeats` timed calls after one untimed call."""
    return min(common.time_runs(fn, "cpu", 1, repeats))


def voronoi_call(points):
    return lambda: torchvor.voronoi(points, common.UNIT_BOX, on_failure="flag")


def voro_seconds(points) -> float:
    result = voro_pp(points)
    if isinstance(result, str):
        sys.exit(f"bench_cpu: {result}")
    return result.get("core", result["compute"])


def ckdtree_seconds(points_np) -> float:
    """One cKDTree build and query, as bench_knn.py times it."""
    return common.time_runs(lambda: ckdtree_knn(points_np, KNN_K), "cpu", 0, 1)[0]


def rounds_of(ours, theirs, rounds: int, label: str, names=("torchvor", "peer")):
    """(ours, theirs) seconds of each round, the sides' order alternating."""
    pairs = []
    for r in range(rounds):
        if r % 2 == 0:
            a = ours()
            b = theirs()
        else:
            b = theirs()
            a = ours()
        pairs.append((a, b))
        common.log(f"{label} round {r + 1}: {names[0]} {common.fmt_s(a)}, {names[1]} {common.fmt_s(b)}")
    return pairs


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--rounds", type=int, default=3, help="rounds of each comparison (default 3)")
    parser.add_argument("--only", default="voronoi,knn,float64", help="comma-separated: voronoi, knn, float64")
    parser.set_defaults(repeats=3, blue_iters=BLUE_ITERS)
    args = parser.parse_args()
    if args.device != "cpu":
        sys.exit("bench_cpu: the CPU's targets (--device cpu)")
    device, _ = common.setup(args)
    sizes = args.sizes or [100_000, 1_000_000]
    only = set(args.only.split(","))
    rows = []

    def add(target, label, n, pairs, invert=False):
        ours, theirs = [p[0] for p in pairs], [p[1] for p in pairs]
        ratios = [(a / b) if invert else (b / a) for a, b in pairs]
        best = (min(ours) / min(theirs)) if invert else (min(theirs) / min(ours))
        goal = TARGETS[target]
        met = best <= goal if invert else best >= goal
        rows.append([label, common.npoints_label(n), common.fmt_s(min(ours)), common.fmt_s(min(theirs)),
                     f"{best:.2f}x", f"{min(ratios):.2f}-{max(ratios):.2f}x",
                     f"{'<=' if invert else '>='} {goal:g}x", "met" if met else "NOT met"])

    for n in sizes if only & {"voronoi", "float64"} else []:
        for kind in ("white", "blue"):
            points, _ = common.make_points(kind, n, seed=args.seed, dtype=torch.float32, device=device,
                                           cache_dir=args.cache_dir, blue_iters=args.blue_iters)
            if "voronoi" in only:
                pairs = rounds_of(lambda: fastest(voronoi_call(points), args.repeats),
                                  lambda: voro_seconds(points), args.rounds, f"{kind} {n:,}", ("torchvor", "voro++"))
                add(kind, f"voronoi {kind} float32 / voro++", n, pairs)
            if "float64" in only:
                doubles = points.double()
                pairs = rounds_of(lambda: fastest(voronoi_call(doubles), args.repeats),
                                  lambda: fastest(voronoi_call(points), args.repeats), args.rounds,
                                  f"{kind} {n:,}", ("float64", "float32"))
                add("float64", f"voronoi {kind} float64 / float32", n, pairs, invert=True)
    if "knn" in only:
        if cKDTree is None:
            sys.exit("bench_cpu: scipy is needed for the kNN's peer")
        points = torchvor.samples.white_noise(KNN_N, seed=args.seed)
        points_np = points.double().numpy()
        pairs = rounds_of(lambda: fastest(lambda: torchvor.knn(points, KNN_K), args.repeats),
                          lambda: ckdtree_seconds(points_np), args.rounds, f"knn {KNN_N:,}", ("torchvor", "cKDTree"))
        add("knn", f"knn white k={KNN_K} / cKDTree", KNN_N, pairs)
    headers = ["comparison", "n", "torchvor", "peer", "ratio of fastest", "rounds' ratios", "target", ""]
    notes = [f"{torch.get_num_threads()} torch threads; voro++ one core (pyvoro2's native call, volumes only, "
             f"float64); cKDTree workers=-1 (build and query, float64 copy); blue noise = white noise after "
             f"{args.blue_iters} Lloyd iterations; torchvor: the fastest of {args.repeats} calls after a warm-up, "
             f"each round; {args.rounds} rounds, the sides' order alternating. float64 rows: float64 / float32."]
    common.print_results("CPU targets", headers, rows, notes)


if __name__ == "__main__":
    main()
