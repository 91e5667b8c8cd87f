"""Where the time of the headline calls goes, kernel by kernel.

Runs each call once under torch.profiler after a warm-up and prints the CUDA
kernels sorted by their total time, plus the wall time of the call (CUDA
events). Reports only; nothing asserts.

    python benchmarks/profile_gpu.py --device cuda [--sizes 1M] [--knn-10m] [--rows 12] [--timeline [--timeline-k K]]

--timeline also prints, for voronoi on blue noise of each size, the GPU's
activities in order with the idle time before each and the host calls made
meanwhile: where the wall time that no kernel accounts for goes. Its voronoi
call takes the op's default k (its pilot) unless --timeline-k gives one; the
Lloyd iteration takes k=19.
"""
from __future__ import annotations

import sys
from pathlib import Path

import torch
from torch.profiler import ProfilerActivity, profile

sys.path.insert(0, str(Path(__file__).resolve().parent))
import common  # noqa: E402
import torchvor  # noqa: E402
from torchvor import samples  # noqa: E402


def report(title: str, fn, device: torch.device, rows: int) -> None:
    milliseconds = 1e3 * common.time_fn(fn, device, warmup=1, repeats=5)
    on_gpu = device.type == "cuda"
    with profile(activities=[ProfilerActivity.CUDA if on_gpu else ProfilerActivity.CPU]) as prof:
        fn()
        common.synchronize(device)
    spent = (lambda e: e.device_time_total) if on_gpu else (lambda e: e.self_cpu_time_total)
    events = sorted((e for e in prof.key_averages() if spent(e) > 0), key=lambda e: -spent(e))
    total = sum(spent(e) for e in events)
    print(f"\n### {title}: {milliseconds:.2f} ms wall (median of 5), {total / 1e3:.2f} ms in "
          f"{'kernels' if on_gpu else 'ops (self time)'}")
    print("| kernel or op | calls | total ms |")
    print("|---|---|---|")
    for e in events[:rows]:
        print(f"| {e.key[:90]} | {e.count} | {spent(e) / 1e3:.3f} |")


def timeline(title: str, fn, min_gap_us: float = 8.0) -> None:
    """GPU activities of one call in order; for each idle gap of at least
    `min_gap_us`, the host-side ATen ops and CUDA runtime calls that began in it."""
    fn()
    torch.cuda.synchronize()
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    events = prof.events()
    gpu = sorted((e for e in events if e.device_type == torch.autograd.DeviceType.CUDA),
                 key=lambda e: e.time_range.start)
    host = sorted((e for e in events if e.device_type == torch.autograd.DeviceType.CPU
                   and (e.name.startswith("cuda") or (e.name.startswith("aten::") and e.cpu_parent is not None
                                                       and not e.cpu_parent.name.startswith("aten::")))),
                  key=lambda e: e.time_range.start)
    if not gpu:
        return
    origin = gpu[0].time_range.start
    busy = sum(e.time_range.elapsed_us() for e in gpu)
    span = gpu[-1].time_range.end - origin
    print(f"\n### timeline: {title}: {span / 1e3:.2f} ms from first to last GPU activity, "
          f"{busy / 1e3:.2f} ms busy, {len(gpu)} activities")
    print("| start us | idle before us | GPU activity | us | host calls begun while idle |")
    print("|---|---|---|---|---|")
    previous_end = origin
    for e in gpu:
        gap = e.time_range.start - previous_end
        calls = ""
        if gap >= min_gap_us:
            names = [h.name for h in host if previous_end <= h.time_range.start < e.time_range.start]
            calls = ", ".join(dict.fromkeys(names))[:160]
        print(f"| {e.time_range.start - origin:.0f} | {gap:.0f} | {e.name[:60]} | {e.time_range.elapsed_us():.0f} | {calls} |")
        previous_end = max(previous_end, e.time_range.end)


def main() -> None:
    parser = common.base_parser(__doc__)
    parser.add_argument("--rows", type=int, default=12)
    parser.add_argument("--knn-10m", action="store_true", help="also kNN of 10M uniform points, k=190")
    parser.add_argument("--timeline", action="store_true", help="GPU idle gaps of voronoi and of one Lloyd step (blue)")
    parser.add_argument("--timeline-k", type=int, default=None, help="the timeline's voronoi k (default: the pilot's)")
    args = parser.parse_args()
    device, dtype = common.setup(args)
    box = common.UNIT_BOX
    for n in args.sizes or [1_000_000]:
        jittered = samples.jittered_grid(n, seed=1, device=device)
        report(f"knn {n} jittered k=35", lambda: torchvor.knn(jittered, 35), device, args.rows)
        blue, _ = common.make_points("blue", n, seed=args.seed, dtype=dtype, device=device,
                                     cache_dir=args.cache_dir, blue_iters=args.blue_iters)
        report(f"voronoi {n} blue k=24", lambda: torchvor.voronoi(blue, box, k=24, on_failure="flag"), device, args.rows)
        if args.timeline and device.type == "cuda":
            k = args.timeline_k
            timeline(f"voronoi {n} blue k={k or 'pilot'}", lambda: torchvor.voronoi(blue, box, k=k, on_failure="flag"))
            timeline(f"one Lloyd iteration, {n} blue k=19", lambda: torchvor.lloyd(blue, box, iters=1, k=19))
        report(f"voronoi {n} blue k=None", lambda: torchvor.voronoi(blue, box, on_failure="flag"), device, args.rows)
        white = samples.white_noise(n, seed=1, device=device)
        report(f"voronoi {n} white k=64", lambda: torchvor.voronoi(white, box, k=64, on_failure="flag"), device, args.rows)
    if args.knn_10m:
        uniform = samples.white_noise(10_000_000, seed=2, device=device)
        report("knn 10M uniform k=190", lambda: torchvor.knn(uniform, 190), device, args.rows)


if __name__ == "__main__":
    main()
