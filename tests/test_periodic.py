"""Periodic boxes (torchvor/periodic.py): kNN against scipy's cKDTree(boxsize)
and a minimum-image brute force, radius neighbourhoods, Voronoi cells and
faces against the half-space oracle over the points' images, gradients."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor
from oracles import minimum_image_dist2, periodic_cell_oracle

BOX = ([0.0, 0.0, 0.0], [1.0, 1.0, 1.0])
SKEWED = ([-1.0, 0.5, 2.0], [1.0, 1.25, 3.5])  # unequal periods, away from the origin
ALL = (True, True, True)


def cloud(n, gen, box=BOX, dtype=torch.float64, device="cpu"):
    lo, hi = (torch.tensor(b, dtype=torch.float64) for b in box)
    return (lo + torch.rand(n, 3, generator=gen, dtype=torch.float64) * (hi - lo)).to(dtype).to(device)


def box_volume(box):
    return float(np.prod(np.array(box[1]) - np.array(box[0])))


# ---- arguments ---------------------------------------------------------------

def test_periodic_needs_a_box_with_positive_periods(gen):
    points = cloud(20, gen)
    with pytest.raises(ValueError, match="periodic needs a box"):
        torchvor.voronoi(points, periodic=True)
    with pytest.raises(ValueError, match="periodic needs a box"):
        torchvor.knn(points, 3, periodic=True)
    with pytest.raises(ValueError, match="flat along a periodic axis"):
        torchvor.voronoi(points, ([0, 0, 0], [1, 1, 0]), periodic=True)
    with pytest.raises(ValueError, match="periodic must be True, False or three bools"):
        torchvor.voronoi(points, BOX, periodic=(True, False))
    with pytest.raises(ValueError, match="NaN or Inf"):
        torchvor.voronoi(torch.full((3, 3), float("nan"), dtype=torch.float64), BOX, periodic=True)
    # a flat box along an axis that does not repeat is the plain error
    with pytest.raises(ValueError):
        torchvor.voronoi(points, ([0, 0, 0], [1, 1, 0]), periodic=(True, True, False))


def test_batch_checks_and_one_box_for_every_cloud(gen):
    points = cloud(60, gen)
    batch = torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([30, 30]))
    cells = torchvor.voronoi(points, BOX, batch=batch, periodic=True)
    sums = torch.zeros(2, dtype=torch.float64).index_add(0, batch, cells.volume)
    np.testing.assert_allclose(sums.numpy(), [1.0, 1.0], rtol=1e-9)
    with pytest.raises(ValueError, match="sorted"):
        torchvor.voronoi(points, BOX, batch=batch.flip(0), periodic=True)
    with pytest.raises(ValueError, match="shape"):
        torchvor.knn(points, 3, batch=batch[:10], box=BOX, periodic=True)
    with pytest.raises(TypeError, match="int64"):
        torchvor.radius(points, 0.1, batch=batch.int(), box=BOX, periodic=True)


def test_float32_in_a_box_about_zero_is_computed_in_float64(device, gen):
    """SKEWED's images of points near hi round in float32: the call runs in float64."""
    points = cloud(300, gen, SKEWED, torch.float32, device)
    single = torchvor.voronoi(points, SKEWED, periodic=True)
    double = torchvor.voronoi(points.double(), SKEWED, periodic=True)
    assert torch.equal(single.volume, double.volume.float())
    assert torch.equal(single.centroid, double.centroid.float())
    near = torchvor.knn(points, 5, box=SKEWED, periodic=True)
    assert torch.equal(near.dist2, torchvor.knn(points.double(), 5, box=SKEWED, periodic=True).dist2.float())


def test_periodic_false_is_the_plain_call(gen):
    points = cloud(50, gen)
    plain = torchvor.voronoi(points, BOX)
    same = torchvor.voronoi(points, BOX, periodic=(False, False, False))
    assert torch.equal(plain.volume, same.volume)


# ---- kNN and radius ----------------------------------------------------------

@pytest.mark.parametrize("box", [BOX, SKEWED], ids=["unit", "skewed"])
def test_knn_matches_ckdtree_boxsize(device, dtype, gen, box):
    from scipy.spatial import cKDTree

    points = cloud(500, gen, box, dtype, device)
    k = 12
    result = torchvor.knn(points, k, box=box, periodic=True)
    lo, hi = np.array(box[0]), np.array(box[1])
    data = points.double().cpu().numpy() - lo
    tree = cKDTree(data, boxsize=hi - lo)
    dist, idx = tree.query(data, k + 1)
    expected = dist[:, 1:] ** 2
    got = result.dist2.double().cpu().numpy()
    tolerance = 1e-6 if dtype == torch.float32 else 1e-12
    np.testing.assert_allclose(got, expected, rtol=tolerance, atol=tolerance)
    # indices: the oracle's distance of each returned point is the returned distance
    d2 = minimum_image_dist2(points.cpu(), points.cpu(), box, ALL)
    rows = np.arange(len(points))[:, None]
    np.testing.assert_allclose(d2[rows, result.idx.cpu().numpy()], got, rtol=tolerance, atol=tolerance)
    assert not (result.idx.cpu().numpy() == rows).any()


def test_knn_partly_periodic_with_queries_and_batches(device, gen):
    box = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 2.0, 1.0]], [[5.0, 5.0, 5.0], [6.0, 6.0, 7.0]]], dtype=torch.float64)
    periodic = (True, False, True)
    a, b = cloud(120, gen, box[0].tolist()), cloud(80, gen, box[1].tolist())
    points = torch.cat([a, b]).to(device)
    batch = torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([120, 80])).to(device)
    qa, qb = cloud(30, gen, box[0].tolist()), cloud(20, gen, box[1].tolist())
    queries = torch.cat([qa, qb]).to(device)
    query_batch = torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([30, 20])).to(device)
    result = torchvor.knn(points, 7, queries, batch=batch, query_batch=query_batch, box=box.to(device),
                          periodic=periodic)
    for e, (p_rows, q_rows) in enumerate([(slice(0, 120), slice(0, 30)), (slice(120, 200), slice(30, 50))]):
        d2 = minimum_image_dist2(queries[q_rows].cpu(), points[p_rows].cpu(), box[e].tolist(), periodic)
        expected = np.sort(d2, axis=1)[:, :7]
        np.testing.assert_allclose(result.dist2[q_rows].cpu().numpy(), expected, rtol=1e-12, atol=1e-14)
        offset = p_rows.start
        idx = result.idx[q_rows].cpu().numpy() - offset
        np.testing.assert_allclose(np.take_along_axis(d2, idx, 1), expected, rtol=1e-12, atol=1e-14)


def test_knn_of_a_cloud_smaller_than_k_counts_each_point_once(device):
    points = torch.tensor([[0.1, 0.1, 0.1], [0.9, 0.9, 0.9], [0.5, 0.5, 0.5]], dtype=torch.float64, device=device)
    result = torchvor.knn(points, 4, box=BOX, periodic=True)
    idx = result.idx.cpu()
    assert idx[:, 2:].eq(-1).all() and torch.isinf(result.dist2[:, 2:]).all()
    # 0.1 and 0.9 are 0.2 apart per axis through the faces
    assert idx[0, 0] == 1 and abs(result.dist2[0, 0].item() - 3 * 0.2 ** 2) < 1e-12
    assert set(idx[2, :2].tolist()) == {0, 1}


def test_radius_matches_minimum_image_brute_force(device, dtype, gen):
    points = cloud(300, gen, SKEWED, dtype, device)
    for r in (0.1, 0.45):  # 0.45: beyond half the y period (0.75 / 2): images of a point twice within r
        result = torchvor.radius(points, r, box=SKEWED, periodic=True)
        d2 = minimum_image_dist2(points.cpu(), points.cpu(), SKEWED, ALL)
        np.fill_diagonal(d2, np.inf)
        expected = {(j, i) for i, j in zip(*np.nonzero(d2 <= r * r))}
        idx, row = result.edge_index.cpu().numpy()
        got = set(zip(idx.tolist(), row.tolist()))
        near = {(j, i) for i, j in zip(*np.nonzero(np.abs(d2 - r * r) <= 1e-6 * r * r))}
        assert got - near == expected - near
        assert len(got) == len(idx)  # each pair once
        # sorted by query, then distance
        key = row.astype(np.float64) * 10 + result.dist2.double().cpu().numpy()
        assert (np.diff(key) >= 0).all()
    capped = torchvor.radius(points, 0.2, box=SKEWED, periodic=True, max_num_neighbors=3)
    counts = torch.bincount(capped.edge_index[1].cpu(), minlength=300)
    assert counts.max() <= 3
    graph = torchvor.radius_graph(points, 0.1, box=SKEWED, periodic=True)
    assert graph.shape[1] == torchvor.radius(points, 0.1, box=SKEWED, periodic=True).edge_index.shape[1]


def test_knn_and_radius_distances_are_differentiable(gen):
    points = cloud(40, gen).requires_grad_()
    torch.autograd.gradcheck(lambda p: torchvor.knn(p, 3, box=BOX, periodic=True).dist2, (points,))
    torch.autograd.gradcheck(lambda p: torchvor.radius(p, 0.25, box=BOX, periodic=True).dist2, (points,))


# ---- Voronoi cells -----------------------------------------------------------

def check_cells(points, box, periodic, cells, sample, tolerance):
    lo = np.array(box[0])
    for i in sample:
        oracle = periodic_cell_oracle(points.double().cpu(), int(i), box, periodic)
        scale = oracle.volume
        assert abs(cells.volume[i].item() - oracle.volume) <= tolerance * scale, (i, cells.volume[i].item(), oracle.volume)
        size = max(oracle.volume ** (1 / 3), 1e-300)
        np.testing.assert_allclose(cells.centroid[i].double().cpu().numpy(), oracle.centroid, atol=tolerance * size)
        assert abs(cells.second_moment[i].item() - oracle.second_moment) <= 10 * tolerance * oracle.second_moment
        # the farthest computed vertex, rounded up: short by the vertices' rounding at most
        short = max(tolerance, 1e-4) * max(size, oracle.radius) if cells.radius.dtype == torch.float32 else 0.0
        assert oracle.radius - short <= cells.radius[i].item() <= oracle.radius * (1 + 1e-5) + 1e-300
    del lo


@pytest.mark.parametrize("periodic", [ALL, (True, False, True), (False, False, True)], ids=["xyz", "xz", "z"])
def test_cells_match_the_oracle_over_images(device, dtype, gen, periodic):
    points = cloud(400, gen, SKEWED, dtype, device)
    cells = torchvor.voronoi(points, SKEWED, periodic=periodic, on_failure="raise")
    assert cells.volume.dtype == dtype
    total = cells.volume.double().sum().item()
    assert abs(total - box_volume(SKEWED)) <= 1e-6 * box_volume(SKEWED)
    tolerance = 1e-5 if dtype == torch.float32 else 1e-9
    check_cells(points, SKEWED, periodic, cells, range(0, 400, 23), tolerance)


def test_cells_of_tiny_clouds(device):
    one = torch.tensor([[0.25, 0.5, 0.75]], dtype=torch.float64, device=device)
    cells = torchvor.voronoi(one, BOX, periodic=True)
    assert cells.volume.item() == pytest.approx(1.0, rel=1e-12)
    np.testing.assert_allclose(cells.centroid.cpu().numpy(), one.cpu().numpy(), atol=1e-12)
    assert cells.second_moment.item() == pytest.approx(0.25, rel=1e-12)  # 3 * (1/12)
    two = torch.tensor([[0.1, 0.1, 0.1], [0.2, 0.9, 0.5]], dtype=torch.float64, device=device)
    cells = torchvor.voronoi(two, SKEWED if False else BOX, periodic=True)
    assert cells.volume.sum().item() == pytest.approx(1.0, rel=1e-12)
    check_cells(two, BOX, ALL, cells, [0, 1], 1e-9)


def _first_of_each(rows: torch.Tensor) -> torch.Tensor:
    """The index of the first of each distinct row."""
    _, inverse = torch.unique(rows, dim=0, return_inverse=True)
    first = torch.full((int(inverse.max()) + 1,), rows.shape[0], dtype=torch.int64)
    first = first.scatter_reduce(0, inverse, torch.arange(rows.shape[0]), "amin")
    return torch.sort(first).values


@pytest.mark.parametrize("periodic", [ALL, (False, True, False), (True, False, True)], ids=["xyz", "y", "xz"])
def test_tiny_clouds_with_points_on_the_faces(device, gen, periodic):
    """1 to 5 points, some coordinates exactly lo or hi (hi wraps to lo), a
    margin of a whole period: every cell against the oracle over the images,
    volumes summing to the box."""
    for n in range(1, 6):
        for _ in range(3):
            points = cloud(n, gen, SKEWED)
            lo, hi = (torch.tensor(b, dtype=torch.float64) for b in SKEWED)
            snap = torch.rand(n, 3, generator=gen) < 0.4
            ends = torch.where(torch.rand(n, 3, generator=gen) < 0.5, lo, hi)
            points = torch.where(snap, ends, points)
            on_torus = torch.where(torch.tensor(periodic) & (points == hi), lo, points)  # hi is lo there
            points = points[_first_of_each(on_torus)].to(device)  # no copies on the torus
            cells = torchvor.voronoi(points, SKEWED, periodic=periodic)
            volume = float((hi - lo).prod())
            assert cells.volume.sum().item() == pytest.approx(volume, rel=1e-9), points
            check_cells(points, SKEWED, periodic, cells, range(points.shape[0]), 1e-9)


def test_lattice_cells_are_exact(device, dtype):
    g = torch.arange(5, dtype=torch.float64) / 5 + 0.1
    points = torch.stack(torch.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3).to(dtype).to(device)
    cells = torchvor.voronoi(points, BOX, periodic=True, on_failure="raise")
    np.testing.assert_allclose(cells.volume.double().cpu().numpy(), 1 / 125, rtol=1e-6)
    np.testing.assert_allclose(cells.centroid.double().cpu().numpy(), points.double().cpu().numpy(), atol=1e-7)


def test_points_outside_the_box_are_their_images(device, gen):
    points = cloud(200, gen)
    turns = torch.randint(-3, 4, (200, 3), generator=gen).double()
    moved = (points + turns).to(device)
    cells = torchvor.voronoi(points.to(device), BOX, periodic=True)
    again = torchvor.voronoi(moved, BOX, periodic=True)
    np.testing.assert_allclose(again.volume.cpu().numpy(), cells.volume.cpu().numpy(), rtol=1e-12)
    # centroids next to the points as given
    np.testing.assert_allclose((again.centroid - moved).cpu().numpy(), (cells.centroid - points.to(device)).cpu().numpy(),
                               atol=1e-9)


def test_duplicates_across_the_faces(device):
    points = torch.tensor([[0.0, 0.5, 0.5], [1.0, 0.5, 0.5], [0.5, 0.5, 0.5]], dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, BOX, periodic=True, on_failure="raise")
    assert cells.status.tolist() == [0, torchvor.CellStatus.DUPLICATE, 0]
    assert cells.volume.sum().item() == pytest.approx(1.0, rel=1e-12)


def test_batches_with_their_own_boxes(device, gen):
    box = torch.tensor([[[0.0, 0.0, 0.0], [1.0, 1.0, 1.0]], [[2.0, 2.0, 2.0], [2.5, 3.0, 2.25]]], dtype=torch.float64)
    points = torch.cat([cloud(150, gen, box[0].tolist()), cloud(60, gen, box[1].tolist())]).to(device)
    batch = torch.repeat_interleave(torch.tensor([0, 1]), torch.tensor([150, 60])).to(device)
    cells = torchvor.voronoi(points, box.to(device), batch=batch, periodic=True, on_failure="raise")
    sums = torch.zeros(2, dtype=torch.float64).index_add(0, batch.cpu(), cells.volume.cpu())
    np.testing.assert_allclose(sums.numpy(), [1.0, 0.5 * 1.0 * 0.25], rtol=1e-9)
    alone = torchvor.voronoi(points[150:], box[1].tolist(), periodic=True)
    np.testing.assert_allclose(cells.volume[150:].cpu().numpy(), alone.volume.cpu().numpy(), rtol=1e-12)


def test_clustered_cells_reach_past_the_first_margin(device, gen):
    """A dense cluster in one corner and a few points elsewhere: cells far
    larger than the mean spacing wrap around (a wider margin)."""
    cluster = 0.05 + 0.02 * torch.rand(300, 3, generator=gen, dtype=torch.float64)
    sparse = cloud(5, gen)
    points = torch.cat([cluster, sparse]).to(device)
    cells = torchvor.voronoi(points, BOX, periodic=True, on_failure="raise")
    assert cells.volume.sum().item() == pytest.approx(1.0, rel=1e-9)
    check_cells(points, BOX, ALL, cells, [300, 301, 302, 303, 304, 0], 1e-9)


def test_cell_gradients_through_the_images(gen):
    points = cloud(30, gen).requires_grad_()

    def outputs(p):
        cells = torchvor.voronoi(p, BOX, periodic=True)
        return cells.volume, cells.centroid, cells.second_moment

    torch.autograd.gradcheck(outputs, (points,), atol=1e-6, rtol=1e-4)


# ---- faces -------------------------------------------------------------------

def test_graph_faces_match_the_oracle(device, gen):
    points = cloud(150, gen, SKEWED, torch.float64, device)
    periodic = (True, True, False)
    graph = torchvor.voronoi_graph(points, SKEWED, periodic=periodic, on_failure="raise")
    j, i = graph.edge_index.cpu()
    shift = graph.shift.cpu().long()
    assert graph.shift.dtype == torch.int8
    # sorted by cell, neighbour, shift; each face both ways with the opposite shift
    key = [(a, b, tuple(s)) for a, b, s in zip(i.tolist(), j.tolist(), shift.tolist())]
    assert key == sorted(key)
    back = {(a, b, s): e for e, (a, b, s) in enumerate(key)}
    for e, (a, b, s) in enumerate(key):
        f = back[(b, a, tuple(-v for v in s))]
        assert graph.area[e].item() == pytest.approx(graph.area[f].item(), rel=1e-9)
    # no walls on the periodic axes
    assert graph.wall_area[:, :4].abs().max().item() == 0
    for cell in range(0, 150, 17):
        oracle = periodic_cell_oracle(points.cpu(), cell, SKEWED, periodic)
        mine = {(b, s): e for e, (a, b, s) in enumerate(key) if a == cell}
        theirs = {k: v for k, v in oracle.faces.items() if k[1] is not None and v[0] > 1e-12 * oracle.area}
        assert set(mine) == set(theirs), cell
        for face, (area, centroid) in theirs.items():
            e = mine[face]
            assert graph.area[e].item() == pytest.approx(area, rel=1e-7, abs=1e-12)
            np.testing.assert_allclose(graph.centroid[e].cpu().numpy(), centroid, atol=1e-8)


def test_graph_of_one_point_meets_its_own_images(device):
    one = torch.tensor([[0.3, 0.3, 0.3]], dtype=torch.float64, device=device)
    graph = torchvor.voronoi_graph(one, BOX, periodic=True)
    assert graph.edge_index.tolist() == [[0] * 6, [0] * 6]
    assert sorted(map(tuple, graph.shift.tolist())) == sorted(
        [(-1, 0, 0), (1, 0, 0), (0, -1, 0), (0, 1, 0), (0, 0, -1), (0, 0, 1)])
    np.testing.assert_allclose(graph.area.cpu().numpy(), 1.0, rtol=1e-12)


def test_periodic_laplacian_closes_every_cell(device, gen):
    points = cloud(200, gen, SKEWED, torch.float64, device)
    graph = torchvor.voronoi_graph(points, SKEWED, periodic=True)
    laplacian = torchvor.voronoi_laplacian(points, SKEWED, periodic=True).to_dense().cpu()
    assert torch.allclose(laplacian, laplacian.T, atol=1e-12)
    assert laplacian.sum(1).abs().max() < 1e-9
    # every face closes its cell: sum_j a_ij (x_j + s L - x_i) / d_ij = 0
    j, i = graph.edge_index
    period = torch.tensor(SKEWED[1], dtype=torch.float64, device=device) - torch.tensor(SKEWED[0], dtype=torch.float64,
                                                                                     device=device)
    across = points[j] + graph.shift.double() * period - points[i]
    normal = graph.area[:, None] * across / across.norm(dim=1, keepdim=True)
    closure = torch.zeros_like(points).index_add(0, i, normal)
    assert closure.abs().max().item() < 1e-9


# ---- energy, Lloyd, command line -----------------------------------------------

def test_cvt_energy_and_its_gradient(gen):
    points = cloud(60, gen).requires_grad_()
    energy = torchvor.cvt_energy(points, BOX, periodic=True)
    cells = torchvor.voronoi(points.detach(), BOX, periodic=True)
    assert energy.item() == pytest.approx(cells.second_moment.sum().item(), rel=1e-12)
    (grad,) = torch.autograd.grad(energy, points, create_graph=True)
    expected = 2 * cells.volume[:, None] * (points.detach() - cells.centroid)
    torch.testing.assert_close(grad, expected)
    with pytest.raises(RuntimeError):  # first order only
        grad.sum().backward()
    torch.autograd.gradcheck(lambda p: torchvor.cvt_energy(p, BOX, periodic=True), (points.detach().requires_grad_(),),
                             atol=1e-6, rtol=1e-4)


def test_lloyd_wraps_and_lowers_the_energy(device, gen):
    points = cloud(300, gen, SKEWED, torch.float64, device)
    relaxed, history = torchvor.lloyd(points, SKEWED, iters=8, periodic=True, return_history=True)
    lo, hi = (torch.tensor(b, dtype=torch.float64, device=device) for b in SKEWED)
    assert bool(((relaxed >= lo) & (relaxed < hi)).all())
    energies = [step.energy for step in history]
    assert all(b <= a * (1 + 1e-12) for a, b in zip(energies, energies[1:]))
    # one step by hand: each point to its cell's centroid, wrapped
    cells = torchvor.voronoi(points, SKEWED, periodic=True)
    one = torchvor.lloyd(points, SKEWED, iters=1, periodic=True)
    moved = lo + torch.remainder(cells.centroid - lo, hi - lo)
    torch.testing.assert_close(one, moved, rtol=0, atol=1e-12)
    # the relaxed cells are more even than white noise's
    assert torchvor.voronoi(relaxed, SKEWED, periodic=True).volume.std() < cells.volume.std() / 2


def test_command_line(tmp_path):
    from torchvor.cli import main

    out = tmp_path / "graph.npz"
    assert main(["graph", "--n", "200", "--periodic", "xz", "--out", str(out), "--quiet", "--device", "cpu"]) == 0
    data = np.load(out)
    assert data["shift"].shape == (data["edge_index"].shape[1], 3) and data["shift"][:, 1].max() == 0
    assert data["volume"].sum() == pytest.approx(1.0, rel=1e-5)
    points = np.random.default_rng(0).random((100, 3)) * 2  # outside the unit box along every axis
    np.save(tmp_path / "points.npy", points)
    cells = tmp_path / "cells.npz"
    assert main(["cells", str(tmp_path / "points.npy"), "--periodic", "xyz", "--box", "0", "0", "0", "1", "1", "1",
                 "--out", str(cells), "--quiet", "--device", "cpu", "--dtype", "float64"]) == 0
    assert main(["cells", str(tmp_path / "points.npy"), "--periodic", "xyz", "--out", str(cells), "--quiet",
                 "--device", "cpu"]) == 2  # needs --box
    assert main(["lloyd", "--n", "100", "--periodic", "xw", "--out", str(tmp_path / "p.npy"), "--quiet",
                 "--device", "cpu"]) == 2


def test_empty_inputs(device):
    empty = torch.empty(0, 3, dtype=torch.float64, device=device)
    assert torchvor.voronoi(empty, BOX, periodic=True).volume.shape == (0,)
    assert torchvor.knn(empty, 3, box=BOX, periodic=True).idx.shape == (0, 3)
    assert torchvor.radius(empty, 0.1, box=BOX, periodic=True).edge_index.shape == (2, 0)
    graph = torchvor.voronoi_graph(empty, BOX, periodic=True)
    assert graph.edge_index.shape == (2, 0) and graph.shift.shape == (0, 3)
    assert torchvor.lloyd(empty, BOX, iters=2, periodic=True).shape == (0, 3)
    queries = torch.rand(4, 3, dtype=torch.float64, device=device)
    assert torchvor.knn(empty, 2, queries, box=BOX, periodic=True).idx.eq(-1).all()


def test_a_period_far_shorter_than_the_cells(device, dtype, gen):
    """A box 1e-5 thin along a periodic axis: cells span it, and images past
    one period are never needed (the padding stops there)."""
    box = ([0.0, 0.0, 0.0], [1.0, 1.0, 1e-5])
    points = cloud(40, gen, box, dtype, device)
    cells = torchvor.voronoi(points, box, periodic=True, on_failure="raise")
    assert cells.volume.double().sum().item() == pytest.approx(1e-5, rel=1e-5)
    check_cells(points, box, ALL, cells, [0, 13], 1e-5 if dtype == torch.float32 else 1e-9)
    from scipy.spatial import cKDTree

    near = torchvor.knn(points, 5, box=box, periodic=True)
    data = points.double().cpu().numpy()
    dist, _ = cKDTree(data, boxsize=[1.0, 1.0, 1e-5]).query(data, 6)
    np.testing.assert_allclose(near.dist2.double().cpu().numpy(), dist[:, 1:] ** 2, rtol=1e-6)


def test_float32_periods_are_taken_in_float64(device):
    """A float32 box whose edge rounds in float32: the period is the corners'
    difference in float64 (a rounded one moved the images by 3e-13, and a
    sliver cell beside the face of a thin slab by 2e-3)."""
    import fuzz_cases

    case = fuzz_cases.make_case(9, 34, max_n=1000)  # thin slab, points clamped to its faces
    points = torch.as_tensor(case.points, dtype=torch.float32, device=device)
    box = torch.as_tensor(case.boxes[0], dtype=torch.float32, device=device)
    single = torchvor.voronoi(points, box, periodic=(True, False, True))
    double = torchvor.voronoi(points.double(), box.double(), periodic=(True, False, True))
    assert torch.equal(single.volume, double.volume.float())


def test_float32_runs_in_float32_where_every_image_is_exact(device, gen, monkeypatch):
    """float32 points are computed in float32 where every image x - k (hi - lo)
    is exact (a box [0, 1]), in float64 where one would round (a box
    [-0.5, 0.5]: points just below 0.5 have a finer spacing than their images
    below -0.5); both within float32's 1e-4 of the float64 cells of the same
    coordinates, a cluster of spread 1e-6 at each face included. (Enough
    points that the images lie within half a period below lo: x - 1 is exact
    for x in [0.5, 1].)"""
    from torchvor import periodic as periodic_module

    used = []
    inner = periodic_module._cells
    monkeypatch.setattr(periodic_module, "_cells", lambda *args: used.append(args[6]) or inner(*args))  # its dtype
    for box, expected in ((BOX, torch.float32), (([-0.5] * 3, [0.5] * 3), torch.float64)):
        lo, hi = (torch.tensor(b, dtype=torch.float64) for b in box)
        spread = torch.cat([lo + torch.rand(20000, 3, generator=gen, dtype=torch.float64) * (hi - lo),
                            lo + 3e-6 + 1e-6 * torch.rand(30, 3, generator=gen, dtype=torch.float64),
                            hi - 3e-6 - 1e-6 * torch.rand(30, 3, generator=gen, dtype=torch.float64)])
        points = spread.float().to(device)
        used.clear()
        single = torchvor.voronoi(points, box, periodic=True)
        assert used[-1] == expected
        double = torchvor.voronoi(points.double(), box, periodic=True)
        assert torch.equal(single.status, double.status)  # SUCCESS, or DUPLICATE where float32 rounds points together
        assert bool(((single.status == 0) | (single.status == int(torchvor.CellStatus.DUPLICATE))).all())
        torch.testing.assert_close(single.volume.double(), double.volume, rtol=1e-4, atol=0)
        size = double.volume ** (1 / 3)
        ulp = 2.0 ** -23 * double.centroid.abs().amax(1)  # the float32 output's rounding
        assert bool(((single.centroid.double() - double.centroid).norm(dim=1) <= 1e-4 * size + 2 * ulp).all())
        assert abs(float(double.volume.sum()) - 1.0) <= 1e-9


def test_images_that_would_round_are_detected(device):
    """x - 1 is exact for x in [0.5, 1) but rounds for an x below 0.5 with its
    last bit set: the one-sided padding is then not used (float64 cells of a
    pair 1 ulp apart, split wrongly at its rounded images: fuzz seed 5 case 22)."""
    from torchvor import periodic as periodic_module

    fine = 0.25 + 2.0 ** -54  # in [0.25, 0.5): its image below 0 rounds
    for value, exact in ((0.75, True), (fine, False)):
        x = torch.tensor([[value, 0.5, 0.5]], dtype=torch.float64, device=device)
        pbox = periodic_module.periodic_box(x, BOX, None, ALL, "voronoi")
        margin = torch.ones(1, dtype=torch.float64, device=device)
        padded = periodic_module.pad(x, pbox, None, margin, one_sided=True)
        assert periodic_module.images_exact(x, x, padded, pbox, None) == exact
    pair = torch.tensor([[fine, 0.3, 0.4], [fine + 2.0 ** -54, 0.3 + 2.0 ** -54, 0.4], [0.7, 0.8, 0.9]],
                        dtype=torch.float64, device=device)
    cells = torchvor.voronoi(pair, BOX, periodic=(True, False, True))
    check_cells(pair, BOX, (True, False, True), cells, range(3), 1e-9)
