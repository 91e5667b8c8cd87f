"""A/B helper for the GPU machine: wall and per-kernel time of one voronoi
call on 1M blue noise (k=24) and one kNN call (1M jittered, k=35), the wall
time of one Lloyd iteration on the blue noise (k=24 and k=19, the k lloyd
adapts to there), and the median of the last 5 of 10 iterations as lloyd
reports them (seconds per iteration, adaptive k). AB_10M=1 adds one voronoi
call on 10M blue noise (k=24; made by lloyd on the machine, ~6 s, cached in
/tmp), one Lloyd iteration on it (k=19) and the median of iterations 4-8 of a
run of 8 (k=19). AB_IRREGULAR=1 adds voronoi calls
on white noise and perturbed grids of 1M and 10M points (k from the pilot: warp
cells)."""
import os
import statistics
import sys

import torch
import torchvor
import torchvor.samples
from torch.profiler import ProfilerActivity, profile

cache = "/tmp/blue_1m.pt"
if not os.path.exists(cache):
    white = torchvor.samples.white_noise(1_000_000, device="cuda")
    torch.save(torchvor.lloyd(white, ([0, 0, 0], [1, 1, 1]), iters=100).cpu(), cache)
blue = torch.load(cache).cuda()
jittered = torchvor.samples.jittered_grid(1_000_000, device="cuda")
box = ([0, 0, 0], [1, 1, 1])


def timed(fn, repeats=20):
    fn()
    torch.cuda.synchronize()
    times = []
    for _ in range(repeats):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        fn()
        end.record()
        end.synchronize()
        times.append(start.elapsed_time(end))
    return statistics.median(times)


def kernels(fn):
    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        fn()
        torch.cuda.synchronize()
    out = {}
    for e in prof.key_averages():
        for name in ("ClipFunctor", "KnnFunctor", "ToRowsFunctor"):
            if name in e.key:
                out[name] = round(out.get(name, 0.0) + e.device_time_total / 1e3, 3)
    return out


label = sys.argv[1] if len(sys.argv) > 1 else "?"
vor = lambda: torchvor.voronoi(blue, box, k=24, on_failure="flag")
knn = lambda: torchvor.knn(jittered, 35)
step = lambda: torchvor.lloyd(blue, box, iters=1, k=24)
step19 = lambda: torchvor.lloyd(blue, box, iters=1, k=19)
_, history = torchvor.lloyd(blue, box, iters=10, return_history=True)
late = statistics.median(1e3 * h.seconds for h in history[5:])
print(f"{label}: voronoi 1M blue k=24 {timed(vor):.2f} ms {kernels(vor)}; "
      f"knn 1M jittered k=35 {timed(knn):.2f} ms {kernels(knn)}; "
      f"lloyd iteration 1M blue k=24 {timed(step):.2f} ms, k=19 {timed(step19):.2f} ms; "
      f"lloyd history, late iterations {late:.2f} ms (k {history[-1].k})", flush=True)
if os.environ.get("AB_10M") == "1":
    cache10 = "/tmp/blue_10m.pt"
    if not os.path.exists(cache10):
        white = torchvor.samples.white_noise(10_000_000, device="cuda")
        torch.save(torchvor.lloyd(white, box, iters=100, k=24).cpu(), cache10)
    blue10 = torch.load(cache10).cuda()
    vor10 = lambda: torchvor.voronoi(blue10, box, k=24, on_failure="flag")
    _, history10 = torchvor.lloyd(blue10, box, iters=8, k=19, return_history=True)
    late10 = statistics.median(1e3 * h.seconds for h in history10[3:])
    print(f"{label}: voronoi 10M blue k=24 {timed(vor10, repeats=7):.2f} ms {kernels(vor10)}; "
          f"lloyd iteration 10M blue k=19 {timed(lambda: torchvor.lloyd(blue10, box, iters=1, k=19), repeats=7):.2f} ms, "
          f"late iterations of 8 {late10:.2f} ms", flush=True)
if os.environ.get("AB_IRREGULAR") == "1":
    # Warp cells: 1M and 10M white noise and perturbed grids, k from the pilot.
    for n, tag in ((1_000_000, "1M"), (10_000_000, "10M")):
        for kind, make in (("white", torchvor.samples.white_noise), ("perturbed", torchvor.samples.perturbed_grid)):
            points = make(n, seed=0, device="cuda")
            call = lambda: torchvor.voronoi(points, box, on_failure="flag")  # noqa: E731
            print(f"{label}: voronoi {tag} {kind} {timed(call, repeats=5 if n > 1_000_000 else 20):.2f} ms "
                  f"{kernels(call)}", flush=True)
