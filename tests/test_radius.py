"""torchvor.radius and radius_graph against brute force in float64 and scipy's cKDTree."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor
from oracles import distances_separated


def rand(n, gen, dtype, device, scale=1.0, offset=0.0):
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) * scale + offset).to(dtype).to(device)


def ragged_batch(sizes, device):
    return torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes)).to(device)


def brute_force(points, queries, r, exclude_self, batch=None, query_batch=None):
    """(point, query) pairs within r in float64 of the inputs' values, and the
    pairs within a rounding of r (either answer is right for those)."""
    p, q = points.double().cpu(), queries.double().cpu()
    d2 = ((q[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    inside = d2 <= r * r
    near = (d2 - r * r).abs() <= 1e-5 * r * r + 1e-30
    if exclude_self:
        eye = torch.eye(len(q), len(p), dtype=torch.bool)
        inside &= ~eye
        near &= ~eye
    if batch is not None:
        same = query_batch.cpu()[:, None] == batch.cpu()[None, :]
        inside &= same
        near &= same
    return inside, near


def check_against_brute_force(result, points, queries, r, exclude_self, batch=None, query_batch=None):
    inside, near = brute_force(points, queries, r, exclude_self, batch, query_batch)
    got = torch.zeros_like(inside)
    src, dst = result.edge_index.cpu()
    got[dst, src] = True
    assert int(got.sum()) == result.edge_index.shape[1], "an edge appears twice"
    wrong = (got != inside) & ~near
    assert not wrong.any(), f"{int(wrong.sum())} pairs differ from brute force, e.g. {wrong.nonzero()[:5].tolist()}"
    d2 = ((queries.double().cpu()[dst] - points.double().cpu()[src]) ** 2).sum(-1)
    tol = 1e-6 if points.dtype == torch.float32 else 1e-14
    torch.testing.assert_close(result.dist2.double().cpu(), d2, rtol=tol, atol=tol * r * r)


def check_sorted(result, num_queries):
    """By query, then distance, then point index."""
    src, dst = result.edge_index.cpu()
    d2 = result.dist2.cpu()
    key_ok = (dst[1:] > dst[:-1]) | ((dst[1:] == dst[:-1]) & (
        (d2[1:] > d2[:-1]) | ((d2[1:] == d2[:-1]) & (src[1:] > src[:-1]))))
    assert bool(key_ok.all()), "edges are not sorted by (query, dist2, point)"
    assert dst.numel() == 0 or (0 <= int(dst.min()) and int(dst.max()) < num_queries)


@pytest.mark.parametrize("r", [0.02, 0.1, 0.35])
def test_uniform_points(device, dtype, gen, r):
    points = rand(600, gen, dtype, device)
    result = torchvor.radius(points, r)
    check_against_brute_force(result, points, points, r, exclude_self=True)
    check_sorted(result, 600)


@pytest.mark.parametrize("r", [1.5, 3.2])
def test_lattice_ties_sorted(device, dtype, gen, r):
    """An 8^3 integer lattice in shuffled order: every list repeats distances
    and is ordered by (distance, point index); at r = 3.2 an inner point's
    list holds more than 128 points (past the host's rank count)."""
    axis = torch.arange(8, dtype=dtype)
    lattice = torch.cartesian_prod(axis, axis, axis)
    points = lattice[torch.randperm(len(lattice), generator=gen)].to(device)
    result = torchvor.radius(points, r)
    check_against_brute_force(result, points, points, r, exclude_self=True)
    check_sorted(result, len(points))
    if r > 3:
        assert int(torch.bincount(result.edge_index[1].cpu()).max()) > 128


def test_against_ckdtree_query_pairs(device, gen):
    from scipy.spatial import cKDTree

    points = rand(3000, gen, torch.float64, device)
    edges = torchvor.radius_graph(points, 0.07).cpu()
    pairs = cKDTree(points.cpu().numpy()).query_pairs(0.07, output_type="ndarray")
    expected = np.concatenate([pairs, pairs[:, ::-1]])
    got = edges.t().numpy()
    assert len(got) == len(expected)
    assert set(map(tuple, got)) == set(map(tuple, expected))


def test_separate_queries(device, dtype, gen):
    points = rand(400, gen, dtype, device)
    queries = rand(150, gen, dtype, device, scale=1.4, offset=-0.2)  # some outside the points' box
    result = torchvor.radius(points, 0.15, queries)
    check_against_brute_force(result, points, queries, 0.15, exclude_self=False)
    check_sorted(result, 150)


def test_clustered_and_far_from_zero(device, dtype, gen):
    centre = rand(5, gen, torch.float64, device) * 100 + 1000
    points = (centre.repeat_interleave(80, 0) + 1e-2 * torch.randn(400, 3, generator=gen, dtype=torch.float64)
              .to(device)).to(dtype)
    result = torchvor.radius(points, 0.01)
    check_against_brute_force(result, points, points, 0.01, exclude_self=True)


def test_ragged_batch(device, dtype, gen):
    points = rand(300, gen, dtype, device)
    batch = ragged_batch([100, 0, 120, 80], device)
    result = torchvor.radius(points, 0.2, batch=batch)
    check_against_brute_force(result, points, points, 0.2, True, batch, batch)
    queries = rand(90, gen, dtype, device)
    query_batch = ragged_batch([30, 20, 0, 40], device)
    result = torchvor.radius(points, 0.2, queries, batch=batch, query_batch=query_batch)
    check_against_brute_force(result, points, queries, 0.2, False, batch, query_batch)


def test_loop_and_duplicates(device, dtype, gen):
    base = rand(50, gen, dtype, device)
    points = torch.cat([base, base[:10]])  # 10 exact copies
    without = torchvor.radius_graph(points, 0.0)
    # r = 0: only the copies pair (both directions), never a point with itself
    assert without.shape[1] == 20 and bool((without[0] != without[1]).all())
    with_loops = torchvor.radius_graph(points, 0.0, loop=True)
    assert with_loops.shape[1] == 20 + 60
    graph = torchvor.radius_graph(points, 0.3, loop=True)
    check_against_brute_force(torchvor.radius(points, 0.3, exclude_self=False), points, points, 0.3, False)
    assert bool((graph[0] == graph[1]).sum() == 60)


def test_radius_graph_is_symmetric(device, dtype, gen):
    points = rand(500, gen, dtype, device)
    edges = torchvor.radius_graph(points, 0.12).cpu()
    forward = set(map(tuple, edges.t().tolist()))
    assert forward == {(j, i) for i, j in forward}


@pytest.mark.parametrize("cap", [1, 4, 1000])
def test_max_num_neighbors_keeps_the_nearest(device, dtype, gen, cap):
    points = rand(500, gen, dtype, device)
    full = torchvor.radius(points, 0.15)
    capped = torchvor.radius(points, 0.15, max_num_neighbors=cap)
    check_sorted(capped, 500)
    # the first `cap` of each query's sorted list
    dst = full.edge_index[1].cpu()
    start = torch.searchsorted(dst, dst, right=False)
    rank = torch.arange(len(dst)) - start
    keep = rank < cap
    assert torch.equal(capped.edge_index.cpu(), full.edge_index.cpu()[:, keep])
    assert torch.equal(capped.dist2.cpu(), full.dist2.cpu()[keep])
    graph = torchvor.radius_graph(points, 0.15, max_num_neighbors=cap)
    assert torch.equal(graph, capped.edge_index)


def test_deterministic(device, dtype, gen):
    points = rand(2000, gen, dtype, device)
    a, b = torchvor.radius(points, 0.05), torchvor.radius(points, 0.05)
    assert torch.equal(a.edge_index, b.edge_index) and torch.equal(a.dist2, b.dist2)


def test_empty_inputs(device, dtype, gen):
    points = rand(20, gen, dtype, device)
    empty = points[:0]
    for result in (torchvor.radius(empty, 0.5), torchvor.radius(points, 0.5, empty),
                   torchvor.radius(empty, 0.5, points)):
        assert result.edge_index.shape == (2, 0) and result.edge_index.dtype == torch.int64
        assert result.dist2.shape == (0,) and result.dist2.dtype == dtype
    assert torchvor.radius_graph(points[:1], 1.0).shape == (2, 0)


def test_bad_inputs(device):
    points = torch.rand(10, 3, device=device)
    with pytest.raises(ValueError, match="r must be finite and non-negative"):
        torchvor.radius(points, -0.1)
    with pytest.raises(ValueError, match="r must be finite"):
        torchvor.radius(points, float("nan"))
    with pytest.raises(TypeError, match="r must be a number"):
        torchvor.radius(points, "0.1")
    with pytest.raises(ValueError, match="max_num_neighbors must be at least 1"):
        torchvor.radius(points, 0.1, max_num_neighbors=0)
    with pytest.raises(TypeError, match="max_num_neighbors must be an int"):
        torchvor.radius(points, 0.1, max_num_neighbors=2.5)
    with pytest.raises(ValueError, match="contains NaN or Inf"):
        torchvor.radius(torch.full((4, 3), float("nan"), device=device), 0.1)
    with pytest.raises(ValueError, match="shape"):
        torchvor.radius(torch.rand(10, 2, device=device), 0.1)
    with pytest.raises(TypeError):
        torchvor.radius(torch.rand(10, 3, device=device, dtype=torch.float16), 0.1)
    with pytest.raises(ValueError, match="exclude_self=True needs queries=None"):
        torchvor.radius(points, 0.1, points, exclude_self=True)
    with pytest.raises(ValueError, match="query_batch is required"):
        torchvor.radius(points, 0.1, points, batch=torch.zeros(10, dtype=torch.int64, device=device))


def test_dist2_gradients(device, gen):
    while True:  # a draw whose radius lists finite differences cannot change
        points, queries = rand(40, gen, torch.float64, device), rand(15, gen, torch.float64, device)
        if distances_separated(points, queries, radius=0.4):
            break
    points, queries = points.requires_grad_(), queries.requires_grad_()

    def f(p, q):
        return torchvor.radius(p, 0.4, q).dist2

    assert torch.autograd.gradcheck(f, (points, queries))
    assert torch.autograd.gradcheck(lambda p: torchvor.radius(p, 0.4).dist2, (points,))
    result = torchvor.radius(points, 0.4, queries)
    assert not result.edge_index.requires_grad and result.dist2.requires_grad


def test_opcheck_radius(device, dtype, gen):
    points = rand(40, gen, dtype, device)
    batch = ragged_batch([25, 0, 15], device)
    for args in [(points, rand(15, gen, dtype, device), 0.3, None, None, False),
                 (points, points, 0.25, None, None, True),
                 (points, points, 0.3, batch, batch, True)]:
        torch.library.opcheck(torch.ops.torchvor.radius.default, args)


def test_compile_radius_graph(device, dtype, gen):
    """radius_graph and radius (no cap) under torch.compile(fullgraph=True):
    the edge count is a data-dependent size."""
    torch._dynamo.reset()

    def f(p):
        result = torchvor.radius(p, 0.1)
        return result.edge_index, result.dist2.sqrt()

    compiled = torch.compile(f, fullgraph=True)
    points = rand(300, gen, dtype, device)
    got, ref = compiled(points), f(points)
    assert torch.equal(got[0], ref[0])
    torch.testing.assert_close(got[1], ref[1])
    graph = torch.compile(lambda p: torchvor.radius_graph(p, 0.1), fullgraph=True)
    assert torch.equal(graph(points), ref[0])


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cpu_cuda_parity(dtype, gen):
    points = rand(5000, gen, dtype, "cpu")
    cpu = torchvor.radius(points, 0.04)
    cuda = torchvor.radius(points.cuda(), 0.04)
    assert torch.equal(cpu.edge_index, cuda.edge_index.cpu())
    assert torch.equal(cpu.dist2, cuda.dist2.cpu())
