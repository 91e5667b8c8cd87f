"""torchvor.voronoi_graph and voronoi_laplacian against the half-space oracle's faces,
exact lattice cells, and the faces' own identities (symmetry, closure, walls)."""
from __future__ import annotations

from types import SimpleNamespace

import numpy as np
import pytest
import torch

import torchvor
from oracles import voronoi_cell_oracle

UNIT = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
# face areas relative to the cell's surface, face centroids relative to its radius
TOL = {torch.float32: 2e-4, torch.float64: 1e-9}


def rand(n, gen, dtype, device):
    return torch.rand(n, 3, generator=gen, dtype=torch.float64).to(dtype).to(device)


def faces_of(graph, i):
    """Cell i's faces as {neighbour j (or -1 - wall): (area, centroid or None)}."""
    source, target = graph.edge_index.cpu()
    on = target == i
    faces = {int(j): (float(a), c.double().numpy())
             for j, a, c in zip(source[on], graph.area.cpu()[on], graph.centroid.cpu()[on])}
    for w in range(6):
        if graph.wall_area[i, w] > 0:
            faces[-1 - w] = (float(graph.wall_area[i, w]), None)
    return faces


def check_against_oracle(graph, points, box, cells, tol):
    pts = points.double().cpu().numpy()
    for i in cells:
        oracle = voronoi_cell_oracle(pts, int(i), box)
        got = faces_of(graph, int(i))
        for key in set(got) | set(oracle.faces):
            a_got = got.get(key, (0.0, None))[0]
            a_exact = oracle.faces.get(key, (0.0, None))[0]
            assert abs(a_got - a_exact) <= tol * oracle.area, (i, key, a_got, a_exact)
            if key >= 0 and key in got and key in oracle.faces:
                off = np.abs(got[key][1] - oracle.faces[key][1]).max()
                # a tiny face's centroid is only as good as its area
                assert off <= tol * oracle.radius * max(1.0, oracle.area / (1e4 * a_exact)), (i, key, off)


def check_structure(graph, points, batch=None):
    n = points.shape[0]
    source, target = graph.edge_index
    assert graph.edge_index.dtype == torch.int64 and graph.edge_index.shape[0] == 2
    assert graph.area.dtype == points.dtype and graph.centroid.shape == (source.numel(), 3)
    assert graph.wall_area.shape == (n, 6)
    key = target * n + source
    assert bool((key[1:] > key[:-1]).all()), "sorted by cell, then neighbour, each face once"
    assert bool((source != target).all())
    assert bool((graph.area > 0).all())
    reverse = source * n + target
    at = torch.searchsorted(key, reverse).clamp_max(max(key.numel() - 1, 0))
    assert torch.equal(key[at], reverse), "every face both ways"
    assert torch.equal(graph.area[at], graph.area) and torch.equal(graph.centroid[at], graph.centroid)
    if batch is not None:
        assert torch.equal(batch[source], batch[target]), "clouds never connect"


def check_closure(graph, points, dtype):
    """Each cell's faces close: sum over faces of area times outward unit normal is zero."""
    n = points.shape[0]
    p = points.double()
    source, target = graph.edge_index
    normal = p[source] - p[target]
    normal = normal / normal.norm(dim=1, keepdim=True)
    total = torch.zeros(n, 3, dtype=torch.float64, device=p.device).index_add(
        0, target, graph.area.double()[:, None] * normal)
    walls = graph.wall_area.double()
    total[:, 0] += walls[:, 1] - walls[:, 0]
    total[:, 1] += walls[:, 3] - walls[:, 2]
    total[:, 2] += walls[:, 5] - walls[:, 4]
    ok = graph.cells.status == torchvor.CellStatus.SUCCESS
    surface = torch.zeros(n, dtype=torch.float64, device=p.device).index_add(0, target, graph.area.double())
    surface += walls.sum(1)
    worst = (total.norm(dim=1)[ok] / surface[ok]).max().item()
    assert worst <= (1e-4 if dtype == torch.float32 else 1e-10), worst


def test_faces_match_the_oracle(device, dtype, gen, cells_impl):
    points = rand(400, gen, dtype, device)
    graph = torchvor.voronoi_graph(points, UNIT, on_failure="raise")
    check_structure(graph, points)
    check_closure(graph, points, dtype)
    check_against_oracle(graph, points, UNIT, range(0, 400, 9), TOL[dtype])
    cells = torchvor.voronoi(points, UNIT)
    assert torch.equal(graph.cells.status, cells.status)
    torch.testing.assert_close(graph.cells.volume, cells.volume, rtol=TOL[dtype], atol=0)
    # the walls tile the box's surface
    assert abs(graph.wall_area.double().sum().item() - 6.0) <= 6 * TOL[dtype]


def test_clusters_and_offset_box(device, dtype, gen):
    """Tight clusters far from the origin: needle cells, float32 cells
    recomputed in float64; faces still match."""
    centres = torch.rand(5, 3, generator=gen, dtype=torch.float64)
    points = (centres.repeat_interleave(60, 0) + 0.01 * torch.randn(300, 3, generator=gen, dtype=torch.float64))
    points = points.clamp(0, 1) * 10 + 100
    box = ([100.0] * 3, [110.0] * 3)
    points = points.to(dtype).to(device)
    graph = torchvor.voronoi_graph(points, box, on_failure="raise")
    check_structure(graph, points)
    check_closure(graph, points, dtype)
    check_against_oracle(graph, points, box, range(0, 300, 23), 10 * TOL[dtype])


def test_cubic_lattice_is_exact(device, dtype):
    """Cells of a cubic lattice are cubes: 6 faces of area h^2 (the diagonal
    neighbours' bisectors touch them only at edges and corners: no edges)."""
    m = 6
    h = 1.0 / m
    axis = (torch.arange(m, dtype=torch.float64) + 0.5) * h
    points = torch.cartesian_prod(axis, axis, axis).to(dtype).to(device)
    graph = torchvor.voronoi_graph(points, UNIT, on_failure="raise")
    check_structure(graph, points)
    source, target = graph.edge_index
    step = (points[source] - points[target]).double().abs()
    assert torch.allclose(step.sum(1), torch.tensor(h, dtype=torch.float64, device=device), rtol=1e-6)
    assert torch.allclose(step.max(1).values, torch.tensor(h, dtype=torch.float64, device=device), rtol=1e-6)
    torch.testing.assert_close(graph.area.double().cpu(), torch.full((source.numel(),), h * h, dtype=torch.float64),
                               rtol=TOL[dtype], atol=0)
    assert source.numel() == 6 * m ** 3 - 6 * m * m  # every lattice neighbour pair, both ways
    # every cell on a wall has that wall's full square
    walls = graph.wall_area.double().cpu()
    assert torch.allclose(walls[walls > 0], torch.tensor(h * h, dtype=torch.float64), rtol=TOL[dtype])
    assert int((walls > 0).sum()) == 6 * m * m


def test_duplicates_have_no_edges(device, dtype, gen):
    points = rand(200, gen, dtype, device)
    points = torch.cat([points, points[:20]])  # rows 200-219 copy rows 0-19
    graph = torchvor.voronoi_graph(points, UNIT)
    check_structure(graph, points)
    copies = torch.arange(200, 220, device=device)
    assert not bool(torch.isin(graph.edge_index, copies).any())
    assert bool((graph.cells.status[200:] == torchvor.CellStatus.DUPLICATE).all())
    assert bool(torch.isin(torch.arange(20, device=device), graph.edge_index[1]).all())
    assert bool((graph.wall_area[200:] == 0).all())


def test_faces_one_cell_found_kept_both_ways(device):
    """A lattice jittered by 1e-12: its diagonal faces are rounding-sized,
    and a cell retried in double-double (a lower area floor) keeps some that
    its float64 neighbour drops. A face one cell found is kept in both
    directions with that cell's values, and every cell still closes."""
    gen = torch.Generator().manual_seed(5)
    lattice = torch.stack(torch.meshgrid(*[torch.arange(10.0) / 10 + 0.05] * 3, indexing="ij"), -1).reshape(-1, 3)
    points = (lattice.double() + 1e-12 * torch.randn(lattice.shape, generator=gen, dtype=torch.float64)).to(device)
    graph = torchvor.voronoi_graph(points, UNIT)
    check_structure(graph, points)
    check_closure(graph, points, torch.float64)
    assert int((graph.area < 1e-22).sum()) > 0  # the rounding-sized faces are there


def test_batch(device, dtype, gen):
    sizes = [150, 0, 1, 120]
    points = rand(sum(sizes), gen, dtype, device)
    batch = torch.repeat_interleave(torch.arange(len(sizes)), torch.tensor(sizes)).to(device)
    graph = torchvor.voronoi_graph(points, UNIT, batch=batch)
    check_structure(graph, points, batch)
    check_closure(graph, points, dtype)
    single = torchvor.voronoi_graph(points[150:151], UNIT)
    assert single.edge_index.shape == (2, 0)
    torch.testing.assert_close(single.wall_area.double().cpu(), torch.ones(1, 6, dtype=torch.float64),
                               rtol=TOL[dtype], atol=0)
    first = torchvor.voronoi_graph(points[:150], UNIT)
    on_first = graph.edge_index[1] < 150
    assert torch.equal(graph.edge_index[:, on_first], first.edge_index)


def test_cells_past_the_device_tiers(device, dtype, gen):
    """A point above a dense layer on a wall faces hundreds (a host tier) or
    thousands (an unbounded cell) of points: its faces still match."""
    for on_wall in (600, 5000):
        points = torch.rand(on_wall + 1, 3, generator=gen, dtype=torch.float64)
        points[:on_wall, 2] *= 1e-3
        points[on_wall] = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
        points = points.to(dtype).to(device)
        graph = torchvor.voronoi_graph(points, UNIT, on_failure="raise")
        check_structure(graph, points)
        check_closure(graph, points, dtype)
        assert int((graph.edge_index[1] == on_wall).sum()) > 200
        check_against_oracle(graph, points, UNIT, [on_wall, 0], 10 * TOL[dtype])


def test_cells_finished_on_the_grid(device, dtype, gen):
    """Points far from a dense cluster in a wide box need more than 256
    neighbours: their cells are finished by their vertices' balls on the
    grid, and their faces' neighbours are found there."""
    cluster = 0.5 + 0.01 * torch.randn(3000, 3, generator=gen, dtype=torch.float64)
    far = torch.tensor([[0.05, 0.05, 0.05], [0.95, 0.1, 0.9], [0.1, 0.9, 0.5]], dtype=torch.float64)
    points = torch.cat([cluster, far]).to(dtype).to(device)
    graph = torchvor.voronoi_graph(points, UNIT, on_failure="raise")
    assert bool((graph.cells.neighbors_needed[3000:] > 256).any())
    check_structure(graph, points)
    check_closure(graph, points, dtype)
    check_against_oracle(graph, points, UNIT, [3000, 3001, 3002], 10 * TOL[dtype])


@pytest.mark.parametrize("kind", ["white", "clusters", "wall_layer"])
def test_claimed_faces_and_counted_faces_agree(device, dtype, gen, kind, monkeypatch):
    """The one pass whose cells claim their faces' room, and the count pass
    then the fill (room 0, a room too small for the cells, or host cells,
    which do not claim) give the same graph bit for bit, moments too."""
    n = 1500
    if kind == "white":
        points = torch.rand(n, 3, generator=gen, dtype=torch.float64)
    elif kind == "clusters":  # retries in wider tiers and float64
        centres = torch.rand(6, 3, generator=gen, dtype=torch.float64)
        points = (centres[torch.randint(0, 6, (n,), generator=gen)]
                  + 0.01 * torch.randn(n, 3, generator=gen, dtype=torch.float64)).clamp(0.0, 1.0)
    else:  # a point above 600 points on a wall: a host tier's cell
        points = torch.rand(601, 3, generator=gen, dtype=torch.float64)
        points[:600, 2] *= 1e-3
        points[600] = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    points = points.to(dtype).to(device)
    box = torch.tensor([UNIT], dtype=dtype, device=device)
    graphs = []
    for room in ("20", "0", "2", "9"):
        monkeypatch.setenv("TORCHVOR_GRAPH_CLAIMED_FACES", room)
        graphs.append(torch.ops.torchvor.voronoi_graph.default(points, box, None, None, 1 << 30, True))
    for other in graphs[1:]:
        for a, b in zip(graphs[0], other):
            assert torch.equal(a.nan_to_num(), b.nan_to_num())
    edge_index, area, centroid, wall_area = graphs[0][6:10]
    check_structure(SimpleNamespace(edge_index=edge_index, area=area, centroid=centroid, wall_area=wall_area), points)
    assert graphs[0][10].shape == (edge_index.shape[1], 9)


def test_faces_with_and_without_moments_agree(device, gen):
    """The faces without moments (voronoi_graph's kernels of their own on the
    GPU) and with them: the same edges, their areas and centroids equal to
    rounding."""
    points = rand(3000, gen, torch.float64, device)
    box = torch.tensor([UNIT], dtype=torch.float64, device=device)
    without = torch.ops.torchvor.voronoi_graph.default(points, box, None, None, 1 << 30, False)
    with_moments = torch.ops.torchvor.voronoi_graph.default(points, box, None, None, 1 << 30, True)
    assert torch.equal(without[6], with_moments[6])
    for a, b in zip(without[7:10], with_moments[7:10]):
        torch.testing.assert_close(a, b, rtol=1e-12, atol=1e-15)
    assert without[10].numel() == 0 and with_moments[10].shape == (without[6].shape[1], 9)


def test_laplacian(device, dtype, gen):
    points = rand(500, gen, dtype, device)
    laplacian = torchvor.voronoi_laplacian(points, UNIT)
    assert laplacian.shape == (500, 500) and laplacian.dtype == dtype and laplacian.is_sparse
    dense = laplacian.to_dense().double()
    assert torch.equal(dense, dense.T)
    assert dense.sum(1).abs().max().item() <= 1e-4 * dense.diagonal().abs().max().item()
    graph = torchvor.voronoi_graph(points, UNIT)
    interior = (graph.wall_area == 0).all(1)
    linear = points.double() @ torch.tensor([1.0, -2.0, 0.5], dtype=torch.float64, device=device)
    applied = dense @ linear
    scale = dense.diagonal().abs()
    assert (applied[interior].abs() / scale[interior]).max().item() <= (1e-4 if dtype == torch.float32 else 1e-10)
    assert (applied[~interior].abs() / scale[~interior]).max().item() > 1e-3  # walls carry flux


def test_empty_and_bad_input(device, dtype):
    empty = torch.empty(0, 3, dtype=dtype, device=device)
    graph = torchvor.voronoi_graph(empty, UNIT)
    assert graph.edge_index.shape == (2, 0) and graph.area.shape == (0,) and graph.wall_area.shape == (0, 6)
    bad = torch.tensor([[0.5, 0.5, float("nan")]], dtype=dtype, device=device)
    with pytest.raises(ValueError, match="NaN"):
        torchvor.voronoi_graph(bad, UNIT)
    with pytest.raises(ValueError, match="on_failure"):
        torchvor.voronoi_graph(empty, UNIT, on_failure="ignore")
    with pytest.raises(ValueError, match="inside"):
        torchvor.voronoi_graph(torch.full((2, 3), 2.0, dtype=dtype, device=device), UNIT)


def test_outputs_are_not_differentiable(device, gen):
    points = rand(50, gen, torch.float64, device).requires_grad_()
    graph = torchvor.voronoi_graph(points, UNIT)
    assert not any(t.requires_grad for t in (graph.area, graph.centroid, graph.wall_area, graph.cells.volume))


def test_opcheck_voronoi_graph(device, dtype, gen):
    points = rand(60, gen, dtype, device)
    box = torch.tensor([UNIT], dtype=dtype, device=device)
    batch = torch.repeat_interleave(torch.arange(2), torch.tensor([35, 25])).to(device)
    for args in [(points, box, None, None, 1 << 30), (points, box.expand(2, 2, 3).contiguous(), batch, 12, 1 << 30)]:
        torch.library.opcheck(torch.ops.torchvor.voronoi_graph.default, args)


def test_compile_voronoi_graph(device, dtype, gen):
    """voronoi_graph under torch.compile(fullgraph=True): the edge count is a
    data-dependent size (failures are only flagged inside compiled code)."""
    torch._dynamo.reset()

    def f(p):
        graph = torchvor.voronoi_graph(p, UNIT, on_failure="flag")
        return graph.edge_index, graph.area * 2, graph.cells.volume

    compiled = torch.compile(f, fullgraph=True)
    points = rand(200, gen, dtype, device)
    got, ref = compiled(points), f(points)
    assert torch.equal(got[0], ref[0])
    torch.testing.assert_close(got[1], ref[1])
    torch.testing.assert_close(got[2], ref[2])
