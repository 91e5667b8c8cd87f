"""The fuzzer's cases (tests/fuzz_cases.py) through torchvor.distributed: each case
split over SIZE gloo processes (contiguous shares at random cuts, some empty), the
distributed voronoi, voronoi_graph and knn against the single-process calls on the
whole cloud (bit for bit; float32 cells up to rounding), invalid cases raising on
every rank; and the periodic voronoi (the case's boxes periodic along some axes, by
turns, as fuzz_periodic.py) up to rounding (the single process computes a cell that
reaches past the margin again alone, the ranks every cell with a wider margin). A
line per case; the summary last.

    python tests/fuzz_distributed.py --size 3 --seed 1 --cases 200 --max-n 5000 [--device cuda]
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
import fuzz_periodic  # noqa: E402
from fuzz_cases import make_case  # noqa: E402


# outputs counted: bit for bit, to rounding only, and of these the float64 ones
TALLY = {"bitwise": 0, "rounding": 0, "rounding_float64": 0, "rounding_float64_periodic": 0}


# this process's float64 fields that agreed to rounding only, for the case's line
FLOAT64_ROUNDED: list = []


def close(a: torch.Tensor, b: torch.Tensor, rtol: float) -> torch.Tensor:
    """Elementwise: equal, both NaN, or within rtol (relative to the larger, or
    to the tensor's scale near 0)."""
    if not a.is_floating_point():
        return a == b
    scale = float(b.abs().max()) if b.numel() and bool(torch.isfinite(b).any()) else 1.0
    near = (a.double() - b.double()).abs() <= rtol * torch.maximum(b.double().abs(), torch.full_like(b.double(), scale * 1e-3))
    return (a == b) | (a.isnan() & b.isnan()) | near


def compare(name, got, want, rtol: float, tally) -> list:
    """The fields of two named tuples that differ beyond `rtol` (integer fields:
    at all, but float32 cells' neighbour counts, which rounding moves by one);
    `tally` counts the fields equal bit for bit and those only close."""
    problems = []
    for field, a, b in zip(got._fields, got, want):
        if a is None and b is None:
            continue
        if a.shape != b.shape:
            problems.append(f"{name}.{field}: shape {tuple(a.shape)} vs {tuple(b.shape)}")
            continue
        if torch.equal(a, b) or bool(((a == b) | (a.isnan() & b.isnan()) if a.is_floating_point() else a == b).all()):
            tally["bitwise"] += 1
            continue
        ok = close(a, b, rtol) if field != "neighbors_needed" or rtol < 1e-6 else (a - b).abs() <= 1
        if bool(ok.all()):
            tally["rounding"] += 1
            if a.dtype == torch.float64:  # the plain calls' float64 outputs are meant to be bit for bit
                tally["rounding_float64_periodic" if name.startswith("periodic") else "rounding_float64"] += 1
                differ = (a != b) & ~(a.isnan() & b.isnan())
                relative = ((a - b).abs() / b.abs().clamp_min(1e-300))[differ]
                FLOAT64_ROUNDED.append(f"{name}.{field} ({int(differ.sum())} of {a.numel()}, "
                                       f"largest {float(relative.max()):.1e} relative)")
        else:
            problems.append(f"{name}.{field} differs at {(~ok).nonzero()[:3].tolist()}")
    return problems


def compare_faces(got, want, cells: slice, n: int, rtol: float, tally) -> list:
    """This rank's faces against the single-process graph's: the same edges but for
    faces of about rounding size (a face that rounding keeps on one side only),
    areas and centroids to `rtol`."""
    edge = (want.edge_index[1] >= cells.start) & (want.edge_index[1] < cells.stop)
    w_index, w_area, w_centroid = want.edge_index[:, edge], want.area[edge], want.centroid[edge]
    key_g = got.edge_index[1] * n + got.edge_index[0]
    key_w = w_index[1] * n + w_index[0]
    in_w = torch.isin(key_g, key_w)
    in_g = torch.isin(key_w, key_g)
    tiny = 1e-9 * float(w_area.abs().max()) if w_area.numel() else 0.0
    problems = []
    if bool((got.area[~in_w].abs() > tiny).any()) or bool((w_area[~in_g].abs() > tiny).any()):
        problems.append(f"graph: edges differ beyond tiny faces ({int((~in_w).sum())} only here, "
                        f"{int((~in_g).sum())} only in the single-process graph)")
    if not bool(in_w.all()) or not bool(in_g.all()):
        tally["rounding"] += 1
    a = close(got.area[in_w], w_area[in_g], rtol).all() & close(got.centroid[in_w], w_centroid[in_g], rtol).all()
    if not bool(a):
        problems.append("graph: face areas or centroids differ")
    return problems


def run_case(case, rank: int, size: int, tally, device="cpu") -> list:
    points, box, batch = case.arguments(device)
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
    rtol = 1e-5 if case.dtype == torch.float32 else 1e-12
    want = torchvor.voronoi(points, box, batch=batch, on_failure="flag")
    got = tvd.voronoi(points[mine], box, batch=my_batch, on_failure="flag")
    problems += compare("voronoi", got, torchvor.VoronoiCells(*(t[mine] for t in want)), rtol, tally)
    want_graph = torchvor.voronoi_graph(points, box, batch=batch, on_failure="flag")
    got_graph = tvd.voronoi_graph(points[mine], box, batch=my_batch, on_failure="flag")
    problems += compare("graph.cells", got_graph.cells, torchvor.VoronoiCells(*(t[mine] for t in want_graph.cells)),
                        rtol, tally)
    problems += compare_faces(got_graph, want_graph, mine, case.n, rtol, tally)
    if not bool(close(got_graph.wall_area, want_graph.wall_area[mine], rtol).all()):
        problems.append("graph.wall_area differs")
    k = 8
    want_knn = torchvor.knn(points, k, batch=batch)
    got_knn = tvd.knn(points[mine], k, batch=my_batch)
    problems += compare("knn", got_knn, torchvor.KNN(*(t[mine] for t in want_knn)), 0.0, tally)
    axes = fuzz_periodic.AXES[case.index % len(fuzz_periodic.AXES)]
    boxes = torch.tensor(case.boxes, dtype=case.dtype).to(device)
    periodic_box = boxes if batch is not None else boxes[0]
    want_p = torchvor.voronoi(points, periodic_box, batch=batch, periodic=axes, on_failure="flag")
    got_p = tvd.voronoi(points[mine], periodic_box, batch=my_batch, periodic=axes, on_failure="flag")
    problems += compare(f"periodic {axes}", got_p, torchvor.VoronoiCells(*(t[mine] for t in want_p)),
                        max(rtol, 1e-9), tally)
    return problems


def worker(rank: int, size: int, port: int, args, report: str) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    torch.set_num_threads(1)
    device = "cpu"
    if getattr(args, "device", "cpu") == "cuda":  # a GPU a rank, NCCL
        device = f"cuda:{rank % torch.cuda.device_count()}"
        torch.cuda.set_device(device)
    # a rank left waiting fails after this (an exception on one rank only)
    # NCCL told its rank's GPU: guessed from the rank, it warns of a possible hang
    dist.init_process_group("nccl" if device != "cpu" else "gloo", rank=rank, world_size=size,
                            timeout=datetime.timedelta(seconds=args.collective_timeout),
                            device_id=torch.device(device) if device != "cpu" else None)
    lines = []
    tally = dict(TALLY)
    for index in range(args.start, args.start + args.cases):
        case = make_case(args.seed, index, max_n=args.max_n)
        try:
            problems = run_case(case, rank, size, tally, device)
        except Exception as error:  # noqa: BLE001 - a finding
            problems = [f"{type(error).__name__}: {error}"]
        lines.append({"case": case.describe(), "problems": problems})
        if rank == 0 and not args.quiet:
            rounded = f" (float64 to rounding: {'; '.join(FLOAT64_ROUNDED)})" if FLOAT64_ROUNDED else ""
            print(f"{case.describe()}: {'ok' + rounded if not problems else problems}", flush=True)
        FLOAT64_ROUNDED.clear()
        if problems and any(p.split(":")[0].endswith(("Error", "Exception")) for p in problems):
            break  # the ranks may no longer meet in the same collectives: stop here
    lines.append({"tally": tally})
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
    parser.add_argument("--collective-timeout", type=float, default=300.0,
                        help="seconds a rank waits in a collective before it fails")
    parser.add_argument("--device", default="cpu", choices=["cpu", "cuda"],
                        help="cuda: a GPU a rank (ranks share GPUs beyond their count), NCCL")
    args = parser.parse_args()
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with tempfile.TemporaryDirectory() as tmp:
        report = os.path.join(tmp, "report")
        mp.spawn(worker, args=(args.size, port, args, report), nprocs=args.size, join=True)
        found, tally = 0, dict(TALLY)
        for rank in range(args.size):
            with open(f"{report}.{rank}") as f:
                for line in json.load(f):
                    if "tally" in line:
                        tally = {k: tally[k] + line["tally"][k] for k in tally}
                    elif line["problems"]:
                        found += 1
                        print(f"rank {rank}: {line['case']}: {line['problems'][:4]}")
    print(f"fuzz_distributed: {args.cases} cases from {args.start}, seed {args.seed}, {args.size} ranks: "
          f"{'OK' if not found else f'{found} case-rank(s) with problems'}; outputs equal bit for bit "
          f"{tally['bitwise']}, to rounding only {tally['rounding']} (float64: {tally['rounding_float64']}, "
          f"and {tally['rounding_float64_periodic']} periodic)")
    return 0 if not found else 1


if __name__ == "__main__":
    sys.exit(main())
