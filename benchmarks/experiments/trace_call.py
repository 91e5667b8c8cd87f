"""EXPERIMENT: host and GPU times of marked points in voronoi calls (TORCHVOR_TRACE=1, csrc/ops/trace.h)."""
import os
import sys
import time
from pathlib import Path

import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import common  # noqa: E402
import torchvor  # noqa: E402

BOX = common.UNIT_BOX
for tag, n in (("1M", 1_000_000), ("10M", 10_000_000)):
    points, _ = common.make_points("blue", n, seed=0, dtype=torch.float32, device=torch.device("cuda"),
                                   cache_dir=Path(__file__).resolve().parents[1] / ".cache")
    call = lambda: torchvor.voronoi(points, BOX, k=None, on_failure="flag")  # noqa: E731
    from torchvor.ops import as_box, VoronoiCells, _box_for_call

    def stamped(box_fn):
        """torchvor.voronoi's path with host stamps (ns) after the box and after the op returns."""
        box = box_fn(points, BOX, None)
        after_box = time.perf_counter_ns()
        cells = VoronoiCells(*torch.ops.torchvor.voronoi_cells.default(points, box, None, None, 1 << 30))
        return after_box, time.perf_counter_ns(), cells
    for _ in range(3):
        call()
    torch.cuda.synchronize()
    walls = []
    for _ in range(7):
        start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
        start.record()
        call()
        end.record()
        end.synchronize()
        walls.append(start.elapsed_time(end))
    print(f"{tag}: walls {sorted(round(w, 3) for w in walls)}", flush=True)
    os.environ["TORCHVOR_TRACE"] = "1"
    for box_fn in (as_box, _box_for_call, as_box, _box_for_call, as_box, _box_for_call):
        torch.cuda.synchronize()
        sys.stderr.flush()
        before = time.perf_counter_ns()
        after_box, after_op, _ = stamped(box_fn)
        torch.cuda.synchronize()
        print(f"{tag}: {box_fn.__name__} python before call {before} after as_box {after_box} after op {after_op}",
              flush=True)
        sys.stderr.flush()
    del os.environ["TORCHVOR_TRACE"]
    for label, fn in (("as_box", lambda: as_box(points, BOX)),
                      ("torch.tensor to cuda", lambda: torch.tensor([BOX], dtype=points.dtype, device=points.device)),
                      ("torch.tensor non_blocking", lambda: torch.tensor([BOX], dtype=points.dtype).to(
                          points.device, non_blocking=True))):
        for _ in range(20):
            fn()
        torch.cuda.synchronize()
        begin = time.perf_counter_ns()
        for _ in range(200):
            fn()
        print(f"{tag}: {label} {(time.perf_counter_ns() - begin) / 200e3:.1f} us", flush=True)

# Host time of a call's first operations right after the host waited on the
# device for 30 ms (as after a 10M call) or 1 ms.
dev = torch.device("cuda")
big = torch.rand(10_000_000, 3, device=dev)
ns = time.perf_counter_ns
for wait_ms in (30, 1, 30, 1, 30, 1, 30, 1):
    torch.cuda._sleep(int(wait_ms * 1e-3 * 1.7e9))
    torch.cuda.synchronize()
    t0 = ns()
    x = torch.tensor([BOX], dtype=torch.float32)
    t1 = ns()
    y = x.to(dev, non_blocking=True)
    t2 = ns()
    e = torch.empty(8, device=dev)
    t3 = ns()
    e.zero_()
    t4 = ns()
    torch.aminmax(big, dim=0)
    t5 = ns()
    e.zero_()
    t6 = ns()
    print(f"after {wait_ms} ms: tensor {(t1 - t0) / 1e3:.1f} copy {(t2 - t1) / 1e3:.1f} empty {(t3 - t2) / 1e3:.1f} "
          f"zero_ {(t4 - t3) / 1e3:.1f} aminmax {(t5 - t4) / 1e3:.1f} zero_ again {(t6 - t5) / 1e3:.1f} us", flush=True)
