"""The fuzzer's cases (tests/fuzz_cases.py) through torchvor.distributed: each case
split over SIZE gloo processes (contiguous shares at random cuts, some empty), the
distributed voronoi, voronoi_graph and knn against the single-process calls on the
whole cloud (bit for bit; float32 cells up to rounding), invalid cases raising on
every rank. A line per case; the summary last.

    python tests/fuzz_distributed.py --size 3 --seed 1 --cases 200 --max-n 5000
"""
from __future__ import annotations

import argparse
import datetime
import json
import os
import socket
import sys
import tempfile
from pathlib import Path

import numpy as np
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

sys.path.insert(0, str(Path(__file__).resolve().parent))
import torchvor  # noqa: E402
import torchvor.distributed as tvd  # noqa: E402
from fuzz_cases import make_case  # noqa: E402


def compare(name, got, want, float32_cells: bool) -> list:
    """The fields of two named tuples that differ (float32 cells: beyond rounding)."""
    problems = []
    for field, a, b in zip(got._fields, got, want):
        if a is None and b is None:
            continue
        if float32_cells and a.dtype == torch.float32:
            same = torch.isclose(a.double(), b.double(), rtol=1e-5, atol=1e-7) | (a.isnan() & b.isnan())
        else:
            same = (a == b) | (a.isnan() & b.isnan()) if a.is_floating_point() and a.shape == b.shape else a == b
        if a.shape != b.shape or not bool(same.all()):
            where = (~same).nonzero()[:3].tolist() if a.shape == b.shape else f"shape {tuple(a.shape)} vs {tuple(b.shape)}"
            problems.append(f"{name}.{field} differs at {where}")
    return problems


def run_case(case, rank: int, size: int) -> list:
    points, box, batch = case.arguments("cpu")
    rng = np.random.default_rng([case.seed, case.index, 99])
    cuts = np.sort(rng.integers(0, case.n + 1, size - 1)).tolist()
    cuts = [0, *cuts, case.n]
    mine = slice(cuts[rank], cuts[rank + 1])
    my_batch = batch[mine] if batch is not None else None
    if case.expect_error is not None:
        try:
            tvd.voronoi(points[mine], box, batch=my_batch, on_failure="flag")
        except (ValueError, RuntimeError, TypeError):
            return []
        return ["invalid input: no error"]
    problems = []
    f32 = case.dtype == torch.float32
    want = torchvor.voronoi(points, box, batch=batch, on_failure="flag")
    got = tvd.voronoi(points[mine], box, batch=my_batch, on_failure="flag")
    problems += compare("voronoi", got, torchvor.VoronoiCells(*(t[mine] for t in want)), f32)
    want_graph = torchvor.voronoi_graph(points, box, batch=batch, on_failure="flag")
    got_graph = tvd.voronoi_graph(points[mine], box, batch=my_batch, on_failure="flag")
    problems += compare("graph.cells", got_graph.cells, torchvor.VoronoiCells(*(t[mine] for t in want_graph.cells)),
                        f32)
    edge = (want_graph.edge_index[1] >= cuts[rank]) & (want_graph.edge_index[1] < cuts[rank + 1])
    for field in ("edge_index", "area", "centroid"):
        a, b = getattr(got_graph, field), getattr(want_graph, field)
        b = b[:, edge] if field == "edge_index" else b[edge]
        if a.shape != b.shape or not bool(((a == b) | (a.isnan() & b.isnan()) if a.is_floating_point() else a == b)
                                           .all()):
            problems.append(f"graph.{field} differs ({tuple(a.shape)} vs {tuple(b.shape)})")
    if not torch.equal(got_graph.wall_area, want_graph.wall_area[mine]):
        problems.append("graph.wall_area differs")
    k = 8
    want_knn = torchvor.knn(points, k, batch=batch)
    got_knn = tvd.knn(points[mine], k, batch=my_batch)
    problems += compare("knn", got_knn, torchvor.KNN(*(t[mine] for t in want_knn)), False)
    return problems


def worker(rank: int, size: int, port: int, args, report: str) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    torch.set_num_threads(1)
    dist.init_process_group("gloo", rank=rank, world_size=size, timeout=datetime.timedelta(seconds=600))
    lines = []
    for index in range(args.start, args.start + args.cases):
        case = make_case(args.seed, index, max_n=args.max_n)
        try:
            problems = run_case(case, rank, size)
        except Exception as error:  # noqa: BLE001 - a finding
            problems = [f"{type(error).__name__}: {error}"]
        lines.append({"case": case.describe(), "problems": problems})
        if rank == 0 and not args.quiet:
            print(f"{case.describe()}: {'ok' if not problems else problems}", flush=True)
    with open(f"{report}.{rank}", "w") as f:
        json.dump(lines, f)
    dist.destroy_process_group()


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--size", type=int, default=2, help="processes (ranks)")
    parser.add_argument("--seed", type=int, default=1)
    parser.add_argument("--start", type=int, default=0)
    parser.add_argument("--cases", type=int, default=30)
    parser.add_argument("--max-n", type=int, default=5000)
    parser.add_argument("--quiet", action="store_true")
    args = parser.parse_args()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        report = os.path.join(tmp, "report")
        mp.spawn(worker, args=(args.size, port, args, report), nprocs=args.size, join=True)
        found = 0
        for rank in range(args.size):
            with open(f"{report}.{rank}") as f:
                for line in json.load(f):
                    if line["problems"]:
                        found += 1
                        print(f"rank {rank}: {line['case']}: {line['problems'][:4]}")
    print(f"fuzz_distributed: {args.cases} cases from {args.start}, seed {args.seed}, {args.size} ranks: "
          f"{'OK' if not found else f'{found} case-rank(s) with problems'}")
    return 0 if not found else 1


if __name__ == "__main__":
    sys.exit(main())
