"""Interleaved A/B of environment settings inside one process (GPU machine).

Settings that torchvor reads at every call (TORCHVOR_CELLS,
TORCHVOR_CELL_START, TORCHVOR_CELL_BLOCKS_PER_SM, ...) can be switched between calls, so
each round times every setting back to back and host drift (which moved
whole ab_time.py runs by 0.3-0.5 ms at 1M, benchmarks/NOTES.md) hits all of
them alike. Prints, per call and setting, the median over rounds of the
call's wall time (CUDA events) and, with --kernels, the clip and kNN kernels
of one profiled call.

    python benchmarks/ab_env.py "default" "TORCHVOR_CELL_START=box" [--rounds 15] [--sizes 1M,10M] [--kernels]

The setting TORCHVOR_AB_MEMORY_BUDGET=BYTES is this script's own: it passes
voronoi that memory_budget (the op reads no such variable).

Calls (--kinds): voronoi on blue noise (k=24) and one Lloyd iteration on it
(k=19, from points already in Lloyd's grid order, as in late iterations);
voronoi on a perturbed grid (k=48) and on white noise (k=64), the
benchmark's first-pass k (bench_voronoi.py), or with --pilot the op's default
k (k=None: its pilot picks it). The point sets are the
benchmarks' (common.make_points, seed 0; blue noise cached in
benchmarks/.cache, shared with bench_voronoi.py). --knn K1,K2 adds the kNN op
at those k on each kind; kind "clusters" (200 clusters of 0.02) times only that.
"""
import argparse
import os
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
from torchvor.ops import _voronoi_in_grid_order, as_box  # noqa: E402

BOX = common.UNIT_BOX
SIZES = {"100K": 100_000, "1M": 1_000_000, "10M": 10_000_000}
FIRST_PASS_K = {"blue": 24, "perturbed": 48, "white": 64}
DEVICE = "cuda"


def points_of(kind: str, n: int) -> torch.Tensor:
    if kind == "clusters":
        return torchvor.samples.clustered(n, clusters=200, spread=0.02, seed=0).to(DEVICE)
    points, _ = common.make_points(kind, n, seed=0, dtype=torch.float32, device=torch.device(DEVICE),
                                   cache_dir=Path(__file__).resolve().parent / ".cache")
    return points


def apply(setting: str) -> None:
    for name in [v for v in os.environ if v.startswith("TORCHVOR_")]:
        del os.environ[name]
    if setting != "default":
        for part in setting.split(","):
            name, value = part.split("=", 1)
            os.environ[name] = value


def memory_budget() -> dict:
    """voronoi's memory_budget argument: TORCHVOR_AB_MEMORY_BUDGET (bytes) as
    a setting of this script (the op reads no such variable), else none (the
    op's default)."""
    chosen = os.environ.get("TORCHVOR_AB_MEMORY_BUDGET")
    return {"memory_budget": int(chosen)} if chosen else {}


def wall_ms(fn) -> float:
    if DEVICE == "cpu":
        begin = time.perf_counter()
        fn()
        return 1e3 * (time.perf_counter() - begin)
    start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
    start.record()
    fn()
    end.record()
    end.synchronize()
    return start.elapsed_time(end)


def kernel_ms(fn) -> dict:
    on_gpu = DEVICE == "cuda"
    with profile(activities=[ProfilerActivity.CUDA if on_gpu else ProfilerActivity.CPU]) as prof:
        fn()
        if on_gpu:
            torch.cuda.synchronize()
    out = {}
    for e in prof.key_averages():
        for name in ("ClipFunctor", "KnnFunctor"):
            if name in e.key:
                spent = e.device_time_total if on_gpu else e.self_cpu_time_total
                out[name] = round(out.get(name, 0.0) + spent / 1e3, 3)
    return out


def calls_for(kind: str, tag: str, pilot: bool = False, knn_k: list = ()) -> dict:
    points = points_of(kind, SIZES[tag])
    calls = {f"knn {tag} {kind} k={k}": (lambda k=k: torchvor.knn(points, k)) for k in knn_k}
    if kind == "clusters":  # the kNN op only
        return calls
    k = None if pilot else FIRST_PASS_K[kind]
    calls[f"voronoi {tag} {kind} k={k or 'pilot'}"] = lambda: torchvor.voronoi(
        points, BOX, k=k, on_failure="flag", **memory_budget())
    if kind == "blue":
        box = as_box(points, BOX)
        # Lloyd's late iterations start from points already in grid order.
        _, order = _voronoi_in_grid_order(points, box, None, 19)
        in_grid_order = points.index_select(0, order)
        calls[f"lloyd step {tag} k=19"] = lambda: torchvor.lloyd(in_grid_order, box, iters=1, k=19)
    return calls


def time_calls(calls: dict, settings: list, rounds: int, kernels: bool) -> None:
    times = {(call, s): [] for call in calls for s in settings}
    for setting in settings:  # warm-up
        apply(setting)
        for fn in calls.values():
            fn()
    for _ in range(rounds):
        for call, fn in calls.items():
            for setting in settings:
                apply(setting)
                times[(call, setting)].append(wall_ms(fn))
    for call, fn in calls.items():
        for setting in settings:
            apply(setting)
            values = sorted(times[(call, setting)])
            line = (f"{call} | {setting} | median {statistics.median(values):.3f} ms | "
                    f"quartiles {values[len(values) // 4]:.3f}-{values[(3 * len(values)) // 4]:.3f}")
            if kernels:
                line += f" | {kernel_ms(fn)}"
            print(line, flush=True)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("settings", nargs="+", help='"default" or NAME=VALUE[,NAME=VALUE]')
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--sizes", default="1M,10M")
    parser.add_argument("--kinds", default="blue", help="blue, perturbed, white (comma-separated)")
    parser.add_argument("--kernels", action="store_true")
    parser.add_argument("--pilot", action="store_true", help="voronoi with the op's default k (its pilot) instead")
    parser.add_argument("--knn", type=common.parse_ints, default=[],
                        help="also time the kNN op at these k (comma-separated); kind 'clusters' (200 of "
                             "0.02) times only that")
    parser.add_argument("--device", default="cuda", help="cpu: a dry run of this script (timed by the host clock)")
    args = parser.parse_args()
    global DEVICE
    DEVICE = args.device
    for tag in args.sizes.split(","):
        for kind in args.kinds.split(","):
            time_calls(calls_for(kind, tag, args.pilot, args.knn), args.settings, args.rounds, args.kernels)
    apply("default")


if __name__ == "__main__":
    main()
