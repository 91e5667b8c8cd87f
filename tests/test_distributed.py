"""torchvor.distributed against the single-process calls on the whole cloud:
2 and 3 CPU processes over gloo, each with its share of the points (random,
skewed, empty), bit for bit. Each world size is one spawn that runs every
scenario (a spawn costs seconds of imports)."""
from __future__ import annotations

import datetime
import json
import math
import os
import socket
import sys

import pytest
import torch
import torch.distributed as dist
import torch.multiprocessing as mp

import torchvor
import torchvor.distributed as tvd
from torchvor import _slabs, samples

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _cloud(kind: str, dtype):
    """(points, batch or None, box): the whole cloud of a scenario (every rank makes the same)."""
    if kind == "white":
        return samples.white_noise(3000, seed=5, dtype=dtype), None, UNIT
    if kind == "clustered":
        return samples.clustered(3000, seed=6, dtype=dtype), None, None
    if kind == "batches":
        a = samples.white_noise(900, seed=7, dtype=dtype)
        b = samples.clustered(1100, seed=8, dtype=dtype) * 0.5 + 0.25
        batch = torch.cat([torch.zeros(900, dtype=torch.int64), torch.ones(1100, dtype=torch.int64)])
        return torch.cat([a, b]), batch, UNIT
    if kind == "tiny":
        return samples.white_noise(7, seed=9, dtype=dtype), None, UNIT
    raise ValueError(kind)


def _split(n: int, size: int, how: str):
    """The cut points of [0, n) into `size` contiguous shares."""
    if how == "even":
        return [n * r // size for r in range(size + 1)]
    if how == "first":  # every point on rank 0
        return [0] + [n] * size
    if how == "last_empty":  # the last rank has none
        return [n * r // (size - 1) for r in range(size)] + [n]
    raise ValueError(how)


SCENARIOS = [("white", "even", torch.float64), ("white", "first", torch.float64),
             ("clustered", "even", torch.float64), ("clustered", "last_empty", torch.float32),
             ("batches", "even", torch.float64), ("tiny", "even", torch.float64),
             ("white", "even", torch.float32)]


def _same(name, got, want, problems, periodic=False):
    """Bit for bit in float64; float32 cells up to rounding (a float32 cell's
    vertices are rounded to 18 bits in the first tier, and which pass
    computes a cell depends on the pilot's k, which each rank's share picks),
    their neighbour counts to one. `periodic`: every dtype to rounding (the
    single process computes a cell that reaches past the margin again alone,
    among the points within its reach, where the ranks compute every cell
    again with a wider margin)."""
    float32_cells = got[0].dtype == torch.float32 and "knn" not in name
    rtol = 1e-5 if float32_cells else 1e-9
    for field, a, b in zip(got._fields, got, want):
        if a.dtype.is_floating_point and (periodic or (float32_cells and a.dtype == torch.float32)):
            if periodic:  # centroids relative to the box's size
                atol = rtol * float(b.abs().max()) if field == "centroid" and b.numel() else 0.0
            else:
                atol = 1e-7
            close = torch.isclose(a.double(), b.double(), rtol=rtol, atol=atol) | (a.isnan() & b.isnan())
        elif (periodic or float32_cells) and field == "neighbors_needed":  # rounding moves a radius of security
            close = (a - b).abs() <= 1
        else:
            close = a == b
        if a.shape != b.shape or not bool(close.all()):
            diff = (~close).nonzero()[:3].tolist() if a.shape == b.shape else f"shape {tuple(a.shape)}"
            problems.append(f"{name}: {field} differs at {diff}")


def _worker(rank: int, size: int, port: int, report: str) -> None:
    os.environ["MASTER_ADDR"], os.environ["MASTER_PORT"] = "127.0.0.1", str(port)
    torch.set_num_threads(1)
    # a collective that waits longer fails (a rank left waiting would hang the suite)
    dist.init_process_group("gloo", rank=rank, world_size=size, timeout=datetime.timedelta(seconds=120))
    problems = []
    rounds = []  # halos a call computed with: some scenario must grow its halo
    cloud = _slabs.Local.cloud

    def counted(self, width):
        rounds.append(width)
        return cloud(self, width)

    _slabs.Local.cloud = counted
    try:
        for kind, how, dtype in SCENARIOS:
            points, batch, box = _cloud(kind, dtype)
            # a random (non-spatial) order of the cloud, the same on every rank
            order = torch.randperm(points.shape[0], generator=torch.Generator().manual_seed(11))
            if batch is not None:  # batches must stay sorted: shuffle within each cloud
                order = order[torch.sort(batch[order], stable=True).indices]
            points = points[order]
            batch = batch[order] if batch is not None else None
            cuts = _split(points.shape[0], size, how)
            mine = slice(cuts[rank], cuts[rank + 1])
            name = f"{kind}/{how}/{dtype}"
            want = torchvor.voronoi(points, box, batch=batch, on_failure="flag")
            got = tvd.voronoi(points[mine], box, batch=batch[mine] if batch is not None else None, on_failure="flag")
            _same(name + " voronoi", got, torchvor.VoronoiCells(*(t[mine] for t in want)), problems)
            if box is not None:  # periodic: the points moved across the faces too
                axes = (True, True, True) if dtype == torch.float64 else (True, False, True)
                moved = points + torch.tensor([0.5, 0.0, 1.0], dtype=dtype) * torch.tensor(axes, dtype=dtype)
                b = batch[mine] if batch is not None else None
                want_p = torchvor.voronoi(moved, box, batch=batch, periodic=axes, on_failure="flag")
                got_p = tvd.voronoi(moved[mine], box, batch=b, periodic=axes, on_failure="flag")
                _same(name + " periodic voronoi", got_p, torchvor.VoronoiCells(*(t[mine] for t in want_p)), problems,
                      periodic=True)
            want_graph = torchvor.voronoi_graph(points, box, batch=batch, on_failure="flag")
            got_graph = tvd.voronoi_graph(points[mine], box, batch=batch[mine] if batch is not None else None,
                                          on_failure="flag")
            _same(name + " graph cells", got_graph.cells, torchvor.VoronoiCells(*(t[mine] for t in want_graph.cells)),
                  problems)
            ends = [cuts[rank], cuts[rank + 1]]
            edge = (want_graph.edge_index[1] >= ends[0]) & (want_graph.edge_index[1] < ends[1])
            for field in ("edge_index", "area", "centroid"):
                a, b = getattr(got_graph, field), getattr(want_graph, field)
                b = b[:, edge] if field == "edge_index" else b[edge]
                if a.shape != b.shape or not torch.equal(a, b):
                    problems.append(f"{name} graph: {field} differs ({tuple(a.shape)} vs {tuple(b.shape)})")
            if not torch.equal(got_graph.wall_area, want_graph.wall_area[mine]):
                problems.append(f"{name} graph: wall_area differs")
            if how == "even" and dtype == torch.float64 and kind in ("white", "batches"):
                want_lloyd, want_history = torchvor.lloyd(points, box, iters=3, batch=batch, return_history=True)
                got_lloyd, got_history = tvd.lloyd(points[mine], box, iters=3, return_history=True,
                                                   batch=batch[mine] if batch is not None else None)
                if not torch.equal(got_lloyd, want_lloyd[mine]):
                    problems.append(f"{name} lloyd: points differ")
                # a callback that stops on rank 0 only stops every rank, after that iteration
                seen = []

                def stop_at_one(iteration, moved, cells):
                    seen.append((iteration, moved.shape[0], cells.volume.shape[0]))
                    return rank == 0 and iteration == 1

                stopped = tvd.lloyd(points[mine], box, iters=5, callback=stop_at_one,
                                    batch=batch[mine] if batch is not None else None)
                want_two = torchvor.lloyd(points, box, iters=2, batch=batch)
                n_mine = cuts[rank + 1] - cuts[rank]
                if not torch.equal(stopped, want_two[mine]) or seen != [(0, n_mine, n_mine), (1, n_mine, n_mine)]:
                    problems.append(f"{name} lloyd callback: stopped wrong ({seen})")
                for a, b in zip(got_history, want_history):
                    if (abs(a.energy - b.energy) > 1e-12 * abs(b.energy)
                            or abs(a.max_displacement - b.max_displacement) > 1e-12 * b.max_displacement):
                        problems.append(f"{name} lloyd: history differs: {a} vs {b}")
                # periodic: the points wrap into the box (to rounding, as the periodic cells)
                want_p = torchvor.lloyd(points, box, iters=3, batch=batch, periodic=True)
                got_p = tvd.lloyd(points[mine], box, iters=3, periodic=True,
                                  batch=batch[mine] if batch is not None else None)
                if not torch.allclose(got_p, want_p[mine], rtol=0, atol=1e-12):
                    problems.append(f"{name} periodic lloyd: points differ by {(got_p - want_p[mine]).abs().max()}")
            k = 8
            want_knn = torchvor.knn(points, k, batch=batch)
            got_knn = tvd.knn(points[mine], k, batch=batch[mine] if batch is not None else None)
            _same(name + " knn", got_knn, torchvor.KNN(*(t[mine] for t in want_knn)), problems)
            # queries of their own, another share of them on each rank (rank 0 has none)
            queries = samples.white_noise(500, seed=12, dtype=dtype) * 1.2 - 0.1
            query_batch = (torch.arange(500) >= 250).long() if batch is not None else None
            q_cuts = [0] + [500 * r // (size - 1) for r in range(size)]
            q_mine = slice(q_cuts[rank], q_cuts[rank + 1])
            want_q = torchvor.knn(points, k, queries, batch=batch, query_batch=query_batch)
            got_q = tvd.knn(points[mine], k, queries[q_mine], batch=batch[mine] if batch is not None else None,
                            query_batch=query_batch[q_mine] if query_batch is not None else None)
            _same(name + " knn queries", got_q, torchvor.KNN(*(t[q_mine] for t in want_q)), problems)
        if len(rounds) <= 2 * len(SCENARIOS):
            problems.append(f"no halo grew: {rounds}")
        # an invalid input on one rank: every rank raises, none waits
        bad = torch.rand(5, 3, dtype=torch.float64)
        if rank == size - 1:
            bad[0, 0] = float("nan")
        try:
            tvd.voronoi(bad, UNIT)
            problems.append("NaN on one rank: no error")
        except ValueError as error:
            if rank == size - 1 and "NaN" not in str(error):
                problems.append(f"NaN on one rank: {error}")
        # a point outside the given box on one rank: every rank raises
        outside = torch.rand(5, 3, dtype=torch.float64) * 0.5
        if rank == 0:
            outside[0, 0] = 2.0
        try:
            tvd.voronoi(outside, UNIT)
            problems.append("a point outside the box: no error")
        except (ValueError, RuntimeError) as error:
            if rank == 0 and "box" not in str(error):
                problems.append(f"a point outside the box: {error}")
        # periodic along x and z: outside along x is fine, outside along y (not periodic) raises everywhere
        wrapped = torch.rand(5, 3, dtype=torch.float64) + torch.tensor([1.5, 0.0, -2.0], dtype=torch.float64)
        cells = tvd.voronoi(wrapped, UNIT, periodic=(True, False, True))
        if cells.volume.shape != (5,) or not bool((cells.status == 0).all()):
            problems.append(f"periodic outside a periodic axis: {cells.status.tolist()}")
        if rank == 0:
            wrapped[0, 1] = 1.5
        try:
            tvd.voronoi(wrapped, UNIT, periodic=(True, False, True))
            problems.append("periodic, a point outside a non-periodic axis: no error")
        except (ValueError, RuntimeError) as error:
            if rank == 0 and "not periodic" not in str(error):
                problems.append(f"periodic, a point outside a non-periodic axis: {error}")
        # periodic along no axis is the plain call
        plain = tvd.voronoi(outside.clamp(0, 1), UNIT, periodic=(False, False, False))
        if not torch.equal(plain.volume, tvd.voronoi(outside.clamp(0, 1), UNIT, periodic=None).volume):
            problems.append("periodic along no axis: not the plain call")
        try:
            tvd.voronoi_graph(wrapped, UNIT, periodic=True)
            problems.append("periodic voronoi_graph: no error")
        except NotImplementedError:
            pass
    except Exception as error:  # noqa: BLE001 - reported to the test
        problems.append(f"{type(error).__name__}: {error}")
    finally:
        with open(f"{report}.{rank}", "w") as f:
            json.dump(problems, f)
        dist.destroy_process_group()


@pytest.mark.parametrize("size", [2, 3])
def test_distributed_matches_single_process(tmp_path, size):
    if not dist.is_available():
        pytest.skip("torch.distributed is not available")
    report = str(tmp_path / "report")
    mp.spawn(_worker, args=(size, _free_port(), report), nprocs=size, join=True)
    problems = []
    for rank in range(size):
        with open(f"{report}.{rank}") as f:
            problems += [f"rank {rank}: {p}" for p in json.load(f)]
    assert not problems, "\n".join(problems[:20])


def test_distributed_fuzz_slice(tmp_path):
    """The fuzzer's first cases (seed 1, every kind, both dtypes, invalid ones
    too) over 3 ranks, bit for bit against the single-process calls
    (tests/fuzz_distributed.py runs more)."""
    if not dist.is_available():
        pytest.skip("torch.distributed is not available")
    import argparse

    import fuzz_distributed

    args = argparse.Namespace(seed=1, start=0, cases=45, max_n=2000, quiet=True, collective_timeout=120.0)
    report = str(tmp_path / "report")
    mp.spawn(fuzz_distributed.worker, args=(3, _free_port(), args, report), nprocs=3, join=True)
    problems = []
    for rank in range(3):
        with open(f"{report}.{rank}") as f:
            problems += [f"rank {rank}: {line['case']}: {line['problems'][:3]}" for line in json.load(f)
                         if line.get("problems")]
    assert not problems, "\n".join(problems[:10])


def test_merged_positions_merge_two_sorted_lists():
    """_slabs.merged_positions and merged: two sorted lists of distinct
    indices (one long, one short, either empty) placed as a sort would."""
    generator = torch.Generator().manual_seed(3)
    for n, m in [(1000, 37), (50, 0), (0, 20), (1, 1), (300, 300)]:
        every = torch.randperm(4 * (n + m) + 1, generator=generator)[: n + m]
        first, second = every[:n].sort().values, every[n:].sort().values
        at = _slabs.merged_positions(first, second)
        assert torch.equal(_slabs.merged(*at, first, second), every.sort().values)
        rows = torch.rand(n, 3, generator=generator)
        assert torch.equal(_slabs.merged(*at, rows, torch.full((m, 3), -1.0))[at[0]], rows)


def test_slab_tests_in_the_points_dtype_are_the_float64_tests():
    """Slabs.near compares float32 coordinates with each edge rounded up to
    float32: the same rows as the comparison in float64, at and around the
    edges too."""
    generator = torch.Generator().manual_seed(5)
    slabs = object.__new__(_slabs.Slabs)
    edges = torch.rand(3, generator=generator, dtype=torch.float64).sort().values.tolist()
    slabs.bounds, slabs.size = [-math.inf, *edges, math.inf], 4
    for width in (0.0, 1e-3, 0.37, math.inf):
        near_edges = torch.tensor([e + sign * width for e in edges for sign in (-1, 1)]).float()
        up, down = torch.nextafter(near_edges, near_edges + 1), torch.nextafter(near_edges, near_edges - 1)
        x = torch.cat([torch.rand(5000, generator=generator), near_edges, up, down])
        x = x[torch.isfinite(x)]
        for dtype in (torch.float32, torch.float64):
            for s in range(slabs.size):
                wide = x.double()
                want = (wide >= slabs.bounds[s] - width) & (wide < slabs.bounds[s + 1] + width)
                assert torch.equal(slabs.near(x.to(dtype), s, width), want), (width, dtype, s)


def test_distributed_needs_init():
    points = torch.rand(10, 3, dtype=torch.float64)
    if dist.is_available() and dist.is_initialized():
        pytest.skip("a process group exists in this process")
    with pytest.raises(RuntimeError, match="init_process_group"):
        tvd.voronoi(points, UNIT)


if __name__ == "__main__":
    sys.exit(pytest.main([__file__, "-q"]))
