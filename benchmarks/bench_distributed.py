"""torchvor.distributed.voronoi over several processes (one GPU each, NCCL; or CPU
processes, gloo) against the single-process torchvor.voronoi of the same cloud:
strong scaling (the same cloud over more ranks) and weak scaling (--weak: the cloud
grows with the ranks), time and peak memory per rank.

    python benchmarks/bench_distributed.py --device cuda --sizes 10M,100M --ranks 1,2 [--weak] [--phases] [--profile]

Each rank holds a contiguous share of the cloud in its stored order (blue noise keeps
white noise's random order, so every rank's share spans the box: the exchange to
slabs moves about (R - 1) / R of the points); --spatial gives each rank a slab of it
instead (as Lloyd's points stay between iterations). One rank runs the plain call.
"""
from __future__ import annotations

import datetime
import os
import socket
import sys
import time
from collections import defaultdict
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torch  # noqa: E402
import torch.distributed as dist  # noqa: E402
import torch.multiprocessing as mp  # noqa: E402
import torchvor  # noqa: E402
import torchvor.distributed as tvd  # noqa: E402
from torchvor import _slabs  # noqa: E402

# --phases: these steps of one call timed on each rank (inclusive: an exchange
# inside a slab step counts in both; the device synchronized around each).
PHASES = [(tvd, "agree"), (tvd, "global_box"), (tvd, "check_inside"), (_slabs.Slabs, "__init__"),
          (_slabs.Local, "__init__"), (_slabs.Local, "cloud"), (_slabs.Group, "exchange"), (_slabs, "index_order"),
          (_slabs.Group, "all_to_all"), (tvd, "_voronoi_rows"), (tvd, "cell_shortfall"), (_slabs, "near_seeds"),
          (_slabs.Local, "send_back"), (_slabs.Local, "send_home"), (tvd, "certify_rows")]


def timed_phases(device: torch.device):
    """Wraps PHASES with timers; returns (seconds by name, calls by name, undo)."""
    seconds, calls, undo = defaultdict(float), defaultdict(int), []
    for owner, name in PHASES:
        original = getattr(owner, name, None)
        if original is None:  # not in this version
            continue
        label = f"{getattr(owner, '__name__', owner)}.{name}".replace("torchvor.", "")

        def wrapper(*args, _original=original, _label=label, **kwargs):
            common.synchronize(device)
            start = time.perf_counter()
            try:
                return _original(*args, **kwargs)
            finally:
                common.synchronize(device)
                seconds[_label] += time.perf_counter() - start
                calls[_label] += 1

        setattr(owner, name, wrapper)
        undo.append((owner, name, original))
    return seconds, calls, lambda: [setattr(o, n, f) for o, n, f in undo]


def worker(rank: int, ranks: int, port: int, args, n: int, results) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    device = torch.device(args.device, rank) if args.device == "cuda" else torch.device("cpu")
    if args.device == "cuda":
        torch.cuda.set_device(device)
    else:  # the cores shared among the ranks
        torch.set_num_threads(max(1, (os.cpu_count() or 1) // ranks))
    dist.init_process_group("nccl" if args.device == "cuda" else "gloo", rank=rank, world_size=ranks,
                            timeout=datetime.timedelta(seconds=900),
                            device_id=device if args.device == "cuda" else None)
    dtype = getattr(torch, args.dtype)
    # Made on the rank's own device (the Lloyd iterations of blue noise at hundreds
    # of millions of points are far too slow on the CPU), then all but the share freed.
    points, _ = common.make_points(args.kind, n, seed=args.seed, dtype=dtype, device=device,
                                   cache_dir=args.cache_dir, blue_iters=args.blue_iters)
    if args.spatial:
        points = points[torch.sort(points[:, 0]).indices]
    share = points[n * rank // ranks: n * (rank + 1) // ranks].clone()
    del points
    if args.device == "cuda":
        torch.cuda.empty_cache()

    def call():
        return tvd.voronoi(share, common.UNIT_BOX, on_failure="flag")

    times = []
    for repeat in range(args.warmup + args.repeats):
        dist.barrier()
        common.synchronize(device)
        if args.device == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        start = datetime.datetime.now()
        cells = call()
        common.synchronize(device)
        dist.barrier()
        if repeat >= args.warmup:
            times.append((datetime.datetime.now() - start).total_seconds())
    peak = torch.cuda.max_memory_allocated(device) if args.device == "cuda" else 0
    failed = int(((cells.status != 0) & (cells.status != 5)).sum())
    phases = None
    if args.phases:
        seconds, calls, undo = timed_phases(device)
        dist.barrier()
        start = time.perf_counter()
        call()
        common.synchronize(device)
        seconds["whole call"] = time.perf_counter() - start
        undo()
        phases = [(name, 1000 * s, calls[name]) for name, s in seconds.items()]
    if args.profile:  # the device's activities of one more call, by total time
        with torch.profiler.profile(activities=[torch.profiler.ProfilerActivity.CPU] +
                                    ([torch.profiler.ProfilerActivity.CUDA] if args.device == "cuda" else [])) as prof:
            dist.barrier()
            call()
            common.synchronize(device)
        sort_by = "self_cuda_time_total" if args.device == "cuda" else "self_cpu_time_total"
        print(f"profile of one call, rank {rank} of {ranks}:\n" +
              prof.key_averages().table(sort_by=sort_by, row_limit=args.profile_rows, max_name_column_width=70),
              flush=True)
    results[rank] = (sorted(times)[len(times) // 2], peak, share.shape[0], failed, phases)
    dist.destroy_process_group()


def run(args, ranks: int, n: int):
    """(median seconds, [peak bytes per rank], failed cells) of one configuration."""
    if ranks == 1:  # the plain call
        dtype = getattr(torch, args.dtype)
        device = torch.device(args.device)
        points, _ = common.make_points(args.kind, n, seed=args.seed, dtype=dtype, device=device,
                                       cache_dir=args.cache_dir, blue_iters=args.blue_iters)
        if device.type == "cuda":
            torch.cuda.reset_peak_memory_stats(device)
        seconds = common.time_fn(lambda: torchvor.voronoi(points, common.UNIT_BOX, on_failure="flag"), device,
                                 args.warmup, args.repeats)
        peak = torch.cuda.max_memory_allocated(device) if device.type == "cuda" else 0
        return seconds, [peak], 0
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    manager = mp.Manager()
    results = manager.dict()
    mp.spawn(worker, args=(ranks, port, args, n, results), nprocs=ranks, join=True)
    rows = [results[r] for r in range(ranks)]
    for r, row in enumerate(rows):
        if row[4]:
            print(f"phases of one call, rank {r} of {ranks}, n={n}: " +
                  "; ".join(f"{name} {ms:.1f} ms" + (f" x{calls}" if calls > 1 else "") for name, ms, calls in row[4]),
                  flush=True)
    return max(r[0] for r in rows), [r[1] for r in rows], sum(r[3] for r in rows)


def main():
    parser = common.base_parser(__doc__.split("\n\n")[0])
    parser.add_argument("--ranks", type=common.parse_ints, default=[1, 2], help="comma-separated rank counts")
    parser.add_argument("--kind", default="blue", help="blue, white or perturbed")
    parser.add_argument("--weak", action="store_true", help="each size is a rank's share (the cloud grows)")
    parser.add_argument("--spatial", action="store_true", help="each rank holds a slab of the cloud along x")
    parser.add_argument("--phases", action="store_true",
                        help="after timing, one more call with its steps timed on each rank (synchronized)")
    parser.add_argument("--profile", action="store_true",
                        help="after timing, one more call under torch.profiler on each rank (its top activities)")
    parser.add_argument("--profile-rows", type=int, default=30, help="rows of the --profile table")
    args = parser.parse_args()
    device, _ = common.setup(args)
    if device.type == "cuda" and max(args.ranks) > torch.cuda.device_count():
        sys.exit(f"--ranks {max(args.ranks)}: only {torch.cuda.device_count()} GPUs")
    rows = []
    for n in args.sizes or [1_000_000]:
        base = None
        for ranks in args.ranks:
            total = n * ranks if args.weak else n
            seconds, peaks, failed = run(args, ranks, total)
            base = seconds if base is None else base
            ratio = (seconds / base) if args.weak else (base / seconds)
            rows.append([args.kind, common.npoints_label(total), ranks, common.fmt_s(seconds), common.fmt_ratio(ratio),
                         " / ".join(common.fmt_mib(p) for p in peaks) if device.type == "cuda" else "-", failed])
            common.log(f"{args.kind} n={total} ranks={ranks}: {common.fmt_s(seconds)}")
    ratio_name = "time / first" if args.weak else "speedup"
    common.print_results("torchvor.distributed.voronoi", ["points", "n", "ranks", "time", ratio_name,
                                                          "peak per rank (MiB)", "failed"], rows,
                         [f"{args.dtype}, unit cube, default k; the slowest rank's median of {args.repeats} after "
                          f"{args.warmup} warm-up; shares {'spatial' if args.spatial else 'in stored order'}; "
                          "1 rank: the plain call"])


if __name__ == "__main__":
    main()
