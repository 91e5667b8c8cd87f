"""CUDA only: how the CUDA kernels share out the cells (a thread or a warp
per cell, residency caps, cells finished by their vertices' balls) changes
no result, and CUDA's cells equal the CPU's.
"""
from __future__ import annotations

import re

import pytest
import torch

import torchvor
from torchvor import samples

from voronoi_checks import RTOL, UNIT, assert_same_integrals, box_of, check_global, has_cuda, ragged_batch, rand, run


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("blocks_per_sm", ["1", "1000"])
@pytest.mark.parametrize("k", [24, 48])
def test_cuda_cell_residency_changes_no_result(monkeypatch, dtype, gen, blocks_per_sm, k):
    """On CUDA, one thread per cell runs on a capped grid, each warp claiming
    32 cells at a time from a counter (CudaExec::for_each_cell), capped
    lower from k = 28; TORCHVOR_CELL_BLOCKS_PER_SM overrides the cap. One
    block an SM (every warp claims several times) and more than fit
    (clamped to what the SM holds) give the default's cells, bit for bit,
    and none is left unwritten."""
    points = rand(40000, gen, dtype, "cuda")
    monkeypatch.setenv("TORCHVOR_CELLS", "thread")  # every pass, the retries too
    default = torchvor.voronoi(points, UNIT, k=k)
    monkeypatch.setenv("TORCHVOR_CELL_BLOCKS_PER_SM", blocks_per_sm)
    capped = torchvor.voronoi(points, UNIT, k=k)
    check_global(capped, points, [box_of(points, UNIT)], dtype)
    for name in ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius"):
        assert torch.equal(getattr(default, name), getattr(capped, name)), name


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_cuda_warps_claim_many_cells(monkeypatch, dtype, gen):
    """On CUDA a warp per cell runs as a persistent kernel whose warps claim
    one cell at a time from a counter (CudaExec::for_each_cooperative). With
    40000 cells, several times the warps a GPU holds at once (at most 64 an SM),
    each warp claims many: every cell is written, and the cells are the
    thread cells' up to rounding. (Neighbour counts are compared on smaller
    sets, test_cooperative_cells_match_thread_cells: over 40000 cells a
    rounding may move one cell's radius of security by a neighbour.)"""
    points = rand(40000, gen, dtype, "cuda")
    results = {}
    for impl in ("thread", "cooperative"):
        monkeypatch.setenv("TORCHVOR_CELLS", impl)
        results[impl] = torchvor.voronoi(points, UNIT, k=24)
    coop, thread = results["cooperative"], results["thread"]
    check_global(coop, points, [box_of(points, UNIT)], dtype)
    assert torch.equal(coop.status, thread.status)
    rtol = RTOL[dtype]
    size = float(thread.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(coop.volume, thread.volume, rtol=rtol, atol=rtol * size ** 3)
    torch.testing.assert_close(coop.centroid, thread.centroid, rtol=0, atol=rtol * size)


def clip_kernels_run(call):
    """Which clip kernels a CUDA call launched: 'thread' (a thread per cell,
    CudaExec::for_each_cell), 'warp' (a warp per cell, for_each_cooperative),
    and 'vertex balls, warp' or 'vertex balls, thread' (cells finished on the
    grid, ClipFunctor's kVertexBalls: the retries past 256 neighbours)."""
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CUDA]) as prof:
        result = call()
        torch.cuda.synchronize()
    kinds = set()
    for name in (event.key for event in prof.key_averages() if "ClipFunctor" in event.key):
        cells = "warp" if "for_each_cooperative_claimed_kernel" in name else "thread"
        finished_on_grid = re.search(r"ClipFunctor<[^,>]*,[^,>]*,[^,>]*,\s*true\b", name) is not None  # kVertexBalls
        kinds.add(f"vertex balls, {cells}" if finished_on_grid else cells)
    return result, kinds


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("kind", ["voids", "wide box"])
def test_cuda_vertex_balls_match_cpu(dtype, seed, kind, cells_impl):
    """The cells finished on the grid by their vertices' balls (past 256
    neighbours: clusters with voids between them, a box three times as wide
    as the points) run on CUDA as warp cells (by default) or thread cells
    (TORCHVOR_CELLS=thread) and equal the CPU's thread cells: the same
    statuses and integrals up to rounding."""
    if kind == "voids":
        points = samples.clustered(20000, clusters=20, spread=0.02, seed=seed, dtype=dtype)
        box = UNIT
    else:
        points = samples.white_noise(20000, seed=seed, dtype=dtype)
        box = ([-1.0, -1.0, -1.0], [2.0, 2.0, 2.0])
    gpu, launched = clip_kernels_run(lambda: run(points.cuda(), box))
    assert ("vertex balls, warp" if cells_impl == "cooperative" else "vertex balls, thread") in launched
    check_global(gpu, points.cuda(), [box_of(points.cuda(), box)], dtype)
    with pytest.MonkeyPatch.context() as patch:
        patch.setenv("TORCHVOR_CELLS", "thread")
        cpu = run(points, box)
    assert_same_integrals(type(cpu)(*(t.cpu() for t in gpu)), cpu, dtype)


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("k", [None, 48])
@pytest.mark.parametrize("kind", ["jittered", "white"])
def test_cuda_cells_chosen_by_neighbor_spread(dtype, gen, seed, kind, k):
    """Over more than 16384 cells, CUDA computes a cell by a thread where the
    cells need about as many neighbours as each other, and by a warp where
    that varies widely: by the spread (standard deviation / mean) of the
    neighbours a pilot's ~1000 cells needed (CudaExec::cooperative_cells;
    0.14 on a jittered grid, 0.29-0.32 on white noise, against 0.25). A
    caller's k of 40 or more runs that pilot too, whose cells the main pass
    recomputes. Either way every cell is written and equals the CPU's up to
    rounding."""
    n = 100_000
    if kind == "jittered":
        points = samples.jittered_grid(n, seed=seed, dtype=dtype)
    else:
        points = rand(n, gen, dtype, "cpu")
    gpu, launched = clip_kernels_run(lambda: torchvor.voronoi(points.cuda(), UNIT, k=k))
    # The pilot and small retry passes are warps whatever the kind; a cell of
    # white noise near a box corner may need more than 256 neighbours.
    assert launched - {"vertex balls, warp"} == ({"thread", "warp"} if kind == "jittered" else {"warp"})
    check_global(gpu, points.cuda(), [box_of(points.cuda(), UNIT)], dtype)
    cpu = torchvor.voronoi(points, UNIT, k=k)
    assert torch.equal(cpu.status, gpu.status.cpu())
    rtol = RTOL[dtype]
    size = float(cpu.volume.double().mean()) ** (1 / 3)
    torch.testing.assert_close(gpu.volume.cpu(), cpu.volume, rtol=rtol, atol=rtol * size ** 3)
    torch.testing.assert_close(gpu.centroid.cpu(), cpu.centroid, rtol=0, atol=rtol * size)


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("kind", ["white", "clustered", "lattice", "duplicates", "batch", "small_k"])
def test_cpu_cuda_parity(dtype, gen, seed, kind):
    batch, box, k = None, UNIT, None
    if kind == "white":
        points = rand(4000, gen, dtype, "cpu")
    elif kind == "clustered":
        points = samples.clustered(4000, seed=seed, dtype=dtype)
    elif kind == "lattice":
        points = samples.lattice(12, dtype=dtype)
    elif kind == "duplicates":
        points = rand(1000, gen, dtype, "cpu")
        points = torch.cat([points, points[:300]])
    elif kind == "batch":
        batch = ragged_batch([1500, 0, 2, 900], "cpu")
        points = rand(2402, gen, dtype, "cpu")
        box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 4, dtype=dtype)
    else:
        points = rand(3000, gen, dtype, "cpu")
        k = 4
    cpu = torchvor.voronoi(points, box, batch=batch, k=k)
    gpu = torchvor.voronoi(points.cuda(), box if not isinstance(box, torch.Tensor) else box.cuda(),
                           batch=None if batch is None else batch.cuda(), k=k)
    assert torch.equal(cpu.status, gpu.status.cpu())
    rtol = RTOL[dtype]
    torch.testing.assert_close(gpu.volume.cpu(), cpu.volume, rtol=rtol, atol=rtol * cpu.volume.abs().max().item())
    torch.testing.assert_close(gpu.centroid.cpu(), cpu.centroid, rtol=rtol, atol=rtol)
    torch.testing.assert_close(gpu.second_moment.cpu(), cpu.second_moment, rtol=rtol,
                               atol=rtol * cpu.second_moment.abs().max().item())
