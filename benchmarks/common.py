"""Shared helpers of the torchvor benchmarks: arguments, environment header,
timing, memory, point sets (with a cache for blue noise) and Markdown tables.

Benchmarks only measure and print; nothing here asserts on speed.
"""
from __future__ import annotations

import argparse
import datetime
import math
import os
import platform
import statistics
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Callable, NamedTuple, Optional

import torch

import torchvor
from torchvor import samples

HERE = Path(__file__).resolve().parent
UNIT_BOX = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
MiB = float(1 << 20)

# ---- arguments --------------------------------------------------------------------------

_SUFFIX = {"K": 10**3, "M": 10**6, "G": 10**9}


def parse_size(text: str) -> int:
    """'20000', '100K', '1M', '1.5M', '10M' -> int."""
    text = text.strip().upper()
    scale = _SUFFIX.get(text[-1:], 1)
    if scale != 1:
        text = text[:-1]
    return int(round(float(text) * scale))


def parse_sizes(text: str) -> list[int]:
    return [parse_size(part) for part in text.split(",") if part.strip()]


def parse_ints(text: str) -> list[int]:
    return [int(part) for part in text.split(",") if part.strip()]


def base_parser(description: str) -> argparse.ArgumentParser:
    """Options every benchmark accepts; scripts add their own."""
    parser = argparse.ArgumentParser(description=description)
    parser.add_argument("--device", choices=("cpu", "cuda"), default="cpu")
    parser.add_argument("--sizes", type=parse_sizes, default=None,
                        help="comma-separated point counts, suffixes K/M/G allowed (e.g. 100K,1M,10M)")
    parser.add_argument("--repeats", type=int, default=5, help="timed runs; the median is reported")
    parser.add_argument("--warmup", type=int, default=1, help="untimed runs before timing torchvor")
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--cache-dir", type=Path, default=HERE / ".cache",
                        help="where generated blue-noise point sets are kept (default benchmarks/.cache)")
    parser.add_argument("--blue-iters", type=int, default=100,
                        help="Lloyd iterations that turn white noise into blue noise")
    return parser


def setup(args) -> tuple[torch.device, torch.dtype]:
    """Check the device, print the environment header; returns (device, dtype)."""
    if args.device == "cuda" and not torch.cuda.is_available():
        sys.exit("--device cuda: torch.cuda.is_available() is False")
    device = torch.device(args.device)
    print_header(device)
    return device, getattr(torch, args.dtype)


# ---- environment ------------------------------------------------------------------------


def git_commit() -> str:
    """The COMMIT environment variable when set (a copied tree, e.g. on the GPU machine,
    may carry a stale .git); else the checkout's short commit, '+dirty' when tracked
    files differ; else 'unknown'."""
    if os.environ.get("COMMIT"):
        return os.environ["COMMIT"]

    def git(*argv):
        return subprocess.run(["git", "--no-optional-locks", *argv], cwd=HERE, capture_output=True,
                              text=True, timeout=10)
    try:
        head = git("rev-parse", "--short", "HEAD")
        if head.returncode == 0:
            dirty = git("diff", "--quiet", "HEAD", "--").returncode == 1
            return head.stdout.strip() + ("+dirty" if dirty else "")
    except (OSError, subprocess.SubprocessError):
        pass
    return "unknown"


def cpu_model() -> str:
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith("model name"):
                    return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown CPU"


def device_name(device: torch.device) -> str:
    if device.type == "cuda":
        props = torch.cuda.get_device_properties(device)
        return f"{torch.cuda.get_device_name(device)} ({props.total_memory / 2**30:.0f} GiB)"
    return (f"{cpu_model()}, {os.cpu_count()} cores, torch threads {torch.get_num_threads()}, "
            f"clip loop {torch.ops.torchvor.cpu_isa()}")


def print_header(device: torch.device) -> None:
    cuda = f", CUDA {torch.version.cuda}" if torch.version.cuda else ""
    print(f"# {Path(sys.argv[0]).name} {' '.join(sys.argv[1:])}")
    print(f"- date: {datetime.datetime.now().astimezone().isoformat(timespec='seconds')}")
    print(f"- commit: {git_commit()}")
    print(f"- torch {torch.__version__}{cuda}, torchvor {torchvor.__version__}, Python {platform.python_version()}")
    print(f"- device: {device_name(device)}")
    if device.type == "cuda":
        print(f"- host CPU: {cpu_model()}, {os.cpu_count()} cores")
    print(flush=True)


def log(*parts) -> None:
    print(*parts, flush=True)


# ---- timing -----------------------------------------------------------------------------


def synchronize(device: torch.device) -> None:
    if device.type == "cuda":
        torch.cuda.synchronize(device)


def time_runs(fn: Callable[[], object], device: torch.device, warmup: int = 1, repeats: int = 5) -> list[float]:
    """Seconds of each of ``repeats`` calls of fn after ``warmup`` untimed calls.

    CUDA: CUDA events around each call, after synchronising; CPU: perf_counter.
    """
    device = torch.device(device)
    for _ in range(warmup):
        fn()
    synchronize(device)
    times = []
    for _ in range(max(1, repeats)):
        if device.type == "cuda":
            start, end = torch.cuda.Event(enable_timing=True), torch.cuda.Event(enable_timing=True)
            start.record()
            fn()
            end.record()
            end.synchronize()
            times.append(start.elapsed_time(end) / 1e3)
        else:
            start = time.perf_counter()
            fn()
            times.append(time.perf_counter() - start)
    return times


def time_fn(fn: Callable[[], object], device: torch.device, warmup: int = 1, repeats: int = 5) -> float:
    """Median seconds of fn (see :func:`time_runs`)."""
    return statistics.median(time_runs(fn, device, warmup, repeats))


class Stopwatch:
    """Per-step times of a sequence of calls (Lloyd iterations): CUDA events on the GPU,
    read after one final synchronisation, so steps are not serialised by the timer."""

    def __init__(self, device: torch.device):
        self.device = torch.device(device)
        self.marks: list = []

    def mark(self) -> None:
        if self.device.type == "cuda":
            event = torch.cuda.Event(enable_timing=True)
            event.record()
            self.marks.append(event)
        else:
            self.marks.append(time.perf_counter())

    def steps(self) -> list[float]:
        if self.device.type == "cuda":
            self.marks[-1].synchronize()
            return [a.elapsed_time(b) / 1e3 for a, b in zip(self.marks, self.marks[1:])]
        return [b - a for a, b in zip(self.marks, self.marks[1:])]


# ---- memory -----------------------------------------------------------------------------


def tensor_bytes(obj) -> int:
    """Bytes of all tensors in obj (a tensor or nested tuples/lists/dicts of them)."""
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return tensor_bytes(list(obj.values()))
    if isinstance(obj, (tuple, list)):
        return sum(tensor_bytes(item) for item in obj)
    return 0


class Memory(NamedTuple):
    peak: float  # bytes, see MEMORY_NOTE
    work: float  # peak beyond inputs and outputs, bytes


MEMORY_NOTE = {
    "cuda": "peak = torch.cuda.max_memory_allocated() during the call (inputs included); "
            "work = peak - memory allocated before the call (the inputs) - bytes of the outputs, "
            "i.e. temporary memory beyond inputs and outputs. The caching allocator's reserve is not counted.",
    "cpu": "peak = growth of the process's resident set size during the call, sampled every 1 ms "
           "from /proc/self/statm (ru_maxrss growth where /proc is missing); inputs are already resident, "
           "outputs are included; work = peak - bytes of the outputs. Approximate: the allocator may "
           "reuse freed pages (under-report) or keep them (over-report).",
}


def _rss_bytes() -> Optional[int]:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except (OSError, ValueError):
        return None


def _maxrss_bytes() -> int:
    import resource

    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # Linux: KiB


def measure_memory(fn: Callable[[], object], device: torch.device) -> tuple[Memory, object]:
    """Run fn once and return (Memory, fn's result). See MEMORY_NOTE for what is measured."""
    device = torch.device(device)
    if device.type == "cuda":
        synchronize(device)
        torch.cuda.reset_peak_memory_stats(device)
        before = torch.cuda.memory_allocated(device)
        out = fn()
        synchronize(device)
        peak = torch.cuda.max_memory_allocated(device)
        return Memory(peak, max(0, peak - before - tensor_bytes(out))), out
    base = _rss_bytes()
    if base is None:  # no /proc: high-water mark growth only
        before = _maxrss_bytes()
        out = fn()
        growth = max(0, _maxrss_bytes() - before)
        return Memory(growth, max(0, growth - tensor_bytes(out))), out
    peak = [base]
    done = threading.Event()

    def sample():  # torchvor's ops release the GIL, so this thread keeps sampling during the call
        while not done.is_set():
            peak[0] = max(peak[0], _rss_bytes() or 0)
            done.wait(0.001)

    sampler = threading.Thread(target=sample, daemon=True)
    sampler.start()
    try:
        out = fn()
    finally:
        done.set()
        sampler.join()
    peak[0] = max(peak[0], _rss_bytes() or 0)
    growth = peak[0] - base
    return Memory(growth, max(0, growth - tensor_bytes(out))), out


# ---- point sets -------------------------------------------------------------------------

POINT_KINDS = ("white", "uniform", "perturbed", "jittered", "blue")


def make_points(kind: str, n: int, *, seed: int, dtype: torch.dtype, device: torch.device,
                cache_dir: Path, blue_iters: int = 100) -> tuple[torch.Tensor, str]:
    """(points, label) of a point set of ``torchvor.samples`` in the unit cube; grids give
    about n points. 'blue' (``samples.blue_noise``: white noise after ``blue_iters`` Lloyd
    iterations) is cached in cache_dir by (n, seed, dtype, iterations)."""
    if kind in ("white", "uniform"):
        return samples.white_noise(n, seed=seed, dtype=dtype, device=device), kind
    if kind == "perturbed":
        return samples.perturbed_grid(n, seed=seed, dtype=dtype, device=device), kind
    if kind == "jittered":
        return samples.jittered_grid(n, seed=seed, dtype=dtype, device=device), kind
    if kind != "blue":
        raise ValueError(f"unknown point kind {kind!r}; choose from {POINT_KINDS}")
    path = Path(cache_dir) / f"blue_n{n}_seed{seed}_{str(dtype).replace('torch.', '')}_lloyd{blue_iters}.pt"
    if path.exists():
        log(f"blue noise n={n}: loaded from {path}")
        return torch.load(path, weights_only=True).to(device), kind
    log(f"blue noise n={n}: {blue_iters} Lloyd iterations on {device} ...")
    start = time.perf_counter()
    points = samples.blue_noise(n, iters=blue_iters, seed=seed, dtype=dtype, device=device)
    synchronize(device)
    log(f"blue noise n={n}: generated in {time.perf_counter() - start:.1f} s, cached to {path}")
    path.parent.mkdir(parents=True, exist_ok=True)
    partial = path.with_suffix(f".tmp{os.getpid()}")
    torch.save(points.cpu(), partial)
    os.replace(partial, path)
    return points, kind


def profile_calls(calls, device: torch.device, label: str, rows: int = 16) -> None:
    """Print the operators and kernels of each (name, fn) call, by self time."""
    from torch.profiler import ProfilerActivity, profile as torch_profile

    activities = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device.type == "cuda" else [])
    sort = "self_cuda_time_total" if device.type == "cuda" else "self_cpu_time_total"
    for name, fn in calls:
        with torch_profile(activities=activities) as prof:
            fn()
            synchronize(device)
        log(f"profile of {name}, {label}:\n" + prof.key_averages().table(
            sort_by=sort, row_limit=rows, max_name_column_width=60))


def neighbor_percentiles(neighbors: torch.Tensor, qs=(0.5, 0.99, 1.0)) -> list[int]:
    """Percentiles of the (small, integer) neighbour counts from their histogram."""
    counts = torch.bincount(neighbors.long().clamp(min=0)).cumsum(0).cpu()
    total = int(counts[-1])
    return [int(torch.searchsorted(counts, max(1, math.ceil(q * total)))) for q in qs]


def npoints_label(n: int) -> str:
    """1000000 -> '1M', 100000 -> '100K', 97336 -> '97,336'."""
    for scale, suffix in ((10**9, "G"), (10**6, "M"), (10**3, "K")):
        if n >= scale and n % scale == 0:
            return f"{n // scale}{suffix}"
    return f"{n:,}"


# ---- tables -----------------------------------------------------------------------------


def fmt_s(seconds: Optional[float]) -> str:
    if seconds is None:
        return "—"
    if abs(seconds) < 1e-3:
        return f"{seconds * 1e6:.0f} µs"
    if abs(seconds) < 1:
        return f"{seconds * 1e3:.1f} ms"
    return f"{seconds:.2f} s"


def fmt_mib(nbytes: Optional[float]) -> str:
    return "—" if nbytes is None else f"{nbytes / MiB:,.0f}"


def fmt_ratio(ratio: Optional[float]) -> str:
    if ratio is None:
        return "—"
    return f"{ratio:.0f}×" if ratio >= 100 else f"{ratio:.3g}×"


def markdown_table(headers: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(headers) + " |", "|" + "|".join("---" for _ in headers) + "|"]
    lines += ["| " + " | ".join(str(cell) for cell in row) + " |" for row in rows]
    return "\n".join(lines)


def print_results(title: str, headers: list[str], rows: list[list], notes: list[str] = ()) -> None:
    print(f"\n### {title}\n")
    print(markdown_table(headers, rows))
    if notes:
        print()
        for note in dict.fromkeys(notes):  # in order, without repeats
            print(f"- {note}")
    print(flush=True)
