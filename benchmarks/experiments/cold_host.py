"""EXPERIMENT: host time of a call's first operations after the host waited on the GPU,
by how it waited (a blocking synchronize, or polling the stream)."""
import time

import torch

dev = torch.device("cuda")
big = torch.rand(10_000_000, 3, device=dev)
BOX = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
ns = time.perf_counter_ns


def wait_sync():
    torch.cuda.synchronize()


def wait_poll():
    stream = torch.cuda.current_stream()
    while not stream.query():
        pass


def wait_event_sync():
    event = torch.cuda.Event()
    event.record()
    event.synchronize()


for _ in range(3):
    for wait_ms in (30, 1):
        for name, wait in (("sync", wait_sync), ("poll", wait_poll), ("event", wait_event_sync)):
            torch.cuda._sleep(int(wait_ms * 1e-3 * 1.7e9))
            wait()
            t0 = ns()
            x = torch.tensor([BOX], dtype=torch.float32)
            t1 = ns()
            x.to(dev, non_blocking=True)
            t2 = ns()
            e = torch.empty(8, device=dev)
            e.zero_()
            t3 = ns()
            torch.aminmax(big, dim=0)
            t4 = ns()
            e.zero_()
            t5 = ns()
            print(f"{name:5s} after {wait_ms:2d} ms: tensor {(t1 - t0) / 1e3:6.1f} copy {(t2 - t1) / 1e3:6.1f} "
                  f"empty+zero_ {(t3 - t2) / 1e3:6.1f} aminmax {(t4 - t3) / 1e3:6.1f} zero_ {(t5 - t4) / 1e3:6.1f} "
                  f"all {(t5 - t0) / 1e3:6.1f} us", flush=True)
