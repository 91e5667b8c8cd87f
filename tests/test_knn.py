"""torchvor.knn / knn_graph against a float64 brute force (tests/oracles.py).

Every input is drawn fresh per test (``gen`` fixture, seed printed on failure)
on the CPU and moved to ``device``, so CPU and CUDA see the same values.
"""
from __future__ import annotations

import platform
import subprocess

import numpy as np
import pytest
import torch

import torchvor
from torchvor import samples

from oracles import brute_force_knn, check_knn_result, distances_separated, exact_knn_with_ties

has_cuda = torch.cuda.is_available()


def rand(n, gen, dtype, device, lo=0.0, hi=1.0):
    return (torch.rand(n, 3, generator=gen, dtype=torch.float64) * (hi - lo) + lo).to(dtype).to(device)


def ragged_batch(sizes, device):
    return torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes)).to(device)


def knn_and_check(points, k, queries=None, **kwargs):
    result = torchvor.knn(points, k, queries, **kwargs)
    assert isinstance(result, torchvorKNN)
    check_knn_result(result.dist2, result.idx, points, k, queries,
                     batch=kwargs.get("batch"), query_batch=kwargs.get("query_batch"),
                     exclude_self=kwargs.get("exclude_self"))
    return result


torchvorKNN = torchvor.KNN


def assert_exact(result, ref):
    """Index for index and distance for distance (inputs with exact distances)."""
    ref_d, ref_i = ref
    got_i = result.idx.cpu().numpy()
    got_d = result.dist2.cpu().double().numpy()
    mismatch = np.nonzero((got_i != ref_i).any(1))[0]
    assert len(mismatch) == 0, (
        f"{len(mismatch)} rows differ from the exact oracle; first: query {mismatch[0]}\n"
        f"  got    {got_i[mismatch[0]]}\n  oracle {ref_i[mismatch[0]]}\n"
        f"  got d2 {got_d[mismatch[0]]}\n  ref d2 {ref_d[mismatch[0]]}")
    np.testing.assert_array_equal(got_d, ref_d)


@pytest.fixture(params=["thread", "cooperative", "streamed"])
def knn_impl(request, monkeypatch, device):
    """Which implementation searches (TORCHVOR_KNN): one thread per query (the
    CPU's default, and CUDA's for large passes) or a group of lanes per query
    (a warp on CUDA, its default for small passes; one lane on the CPU). The
    tests that take this fixture run both on every device; "streamed" is the
    CPU's thread search writing every result by non-temporal stores (as it
    does results of 32 MiB and more)."""
    if request.param == "streamed":
        if device.type != "cpu":
            pytest.skip("non-temporal row stores are the CPU's")
        monkeypatch.setenv("TORCHVOR_STREAM_ROWS_BYTES", "0")
        monkeypatch.setenv("TORCHVOR_KNN", "thread")
    else:
        monkeypatch.setenv("TORCHVOR_KNN", request.param)
    return request.param


# ----------------------------------------------------------------- correctness


@pytest.mark.parametrize("k", [1, 8, 33])
def test_uniform(device, dtype, gen, k, knn_impl):
    points = rand(1500, gen, dtype, device)
    knn_and_check(points, k)


@pytest.mark.parametrize("k", [1, 16])
def test_clustered(device, dtype, seed, k, knn_impl):
    points = samples.clustered(1500, clusters=7, spread=0.01, seed=seed, dtype=dtype).to(device)
    knn_and_check(points, k)
    queries = samples.clustered(700, clusters=5, spread=0.05, seed=seed + 1, dtype=dtype).to(device)
    knn_and_check(points, k, queries)


@pytest.mark.parametrize("k", [1, 5, 40])
def test_exact_ties_integer_grid(device, dtype, gen, k, knn_impl):
    """Small integer coordinates: every distance is exact in float32 and float64,
    ties are everywhere, and the (distance, lower index) order is unique."""
    points = torch.randint(0, 4, (400, 3), generator=gen).to(dtype).to(device)
    assert_exact(torchvor.knn(points, k), exact_knn_with_ties(points, k))
    assert_exact(torchvor.knn(points, k, exclude_self=False),
                 exact_knn_with_ties(points, k, exclude_self=False))
    queries = torch.randint(-2, 6, (300, 3), generator=gen).to(dtype).to(device)
    assert_exact(torchvor.knn(points, k, queries), exact_knn_with_ties(points, k, queries))


def test_many_exact_duplicates(device, dtype, gen, knn_impl):
    """30 copies each of 20 random points, shuffled: ties broken by the lower
    index, and a point's copies (not itself) come first at distance 0."""
    base = rand(20, gen, dtype, device)
    perm = torch.randperm(600, generator=gen).to(device)
    points = base.repeat(30, 1)[perm]
    k = 40
    result = torchvor.knn(points, k)
    check_knn_result(result.dist2, result.idx, points, k)
    # the 29 other copies, by increasing index, at distance exactly 0
    label = (torch.arange(600).remainder(20).to(device))[perm]
    for i in range(0, 600, 37):
        copies = torch.nonzero(label == label[i]).flatten()
        copies = copies[copies != i]
        assert torch.equal(result.idx[i, :29], copies), (i, result.idx[i, :29], copies)
        assert torch.all(result.dist2[i, :29] == 0)
        assert torch.all(result.dist2[i, 29:] > 0)
    # exclude_self=False: itself among its copies, still by index
    result = torchvor.knn(points, k, exclude_self=False)
    check_knn_result(result.dist2, result.idx, points, k, exclude_self=False)
    for i in range(0, 600, 41):
        copies = torch.nonzero(label == label[i]).flatten()
        assert torch.equal(result.idx[i, :30], copies)


def test_duplicates_exact_oracle(device, dtype, gen, knn_impl):
    """Random points each repeated a random number of times: compared index for
    index with the brute force (ties between exact copies have one answer; other
    distances are distinct with probability 1 but compared tie-aware anyway)."""
    base = rand(150, gen, dtype, device)
    reps = torch.randint(1, 6, (150,), generator=gen)
    points = base.repeat_interleave(reps.to(device), 0)
    points = points[torch.randperm(len(points), generator=gen).to(device)]
    for k in (3, 12):
        result = knn_and_check(points, k)
        ref_d, ref_i = brute_force_knn(points, k)
        # rows are exact on the leading zero-distance block
        zero = ref_d == 0
        got = result.idx.cpu().numpy()
        np.testing.assert_array_equal(np.where(zero, got, -2), np.where(zero, ref_i, -2))


@pytest.mark.parametrize("n,k", [(1, 1), (1, 4), (3, 5), (6, 6), (7, 6)])
def test_fewer_points_than_k(device, dtype, gen, n, k, knn_impl):
    points = rand(n, gen, dtype, device)
    result = knn_and_check(points, k)
    assert (result.idx >= 0).sum(1).tolist() == [min(k, n - 1)] * n
    assert torch.isinf(result.dist2[result.idx < 0]).all()
    queries = rand(4, gen, dtype, device, -1, 2)
    result = knn_and_check(points, k, queries)
    assert (result.idx >= 0).sum(1).tolist() == [min(k, n)] * 4


def test_k1_is_nearest(device, dtype, gen):
    points = rand(2000, gen, dtype, device)
    queries = rand(1000, gen, dtype, device, -0.2, 1.2)
    result = knn_and_check(points, 1, queries)
    assert result.idx.shape == (1000, 1)


@pytest.mark.parametrize("k", [16, 17, 110, 111, 221, 222, 443, 444, 455, 909, 1100])
def test_k_across_scratch_layouts(device, dtype, gen, k, knn_impl):
    """k on both sides of every change of the GPU launch: the heap (8 bytes a slot
    in float32, 16 in float64) lives in shared memory with 128, 64 or 32 threads a
    block, and in global memory beyond 227 KB a block (k > 908 in float32, k > 454 in
    float64). On the CPU these are just more values of k."""
    points = rand(1200, gen, dtype, device)
    knn_and_check(points, k, rand(100, gen, dtype, device, -0.2, 1.2))
    grid = torch.randint(0, 12, (1200, 3), generator=gen).to(dtype).to(device)  # exact ties
    assert_exact(torchvor.knn(grid, k), exact_knn_with_ties(grid, k))


def test_large_k(device, dtype, gen, knn_impl):
    points = rand(1000, gen, dtype, device)
    result = knn_and_check(points, 300)
    assert (result.idx >= 0).all()
    # k = n - 1: every other point, k = n: one padding column
    knn_and_check(points[:400], 399)
    result = knn_and_check(points[:400], 400)
    assert (result.idx[:, -1] == -1).all() and (result.idx[:, :-1] >= 0).all()
    # a heap too large for a warp's shared memory on CUDA (48 KB): the
    # cooperative search falls back to a thread per query there
    many = rand(6300, gen, dtype, device)
    knn_and_check(many, 6200, rand(20, gen, dtype, device))


@pytest.mark.parametrize("offset", [1e4, -3e4])
def test_large_offset(device, dtype, gen, offset, knn_impl):
    """Points near 1e4 with spread 1: float32 keeps ~1e-3 absolute resolution;
    compared with the float64 brute force of the same (rounded) inputs."""
    points = rand(2000, gen, dtype, device, offset, offset + 1)
    knn_and_check(points, 10)
    queries = rand(3000, gen, dtype, device, offset - 0.5, offset + 1.5)
    knn_and_check(points, 10, queries)


def test_far_from_zero_on_few_positions(device, gen, knn_impl):
    """float32 points near 949 spread 5e-5, below the coordinates' spacing
    (6e-5): they fall on a few positions, hundreds of copies each, in grid
    cells smaller than that spacing. Bounds computed as origin + c * h
    rounded to the spacing, and every query searched the whole grid."""
    points = (949.0 + 5e-5 * torch.randn(3000, 3, generator=gen, dtype=torch.float64)).float().to(device)
    assert len(torch.unique(points, dim=0)) < 200
    knn_and_check(points, 16)


def test_anisotropic_and_flat(device, dtype, gen, knn_impl):
    """Extents that differ by orders of magnitude; a plane; a line; one point."""
    points = rand(1500, gen, dtype, device) * torch.tensor([1.0, 1e-3, 10.0], dtype=dtype, device=device)
    knn_and_check(points, 12)
    flat = rand(1500, gen, dtype, device)
    flat[:, 2] = 0.25
    knn_and_check(flat, 12)
    knn_and_check(flat, 12, rand(300, gen, dtype, device))
    line = torch.zeros(500, 3, dtype=dtype, device=device)
    line[:, 0] = torch.rand(500, generator=gen, dtype=torch.float64).to(dtype).to(device)
    knn_and_check(line, 7)
    same = torch.full((50, 3), 0.5, dtype=dtype, device=device)
    result = knn_and_check(same, 7)
    expected = [[j for j in range(50) if j != i][:7] for i in range(50)]
    assert result.idx.cpu().tolist() == expected


def test_line_with_clusters_far_apart(device, dtype, gen, knn_impl):
    """Two clusters of 1000 points at the ends of a line 10^4 cluster widths
    long: the grid has thousands of empty cells along the line and one along
    the other axes, and a k larger than a cluster sends every search across
    the gap (shells as wide as the grid, Rings::last_step)."""
    line = torch.zeros(2000, 3, dtype=torch.float64)
    line[:, 0] = torch.rand(2000, generator=gen, dtype=torch.float64)
    line[1000:, 0] += 1e4
    points = line.to(dtype).to(device)
    knn_and_check(points, 1200)


def test_long_strip_of_cells(device, dtype, gen, knn_impl):
    """100000 integer points on a strip five points wide: ~22000 x 4 grid
    cells, where a float32 cell position along x (up to 2.2e4) is rounded to
    ~0.002 of a cell, more than the grid's margin (1e-3 of a cell). The
    search's row ranges along x (Rings::row_cell, a product by 1 / h where the
    points' cells come from a division) must still reach every point at the
    k-th distance, ties included: squared distances are exact small integers,
    so the result must equal the oracle's index for index."""
    width, n = 5, 100_000
    strip = torch.zeros(n, 3, dtype=torch.float64)
    order = torch.randperm(n, generator=gen)
    strip[:, 0] = (order // width).double()
    strip[:, 1] = (order % width).double()
    points = strip.to(dtype).to(device)
    queries = torch.zeros(300, 3, dtype=torch.float64)
    queries[:, 0] = torch.randint(0, 2 * n // width, (300,), generator=gen).double() / 2
    queries[:, 1] = torch.randint(0, 2 * width - 1, (300,), generator=gen).double() / 2
    queries = queries.to(dtype).to(device)
    k = 8
    assert_exact(torchvor.knn(points, k, queries), exact_knn_with_ties(points, k, queries))
    # The points as their own queries: each excludes itself, the oracle's first column.
    some = torch.randperm(n, generator=gen)[:300].to(device)
    result = torchvor.knn(points, k)
    ref_d, ref_i = exact_knn_with_ties(points, k + 1, points[some], exclude_self=False)
    assert (ref_i[:, 0] == some.cpu().numpy()).all()
    np.testing.assert_array_equal(result.idx[some].cpu().numpy(), ref_i[:, 1:])
    np.testing.assert_array_equal(result.dist2[some].cpu().double().numpy(), ref_d[:, 1:])


def test_separate_queries(device, dtype, gen, knn_impl):
    points = rand(1200, gen, dtype, device)
    queries = torch.cat([
        rand(500, gen, dtype, device),                       # inside
        rand(300, gen, dtype, device, -3.0, 4.0),            # around the box
        rand(50, gen, dtype, device, 100.0, 101.0),          # far away
        rand(50, gen, dtype, device, -101.0, -100.0),
        0.5 + 1e4 * torch.nn.functional.normalize(                      # 1e4 away, all directions
            torch.randn(50, 3, generator=gen, dtype=torch.float64), dim=1).to(dtype).to(device),
        points[:50],                                         # on the points: distance 0 first
    ])
    for k in (1, 9, 64):
        result = knn_and_check(points, k, queries)
        assert torch.equal(result.idx[-50:, 0], torch.arange(50, device=device))
        assert torch.all(result.dist2[-50:, 0] == 0)


def test_exclude_self_false(device, dtype, gen):
    points = rand(800, gen, dtype, device)
    result = knn_and_check(points, 6, exclude_self=False)
    assert torch.equal(result.idx[:, 0], torch.arange(800, device=device))
    assert torch.all(result.dist2[:, 0] == 0)
    excluded = torchvor.knn(points, 5)
    assert torch.equal(result.idx[:, 1:], excluded.idx)
    assert torch.equal(result.dist2[:, 1:], excluded.dist2)


def test_explicit_queries_equal_points(device, dtype, gen):
    """queries=points (explicit) is exclude_self=False."""
    points = rand(700, gen, dtype, device)
    a = torchvor.knn(points, 5, points.clone())
    b = torchvor.knn(points, 5, exclude_self=False)
    assert torch.equal(a.idx, b.idx) and torch.equal(a.dist2, b.dist2)


def test_non_contiguous_inputs(device, dtype, gen):
    points = rand(900, gen, dtype, device).t().contiguous().t()  # column-major view
    assert not points.is_contiguous()
    queries = rand(600, gen, dtype, device)[::2]
    knn_and_check(points, 7)
    knn_and_check(points, 7, queries)
    batch = ragged_batch([400, 0, 500], device)
    batch_view = torch.stack([batch, batch], 1)[:, 0]  # strided view
    qbatch = torch.arange(300, device=device) // 100
    qbatch_view = torch.stack([qbatch, qbatch], 1)[:, 0]
    assert not batch_view.is_contiguous() and not qbatch_view.is_contiguous()
    result = torchvor.knn(points, 7, batch=batch_view)
    check_knn_result(result.dist2, result.idx, points, 7, batch=batch)
    result = torchvor.knn(points, 7, queries, batch=batch_view, query_batch=qbatch_view)
    check_knn_result(result.dist2, result.idx, points, 7, queries, batch=batch, query_batch=qbatch)


@pytest.mark.parametrize("kind", ["uniform", "clustered", "integer", "batch"])
def test_cooperative_knn_matches_thread_knn(monkeypatch, device, dtype, gen, seed, kind):
    """The two implementations of the search (one thread, or a group of lanes
    per query: csrc/core/grid_search.h) offer the same candidates to the same
    keys: equal results, bit for bit; and so do rows written by non-temporal
    stores (the CPU's large results; plain stores elsewhere)."""
    batch = query_batch = None
    if kind == "uniform":
        points, queries = rand(3000, gen, dtype, device), rand(500, gen, dtype, device, -0.5, 1.5)
    elif kind == "clustered":
        points = samples.clustered(3000, clusters=6, spread=0.01, seed=seed, dtype=dtype).to(device)
        queries = samples.clustered(500, clusters=4, spread=0.05, seed=seed + 1, dtype=dtype).to(device)
    elif kind == "integer":  # exact ties everywhere
        points = torch.randint(0, 6, (800, 3), generator=gen).to(dtype).to(device)
        queries = torch.randint(-1, 7, (300, 3), generator=gen).to(dtype).to(device)
    else:
        batch = ragged_batch([700, 0, 5, 900], device)
        query_batch = ragged_batch([100, 20, 30, 150], device)
        points, queries = rand(1605, gen, dtype, device), rand(300, gen, dtype, device)
    for k in (1, 7, 40):
        for args in ((points, k), (points, k, queries)):
            kwargs = {"batch": batch} if len(args) == 2 else {"batch": batch, "query_batch": query_batch}
            results = {}
            for impl in ("thread", "cooperative", "streamed"):
                monkeypatch.setenv("TORCHVOR_KNN", "thread" if impl == "streamed" else impl)
                monkeypatch.setenv("TORCHVOR_STREAM_ROWS_BYTES", "0" if impl == "streamed" else str(1 << 40))
                results[impl] = torchvor.knn(*args, **kwargs)
            for impl in ("cooperative", "streamed"):
                assert torch.equal(results["thread"].idx, results[impl].idx), (impl, k, len(args))
                assert torch.equal(results["thread"].dist2, results[impl].dist2), (impl, k, len(args))


def test_streamed_rows_across_threads(monkeypatch, dtype, gen):
    """Rows written by non-temporal stores (the CPU's results of 32 MiB and
    more), by every thread of a pass over enough queries to split it: the
    same result as plain stores, bit for bit, indices alone too, and with
    rows padded where a batch element has fewer than k points."""
    points = rand(60_000, gen, dtype, "cpu")
    queries = rand(20_000, gen, dtype, "cpu", -0.2, 1.2)
    batch = torch.cat([torch.zeros(59_990, dtype=torch.long), torch.ones(10, dtype=torch.long)])
    query_batch = torch.cat([torch.zeros(19_000, dtype=torch.long), torch.ones(1_000, dtype=torch.long)])
    calls = [lambda: torchvor.knn(points, 24),
             lambda: torchvor.knn(points, 24, queries, batch=batch, query_batch=query_batch),
             lambda: torchvor.knn_graph(points, 12)]
    for call in calls:
        results = []
        for threshold in (str(1 << 40), "0"):
            monkeypatch.setenv("TORCHVOR_STREAM_ROWS_BYTES", threshold)
            results.append(call())
        plain, streamed = (r if isinstance(r, tuple) else (r,) for r in results)
        assert all(torch.equal(a, b) for a, b in zip(plain, streamed))
    padded = torchvor.knn(points, 24, queries, batch=batch, query_batch=query_batch)  # streamed
    assert torch.all(padded.idx[19_000:, 10:] == -1) and torch.all(torch.isinf(padded.dist2[19_000:, 10:]))
    assert torch.all(padded.idx[19_000:, :10] >= 59_990)


def test_deterministic(device, dtype, gen):
    points = samples.clustered(3000, seed=int(torch.randint(1 << 30, (1,), generator=gen)), dtype=dtype)
    points = points.to(device)
    a = torchvor.knn(points, 20)
    b = torchvor.knn(points, 20)
    assert torch.equal(a.idx, b.idx) and torch.equal(a.dist2, b.dist2)


# ----------------------------------------------------------------------- batch


def test_ragged_batch(device, dtype, gen, knn_impl):
    sizes = [1, 300, 2, 0, 450, 5, 120]  # one empty element (3) in the middle
    batch = ragged_batch(sizes, device)
    n = sum(sizes)
    # each cloud in its own region, and overlapping ones: batches must not leak
    points = rand(n, gen, dtype, device)
    for k in (1, 4, 16):
        knn_and_check(points, k, batch=batch)
        knn_and_check(points, k, batch=batch, exclude_self=False)
    result = torchvor.knn(points, 4, batch=batch)
    assert (result.idx[0] == -1).all()  # a cloud of one point has no neighbour
    assert result.idx[1 + 300].tolist() == [1 + 300 + 1, -1, -1, -1]


def test_ragged_batch_queries(device, dtype, gen, knn_impl):
    sizes = [200, 3, 0, 250, 40]
    batch = ragged_batch(sizes, device)
    points = rand(sum(sizes), gen, dtype, device)
    # queries: none in element 1 (empty query element in the middle), some in
    # element 2 (no points there: all padding), some in element 5 (beyond the
    # points' last element: all padding)
    qsizes = [100, 0, 7, 80, 30, 4]
    query_batch = ragged_batch(qsizes, device)
    queries = rand(sum(qsizes), gen, dtype, device, -0.5, 1.5)
    for k in (1, 5, 45):
        result = knn_and_check(points, k, queries, batch=batch, query_batch=query_batch)
        no_points = (query_batch == 2) | (query_batch == 5)
        assert (result.idx[no_points] == -1).all()
        assert torch.isinf(result.dist2[no_points]).all()


def test_batch_matches_separate_calls(device, dtype, gen):
    sizes = [500, 37, 260]
    batch = ragged_batch(sizes, device)
    points = rand(sum(sizes), gen, dtype, device)
    result = torchvor.knn(points, 8, batch=batch)
    start = 0
    for s in sizes:
        part = torchvor.knn(points[start:start + s], 8)
        idx = result.idx[start:start + s]
        assert torch.equal(torch.where(idx >= 0, idx - start, idx), part.idx)
        assert torch.equal(result.dist2[start:start + s], part.dist2)
        start += s


def test_batch_exact_ties(device, dtype, gen, knn_impl):
    sizes = [60, 1, 90, 0, 70]
    batch = ragged_batch(sizes, device)
    points = torch.randint(0, 3, (sum(sizes), 3), generator=gen).to(dtype).to(device)
    assert_exact(torchvor.knn(points, 10, batch=batch), exact_knn_with_ties(points, 10, batch=batch))


# ------------------------------------------------------------------- knn_graph


def graph_oracle(points, k, batch=None, loop=False):
    _, idx = brute_force_knn(points, k, batch=batch, exclude_self=not loop)
    n = points.shape[0]
    target = np.repeat(np.arange(n), k)
    source = idx.reshape(-1)
    keep = source >= 0
    return np.stack([source[keep], target[keep]])


def test_knn_graph_layout(device, dtype, gen):
    # integer coordinates: exact distances, so the edge list is unique
    points = torch.randint(0, 5, (300, 3), generator=gen).to(dtype).to(device)
    edges = torchvor.knn_graph(points, 6)
    assert edges.dtype == torch.int64 and edges.shape == (2, 300 * 6) and edges.device == points.device
    np.testing.assert_array_equal(edges.cpu().numpy(), graph_oracle(points, 6))
    assert not (edges[0] == edges[1]).any()


def test_knn_graph_random(device, dtype, gen):
    points = rand(500, gen, dtype, device)
    edges = torchvor.knn_graph(points, 5)
    assert torch.equal(edges[1], torch.arange(500, device=device).repeat_interleave(5))
    result = torchvor.knn(points, 5)
    assert torch.equal(edges[0], result.idx.reshape(-1))
    check_knn_result(result.dist2, edges[0].reshape(500, 5), points, 5)


def test_knn_graph_loop(device, dtype, gen):
    points = rand(400, gen, dtype, device)
    edges = torchvor.knn_graph(points, 4, loop=True)
    assert edges.shape == (2, 1600)
    src = edges[0].reshape(400, 4)
    assert torch.equal(src[:, 0], torch.arange(400, device=device))  # self first, at distance 0
    np.testing.assert_array_equal(edges.cpu().numpy(), graph_oracle(points, 4, loop=True))


def test_knn_graph_batch_drops_padding(device, dtype, gen):
    sizes = [3, 50, 1, 0, 20]
    batch = ragged_batch(sizes, device)
    points = torch.randint(0, 4, (sum(sizes), 3), generator=gen).to(dtype).to(device)
    k = 4
    edges = torchvor.knn_graph(points, k, batch=batch)
    expected = graph_oracle(points, k, batch=batch)
    np.testing.assert_array_equal(edges.cpu().numpy(), expected)
    assert edges.shape[1] == 3 * 2 + 50 * 4 + 0 + 20 * 4
    b = batch.cpu()
    assert torch.equal(b[edges[0].cpu()], b[edges[1].cpu()])


# ----------------------------------------------------------- CPU / CUDA parity


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
@pytest.mark.parametrize("kind", ["uniform", "clustered", "offset", "integer", "batch"])
def test_cpu_cuda_parity(dtype, gen, kind):
    batch = None
    if kind == "uniform":
        points = rand(5000, gen, dtype, "cpu")
    elif kind == "clustered":
        points = samples.clustered(5000, seed=int(torch.randint(1 << 30, (1,), generator=gen)), dtype=dtype)
    elif kind == "offset":
        points = rand(5000, gen, dtype, "cpu", 1e4, 1e4 + 1)
    elif kind == "integer":
        points = torch.randint(0, 6, (3000, 3), generator=gen).to(dtype)
    else:
        sizes = [1000, 3, 0, 2000]
        batch = ragged_batch(sizes, "cpu")
        points = rand(sum(sizes), gen, dtype, "cpu")
    queries = points[:2000] + 0.01 * torch.randn(2000, 3, generator=gen, dtype=torch.float64).to(dtype)
    for k in (1, 16, 100):
        cpu = torchvor.knn(points, k, batch=batch)
        gpu = torchvor.knn(points.cuda(), k, batch=None if batch is None else batch.cuda())
        assert torch.equal(cpu.idx, gpu.idx.cpu())
        assert torch.equal(cpu.dist2, gpu.dist2.cpu())  # bitwise (inf padding compares equal)
        if batch is None:
            cpu = torchvor.knn(points, k, queries)
            gpu = torchvor.knn(points.cuda(), k, queries.cuda())
            assert torch.equal(cpu.idx, gpu.idx.cpu())
            assert torch.equal(cpu.dist2, gpu.dist2.cpu())


# ------------------------------------------------------------------ bad input


def test_bad_values(device, dtype):
    points = torch.rand(20, 3, dtype=dtype, device=device)
    for bad in (float("nan"), float("inf"), float("-inf")):
        p = points.clone()
        p[7, 1] = bad
        with pytest.raises(ValueError, match="points"):
            torchvor.knn(p, 3)
        with pytest.raises(ValueError, match="queries"):
            torchvor.knn(points, 3, p)


def test_bad_shapes(device, dtype):
    points = torch.rand(20, 3, dtype=dtype, device=device)
    for shape in [(20, 2), (20, 4), (20,), (20, 3, 1), (60,), ()]:
        bad = torch.rand(shape, dtype=dtype, device=device)
        with pytest.raises(ValueError, match="points"):
            torchvor.knn(bad, 3)
        with pytest.raises(ValueError, match="queries"):
            torchvor.knn(points, 3, bad)


def test_bad_dtypes(device):
    points = torch.rand(20, 3, device=device)
    for dt in (torch.int64, torch.int32, torch.float16, torch.bfloat16, torch.bool, torch.complex64):
        with pytest.raises(TypeError, match="points"):
            torchvor.knn(points.to(dt), 3)
        with pytest.raises(TypeError, match="queries"):
            torchvor.knn(points, 3, points.to(dt))
    with pytest.raises(TypeError, match="queries"):
        torchvor.knn(points, 3, points.double())
    with pytest.raises(TypeError, match="queries"):
        torchvor.knn(points.double(), 3, points)
    with pytest.raises(TypeError, match="points"):
        torchvor.knn(points.tolist(), 3)
    with pytest.raises(TypeError, match="queries"):
        torchvor.knn(points, 3, points.cpu().numpy())
    with pytest.raises(TypeError, match="k"):
        torchvor.knn(points, 3.0)
    with pytest.raises(TypeError, match="k"):
        torchvor.knn(points, True)


@pytest.mark.parametrize("k", [0, -1, -100])
def test_bad_k(device, k):
    points = torch.rand(20, 3, device=device)
    with pytest.raises(ValueError, match="k"):
        torchvor.knn(points, k)
    with pytest.raises(ValueError, match="k"):
        torchvor.knn(points, k, points)


def test_bad_batch(device):
    points = torch.rand(20, 3, device=device)
    good = torch.tensor([0] * 10 + [1] * 10, device=device)
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points, 3, batch=good.flip(0))  # unsorted
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points, 3, batch=good - 1)  # negative
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points, 3, batch=good[:-1])  # wrong length
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points, 3, batch=good.reshape(2, 10))  # wrong shape
    with pytest.raises(TypeError, match="batch"):
        torchvor.knn(points, 3, batch=good.int())  # wrong dtype
    with pytest.raises(TypeError, match="batch"):
        torchvor.knn(points, 3, batch=good.double())
    queries = torch.rand(6, 3, device=device)
    qb = torch.tensor([0, 0, 1, 1, 1, 1], device=device)
    with pytest.raises(ValueError, match="query_batch"):
        torchvor.knn(points, 3, queries, batch=good)  # batch without query_batch
    with pytest.raises(ValueError, match="query_batch"):
        torchvor.knn(points, 3, queries, batch=good, query_batch=qb.flip(0))
    with pytest.raises(ValueError, match="query_batch"):
        torchvor.knn(points, 3, queries, batch=good, query_batch=qb[:5])
    with pytest.raises(ValueError, match="query_batch"):
        torchvor.knn(points, 3, queries, batch=good, query_batch=qb - 1)
    with pytest.raises(ValueError):
        torchvor.knn(points, 3, queries, query_batch=qb)  # query_batch without batch


def test_exclude_self_with_queries(device):
    points = torch.rand(20, 3, device=device)
    with pytest.raises(ValueError, match="exclude_self"):
        torchvor.knn(points, 3, points, exclude_self=True)
    torchvor.knn(points, 3, points, exclude_self=False)  # allowed


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_device_mismatch():
    points = torch.rand(20, 3)
    with pytest.raises(ValueError, match="queries"):
        torchvor.knn(points, 3, points.cuda())
    with pytest.raises(ValueError, match="queries"):
        torchvor.knn(points.cuda(), 3, points)
    batch = torch.zeros(20, dtype=torch.long)
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points.cuda(), 3, batch=batch)
    with pytest.raises(ValueError, match="batch"):
        torchvor.knn(points, 3, batch=batch.cuda())
    with pytest.raises(ValueError, match="query_batch"):
        torchvor.knn(points, 3, points, batch=batch, query_batch=batch.cuda())


def test_empty_inputs(device, dtype):
    points = torch.rand(30, 3, dtype=dtype, device=device)
    empty = torch.empty(0, 3, dtype=dtype, device=device)
    # no queries: empty (0, k) results
    result = torchvor.knn(points, 4, empty)
    assert result.dist2.shape == (0, 4) and result.idx.shape == (0, 4)
    assert result.dist2.dtype == dtype and result.idx.dtype == torch.int64
    result = torchvor.knn(empty, 4)
    assert result.dist2.shape == (0, 4) and result.idx.shape == (0, 4)
    # no points: every query padded
    result = torchvor.knn(empty, 4, points)
    assert (result.idx == -1).all() and torch.isposinf(result.dist2).all()
    assert result.idx.shape == (30, 4)
    # empty with batch vectors
    eb = torch.empty(0, dtype=torch.long, device=device)
    result = torchvor.knn(empty, 2, batch=eb)
    assert result.idx.shape == (0, 2)
    result = torchvor.knn(points, 2, empty, batch=torch.zeros(30, dtype=torch.long, device=device),
                          query_batch=eb)
    assert result.idx.shape == (0, 2)


# ------------------------------------------------------------------- gradients


def test_dist2_gradients(device, gen):
    """dist2 = |q - p|^2 is differentiable in the points and the queries
    (2 (q - p) and its negative; gradcheck in float64, second order too),
    through self queries, padding (-1: no gradient) and batches."""
    while True:  # a draw whose neighbour lists finite differences cannot reorder
        points, queries = rand(40, gen, torch.float64, device), rand(9, gen, torch.float64, device)
        if distances_separated(points, queries):
            break
    points, queries = points.requires_grad_(), queries.requires_grad_()
    assert torch.autograd.gradcheck(lambda p, q: torchvor.knn(p, 5, q).dist2, (points, queries))
    assert torch.autograd.gradgradcheck(lambda p, q: torchvor.knn(p, 5, q).dist2, (points, queries))
    assert torch.autograd.gradcheck(lambda p: torchvor.knn(p, 6).dist2, (points,))
    few = points[:3].detach().clone().requires_grad_()
    padded = torchvor.knn(few, 5, queries)
    assert (padded.idx == -1).any()
    padded.dist2.masked_fill(padded.idx < 0, 0.0).sum().backward()
    assert torch.isfinite(few.grad).all() and torch.isfinite(queries.grad).all()
    batch = ragged_batch([25, 0, 15], device)
    assert torch.autograd.gradcheck(lambda p: torchvor.knn(p, 4, batch=batch).dist2, (points,))


def test_dist2_gradient_formula(device, dtype, gen):
    """The gradient of sum(dist2) equals sum over the pairs of 2 (q - p) for
    the query and -2 (q - p) for the neighbour."""
    points = rand(300, gen, dtype, device).requires_grad_()
    queries = rand(50, gen, dtype, device).requires_grad_()
    result = torchvor.knn(points, 7, queries)
    result.dist2.sum().backward()
    diff = (queries.detach().unsqueeze(1) - points.detach()[result.idx]).double()
    expected_q = 2 * diff.sum(1)
    expected_p = torch.zeros(300, 3, dtype=torch.float64, device=device).index_add(
        0, result.idx.reshape(-1), -2 * diff.reshape(-1, 3))
    tol = 1e-5 if dtype == torch.float32 else 1e-12
    torch.testing.assert_close(queries.grad.double(), expected_q, rtol=tol, atol=tol)
    torch.testing.assert_close(points.grad.double(), expected_p, rtol=tol, atol=tol)
    assert not result.idx.requires_grad


# ------------------------------------------------------- opcheck / torch.compile


def knn_op_args(dtype, device, gen, batched):
    points = rand(40, gen, dtype, device)
    if not batched:
        return [
            (points, rand(15, gen, dtype, device), 5, None, None, False),
            (points, points, 4, None, None, True),
            (points[:3], rand(6, gen, dtype, device), 5, None, None, False),  # padding
        ]
    batch = ragged_batch([25, 0, 15], device)
    qbatch = ragged_batch([4, 3, 5], device)
    return [
        (points, points, 6, batch, batch, True),
        (points, rand(12, gen, dtype, device), 3, batch, qbatch, False),
    ]


@pytest.mark.parametrize("batched", [False, True])
def test_opcheck_knn(device, dtype, gen, batched):
    for args in knn_op_args(dtype, device, gen, batched):
        torch.library.opcheck(torch.ops.torchvor.knn.default, args)


def test_compile_knn(device, dtype, gen):
    torch._dynamo.reset()

    def f(p, q):
        r = torchvor.knn(p, 7, q)
        return r.dist2, r.idx, r.dist2.sqrt() + 1  # the op inside a fused graph

    def g(p):
        r = torchvor.knn(p, 5)
        return r.dist2, r.idx

    compiled_f = torch.compile(f, fullgraph=True)
    compiled_g = torch.compile(g, fullgraph=True)
    for n in (200, 333):  # a second shape: recompiles or dynamic shapes
        points = rand(n, gen, dtype, device)
        queries = rand(50, gen, dtype, device)
        d, i, s = compiled_f(points, queries)
        d_ref, i_ref, s_ref = f(points, queries)
        assert torch.equal(i, i_ref) and torch.equal(d, d_ref)
        torch.testing.assert_close(s, s_ref)
        d, i = compiled_g(points)
        d_ref, i_ref = g(points)
        assert torch.equal(i, i_ref) and torch.equal(d, d_ref)


def test_compile_knn_batch(device, dtype, gen):
    torch._dynamo.reset()

    def f(p, b):
        return torchvor.knn(p, 4, batch=b)

    compiled = torch.compile(f, fullgraph=True)
    points = rand(120, gen, dtype, device)
    batch = ragged_batch([50, 70], device)
    got, ref = compiled(points, batch), f(points, batch)
    assert torch.equal(got.idx, ref.idx) and torch.equal(got.dist2, ref.dist2)


def test_compile_knn_graph(device, dtype, gen):
    """knn_graph under torch.compile(fullgraph=True) equals eager (the -1
    filtering is a custom op with a data-dependent output size)."""
    torch._dynamo.reset()

    def f(p):
        return torchvor.knn_graph(p, 6)

    compiled = torch.compile(f, fullgraph=True)
    points = rand(300, gen, dtype, device)
    assert torch.equal(compiled(points), f(points))


def test_compile_knn_graph_padding(device, dtype, gen):
    """knn_graph with a cloud smaller than k + 1: eager drops the missing
    neighbours (its docstring: "missing neighbours are dropped"); the compiled
    graph must not hand back edges with source -1."""
    torch._dynamo.reset()

    def f(p, b):
        return torchvor.knn_graph(p, 4, batch=b)

    compiled = torch.compile(f, fullgraph=True)
    points = rand(10, gen, dtype, device)
    batch = ragged_batch([3, 7], device)
    eager = f(points, batch)
    assert (eager >= 0).all() and eager.shape == (2, 3 * 2 + 7 * 4)
    got = compiled(points, batch)
    assert (got[0] >= 0).all(), f"compiled knn_graph returned padding edges: {got}"
    assert torch.equal(got, eager)


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="the rank counts are x86 code")
def test_rank_counts_match_a_sort(cpp_program, seed):
    """The CPU kNN's last step ranks its k best keys by counting (AVX2, or
    AVX-512 where the CPU has it): both forms, the pair ranks and the float64
    ranking by distance agree with std::sort for every n up to 128, on random,
    sorted, reversed and consecutive keys and on tied distances
    (tests/key_ranks.cpp; AVX-512 unchecked on a CPU without it)."""
    program = cpp_program("key_ranks")
    run = subprocess.run([str(program), str(seed)], capture_output=True, text=True, timeout=300)
    if run.returncode == 77:
        pytest.skip("no AVX2 on this CPU")
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]


@pytest.mark.skipif(platform.machine() not in ("x86_64", "AMD64"), reason="the packed candidate loop is x86 code")
def test_packed_candidates_match_the_scalar_loop(cpp_program, seed):
    """The CPU kNN's candidate loop a pack of points at a time (AVX2) leaves
    the heap exactly as the scalar loop does, in float and float64, for every
    pack tail, with and without an index array and an excluded point, on
    random points, lattices and repeated points (tests/offer_packs.cpp)."""
    program = cpp_program("offer_packs")
    run = subprocess.run([str(program), str(seed)], capture_output=True, text=True, timeout=300)
    if run.returncode == 77:
        pytest.skip("no AVX2 on this CPU")
    assert run.returncode == 0, run.stdout[-4000:] + run.stderr[-2000:]
