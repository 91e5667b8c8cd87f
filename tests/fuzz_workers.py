"""The fuzzing campaign's worker processes (tests/fuzz.py --workers W): each
claims the next case of the range from a counter the workers share, and the
campaign reports them as one."""
from __future__ import annotations

import json
import os
import sys
import time
from typing import List, Sequence

import torch

FUZZ_SCRIPT = os.path.join(os.path.dirname(os.path.abspath(__file__)), "fuzz.py")


class ClaimedCases:
    """The cases of `indices` that this process claims, in order, from a
    counter file the workers share (the next position to run): a worker takes
    the next case when it finishes one, so a time budget cuts the range at
    one place rather than each worker's share at its own."""

    def __init__(self, indices: Sequence[int], counter: str):
        self.indices, self.counter = list(indices), counter

    def __iter__(self):
        import fcntl

        while True:
            with open(self.counter, "r+") as f:
                fcntl.flock(f, fcntl.LOCK_EX)
                position = int(f.read() or 0)
                f.seek(0)
                f.write(str(position + 1))
                f.truncate()
            if position >= len(self.indices):
                return
            yield self.indices[position]


def run_workers(args, argv: List[str], merge_reports, summary) -> int:
    """--workers W: W processes (fuzz.py with --worker w), each with its
    share of the CPU's threads, on CUDA the GPUs in turn, claiming cases from
    one counter (ClaimedCases), and its case lines
    in <json>.worker<w>.log (or the temporary folder's); one summary and
    report for all (fuzz.py's `merge_reports` and `summary`)."""
    import subprocess
    import tempfile

    base = args.json or os.path.join(tempfile.mkdtemp(prefix="fuzz_"), "fuzz.json")
    threads = str(max(1, (os.cpu_count() or 1) // args.workers))
    env = dict(os.environ, OMP_NUM_THREADS=threads, MKL_NUM_THREADS=threads, OPENBLAS_NUM_THREADS=threads)
    gpus = torch.cuda.device_count() if args.device == "cuda" else 0
    # the GPUs this process may use, as CUDA_VISIBLE_DEVICES names them (a worker sees one)
    visible = os.environ.get("CUDA_VISIBLE_DEVICES", "").split(",") if gpus else []
    visible = visible if len(visible) == gpus and all(visible) else [str(g) for g in range(gpus)]
    with open(f"{base}.next", "w") as f:  # ClaimedCases' counter
        f.write("0")
    children = []
    for w in range(args.workers):
        if gpus > 1:
            env = dict(env, CUDA_VISIBLE_DEVICES=visible[w % gpus])
        command = [sys.executable, FUZZ_SCRIPT, *argv, "--worker", str(w),
                   "--json", f"{base}.worker{w}", "--claim", f"{base}.next"]
        log = open(f"{base}.worker{w}.log", "w")
        children.append((subprocess.Popen(command, stdout=log, stderr=subprocess.STDOUT, env=env), log))
    # Past the time budget and --grace more, a worker still in a case is
    # stopped; its report as of its last finished case counts.
    deadline = time.monotonic() + args.time_budget + args.grace if args.time_budget > 0 else None
    reports, stopped = [], []
    for w, (child, log) in enumerate(children):
        try:
            # past the deadline, each worker still in a case is stopped at once (not a second each)
            child.wait(timeout=None if deadline is None else max(0.0, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            child.kill()
            child.wait()
            stopped.append(w)
        log.close()
        try:
            with open(f"{base}.worker{w}") as f:
                reports.append(json.load(f))
        except (OSError, ValueError):
            if w not in stopped:
                print(f"fuzz: worker {w} left no report (exit status {child.returncode}): see {base}.worker{w}.log")
                return 1
    if not reports:
        print("fuzz: no worker finished a case")
        return 1
    report = merge_reports(reports)
    print(summary(report), flush=True)
    if args.case is None:  # where a campaign cut by its budget goes on
        with open(f"{base}.next") as f:
            claimed = min(int(f.read() or 0), args.cases)
        print(f"fuzz: cases {args.start} to {args.start + claimed - 1} claimed; the next is {args.start + claimed}")
    if stopped:
        print(f"fuzz: workers {stopped} stopped {args.grace:g} s past the time budget, in a case not counted")
    if args.json:
        with open(args.json, "w") as f:
            json.dump(report.as_dict(), f, indent=1, default=str)
    return 0 if report.ok() and all(child.returncode == 0 for w, (child, _) in enumerate(children)
                                    if w not in stopped) else 1
