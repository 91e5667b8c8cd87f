"""Power (Laguerre) diagrams: torchvor.voronoi / voronoi_graph / voronoi_laplacian
with weights, and torchvor.power_weights, against the half-space oracle with
power bisectors (oracles.voronoi_cell_oracle with weights)."""
from __future__ import annotations

import math
import warnings

import numpy as np
import pytest
import torch

import torchvor
import torchvor.distributed
from torchvor import CellStatus
from oracles import voronoi_cell_oracle

BOX = ((0.0, 0.0, 0.0), (1.0, 1.0, 1.0))


def _cloud(n, gen, dtype, device):
    return torch.rand(n, 3, generator=gen, dtype=torch.float64).to(dtype=dtype, device=device)


def _weights(n, spread, gen, dtype, device):
    """Weights uniform in [0, spread * s^2], s the mean spacing of n points in the unit cube."""
    scale = spread * n ** (-2.0 / 3.0)
    return (torch.rand(n, generator=gen, dtype=torch.float64) * scale).to(dtype=dtype, device=device)


@pytest.mark.parametrize("shift", [0.0, 3.5])
def test_equal_weights_give_the_voronoi_cells(device, dtype, gen, shift):
    points = _cloud(500, gen, dtype, device)
    plain = torchvor.voronoi(points.double(), BOX)
    power = torchvor.voronoi(points, BOX, weights=torch.full((500,), shift, dtype=dtype, device=device))
    assert bool((power.status == CellStatus.SUCCESS).all())
    tol = 1e-12 if dtype == torch.float64 else 1e-6
    torch.testing.assert_close(power.volume.double(), plain.volume, atol=tol, rtol=tol)
    torch.testing.assert_close(power.centroid.double(), plain.centroid, atol=tol, rtol=tol)
    torch.testing.assert_close(power.second_moment.double(), plain.second_moment, atol=tol, rtol=tol)


def _assert_the_oracle_cells(cells, pts: np.ndarray, w: np.ndarray, box) -> None:
    """Every cell (status, volume, centroid, second moment) as the float64
    half-space oracle with power bisectors gives it; the volumes sum to the box's."""
    status = cells.status.cpu().numpy()
    volume, centroid, second = (t.cpu().numpy() for t in (cells.volume, cells.centroid, cells.second_moment))
    for i in range(len(pts)):
        oracle = voronoi_cell_oracle(pts, i, box, weights=w)
        if oracle.empty or oracle.volume < 1e-13:
            assert status[i] == CellStatus.EMPTY or abs(volume[i]) < 1e-12, (i, status[i], volume[i])
            continue
        assert status[i] == CellStatus.SUCCESS, (i, status[i])
        assert abs(volume[i] - oracle.volume) <= 1e-9 * max(oracle.volume, 1e-6), (i, volume[i], oracle.volume)
        assert np.abs(centroid[i] - oracle.centroid).max() <= 1e-8, i
        assert abs(second[i] - oracle.second_moment) <= 1e-9 * max(oracle.second_moment, 1e-8), i
    box_volume = float(np.prod(box[1] - box[0]))
    assert abs(float(cells.volume.sum()) - box_volume) < 1e-12 * max(box_volume, 1.0)


@pytest.mark.parametrize("spread", [0.3, 3.0])
def test_power_cells_match_the_oracle(device, gen, spread):
    """Every cell of 300 points against the float64 half-space oracle; spread
    3 empties many cells and moves others away from their points."""
    n = 300
    points = _cloud(n, gen, torch.float64, device)
    weights = _weights(n, spread, gen, torch.float64, device)
    cells = torchvor.voronoi(points, BOX, weights=weights, k=8)  # k: unused by power cells
    _assert_the_oracle_cells(cells, points.cpu().numpy(), weights.cpu().numpy(), (np.zeros(3), np.ones(3)))
    if spread == 3.0:
        assert int((cells.status == CellStatus.EMPTY).sum()) > 0
        empty = cells.status == CellStatus.EMPTY
        assert bool((cells.volume[empty] == 0).all())
        torch.testing.assert_close(cells.centroid[empty], points[empty])


def _walk_case(kind, gen):
    """(points (n, 3), weights (n,), box ((3,), (3,))) float64 on the CPU: clouds
    whose cells' walks reach across the grid of the points, or past it."""
    if kind == "clustered_in_a_wide_box":  # the grid covers the cluster only; the cells reach the walls
        points = 0.45 + 0.1 * torch.rand(150, 3, generator=gen, dtype=torch.float64)
        weights = torch.rand(150, generator=gen, dtype=torch.float64) * 0.002
        return points, weights, (np.full(3, -1.0), np.full(3, 2.0))
    if kind == "one_heavy_point":  # its plane cuts cells many cubes away
        points = torch.rand(200, 3, generator=gen, dtype=torch.float64)
        weights = torch.zeros(200, dtype=torch.float64)
        weights[0] = 0.12
        return points, weights, (np.zeros(3), np.ones(3))
    if kind == "crowded_cubes":  # a cluster: the 27 cubes around a point hold more than the nearest-first 64
        points = torch.rand(300, 3, generator=gen, dtype=torch.float64)
        points[100:] = 0.3 + 0.02 * points[100:]
        weights = torch.rand(300, generator=gen, dtype=torch.float64) * 1e-4
        return points, weights, (np.zeros(3), np.ones(3))
    if kind == "flat_cloud":  # one cube thick: every shell past the first is clamped along z
        points = torch.rand(160, 3, generator=gen, dtype=torch.float64)
        points[:, 2] = 0.5
        weights = torch.rand(160, generator=gen, dtype=torch.float64) * 0.01
        return points, weights, (np.zeros(3), np.ones(3))
    # weights of a few points far above the others: many empty cells, long reaches
    points = torch.rand(250, 3, generator=gen, dtype=torch.float64)
    weights = torch.rand(250, generator=gen, dtype=torch.float64) * 0.002
    weights[:5] += 0.05
    return points, weights, (np.zeros(3), np.ones(3))


@pytest.mark.parametrize("kind", ["clustered_in_a_wide_box", "crowded_cubes", "one_heavy_point", "flat_cloud",
                                  "a_few_heavy_points"])
def test_walks_that_reach_far_match_the_oracle(device, gen, kind):
    """Cells whose walk over the grid of the points must reach many cubes away,
    or past the grid to the walls, against the half-space oracle."""
    points, weights, (lo, hi) = _walk_case(kind, gen)
    box = torch.tensor(np.stack([lo, hi]), dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points.to(device), box, weights=weights.to(device))
    _assert_the_oracle_cells(cells, points.numpy(), weights.numpy(), (lo, hi))


@pytest.mark.parametrize("variant, dtype", [
    (("TORCHVOR_POWER_NEAREST_FIRST", "0"), torch.float64),
    (("TORCHVOR_POWER_NEAREST_FIRST", "all"), torch.float32),
    (("TORCHVOR_POWER_POINTS_PER_CUBE", "1"), torch.float64),
    (("TORCHVOR_POWER_POINTS_PER_CUBE", "5"), torch.float64)])
def test_walk_variants_give_the_same_cells(device, gen, monkeypatch, variant, dtype):
    """The walk's tuning options (the first cubes nearest first or in the walk's
    order, for the float64 cells or the float32 ones too; the grid's density, 5
    a cube overflowing the nearest-first points in a cluster) change the order
    of the clips only: the cells agree to rounding."""
    points = torch.rand(600, 3, generator=gen, dtype=torch.float64)
    points[400:] = 0.6 + 0.03 * points[400:]
    weights = torch.rand(600, generator=gen, dtype=torch.float64) * 3e-3
    points, weights = points.to(device, dtype), weights.to(device, dtype)
    default = torchvor.voronoi(points, BOX, weights=weights)
    monkeypatch.setenv(*variant)
    varied = torchvor.voronoi(points, BOX, weights=weights)
    assert bool((varied.status == default.status).all())
    assert int((default.status == CellStatus.EMPTY).sum()) > 0
    rtol, atol = (1e-11, 1e-12) if dtype == torch.float64 else (1e-4, 1e-5)
    torch.testing.assert_close(varied.volume, default.volume, rtol=rtol, atol=1e-16)
    torch.testing.assert_close(varied.centroid, default.centroid, rtol=0, atol=atol)


def test_float32_points_are_computed_in_float64(device, gen):
    points = _cloud(400, gen, torch.float32, device)
    weights = _weights(400, 1.0, gen, torch.float32, device)
    single = torchvor.voronoi(points, BOX, weights=weights)
    double = torchvor.voronoi(points.double(), BOX, weights=weights.double())
    assert single.volume.dtype == torch.float32
    torch.testing.assert_close(single.volume, double.volume.float())
    torch.testing.assert_close(single.status, double.status)


def test_copies_of_a_point(device):
    """A copy with a larger weight empties the cell; equal weights: the lower index keeps it."""
    points = torch.tensor([[0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.5], [0.2, 0.3, 0.4]],
                          dtype=torch.float64, device=device)
    weights = torch.tensor([0.0, 0.01, 0.01, 0.0], dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, BOX, weights=weights)
    assert cells.status.tolist() == [CellStatus.EMPTY, CellStatus.SUCCESS, CellStatus.DUPLICATE, CellStatus.SUCCESS]
    assert cells.volume[0] == 0 and cells.volume[2] == 0
    assert abs(float(cells.volume.sum()) - 1.0) < 1e-12


def test_batches_are_separate_diagrams(device, gen):
    points = _cloud(200, gen, torch.float64, device)
    weights = _weights(200, 1.0, gen, torch.float64, device)
    batch = torch.cat([torch.zeros(80, dtype=torch.int64), torch.ones(120, dtype=torch.int64)]).to(device)
    boxes = torch.tensor([[[0.0, 0, 0], [1, 1, 1]], [[-1.0, 0, 0], [1, 2, 1]]], dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, boxes, batch=batch, weights=weights)
    first = torchvor.voronoi(points[:80], boxes[0], weights=weights[:80])
    second = torchvor.voronoi(points[80:], boxes[1], weights=weights[80:])
    torch.testing.assert_close(cells.volume, torch.cat([first.volume, second.volume]), rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(cells.centroid, torch.cat([first.centroid, second.centroid]), rtol=1e-12,
                               atol=1e-14)


def test_power_graph_faces_match_the_oracle(device, gen):
    n = 120
    points = _cloud(n, gen, torch.float64, device)
    weights = _weights(n, 1.0, gen, torch.float64, device)
    graph = torchvor.voronoi_graph(points, BOX, weights=weights)
    source, target = graph.edge_index.cpu()
    pts, w = points.cpu().numpy(), weights.cpu().numpy()
    box = (np.zeros(3), np.ones(3))
    area, centroid = graph.area.cpu().numpy(), graph.centroid.cpu().numpy()
    wall_area = graph.wall_area.cpu().numpy()
    for i in range(n):
        oracle = voronoi_cell_oracle(pts, i, box, weights=w)
        mine = {int(j): e for e, j in zip(torch.nonzero(target == i).flatten().tolist(), source[target == i].tolist())}
        expected = {j: f for j, f in (oracle.faces or {}).items() if j >= 0 and f[0] > 1e-12}
        assert set(expected) <= set(mine), (i, sorted(expected), sorted(mine))
        for j, e in mine.items():
            a, c = expected.get(j, (0.0, None))
            assert abs(area[e] - a) <= 1e-9, (i, j, area[e], a)
            if c is not None:
                assert np.abs(centroid[e] - c).max() <= 1e-8
        for wall in range(6):
            a = (oracle.faces or {}).get(-1 - wall, (0.0, None))[0]
            assert abs(wall_area[i, wall] - a) <= 1e-9
    # every face both ways, sorted by cell then neighbour
    key = target * n + source
    assert bool((key[1:] > key[:-1]).all())
    reverse = set(zip(target.tolist(), source.tolist()))
    assert all((int(j), int(i)) in reverse for j, i in zip(source.tolist(), target.tolist()))


def test_power_laplacian_rows_sum_to_zero(device, gen):
    points = _cloud(200, gen, torch.float64, device)
    weights = _weights(200, 1.0, gen, torch.float64, device)
    lap = torchvor.voronoi_laplacian(points, BOX, weights=weights)
    dense = lap.to_dense()
    torch.testing.assert_close(dense.sum(1), torch.zeros(200, dtype=torch.float64, device=device), atol=1e-12,
                               rtol=0)
    torch.testing.assert_close(dense, dense.T)


def test_gradients_in_the_weights(device):
    """gradcheck of volume, centroid and second moment in the weights (small
    moves: no face appears or vanishes). A fixed cloud: finite differences
    across a face that appears would not match any gradient."""
    n = 40
    gen = torch.Generator().manual_seed(12)
    points = _cloud(n, gen, torch.float64, device)
    weights = _weights(n, 0.5, gen, torch.float64, device).requires_grad_()
    assert bool((torchvor.voronoi(points, BOX, weights=weights.detach()).status == CellStatus.SUCCESS).all())

    def outputs(w):
        cells = torchvor.voronoi(points, BOX, weights=w)
        return cells.volume, cells.centroid, cells.second_moment

    # CUDA's index_add sums in no fixed order: backward may differ in the last bits
    nondet = 1e-12 if device.type == "cuda" else 0.0
    assert torch.autograd.gradcheck(outputs, (weights,), eps=1e-7, atol=1e-5, rtol=1e-4, nondet_tol=nondet)


def test_gradients_in_the_points_raise(device, gen):
    points = _cloud(30, gen, torch.float64, device).requires_grad_()
    weights = torch.zeros(30, dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, BOX, weights=weights)
    with pytest.raises(RuntimeError, match="not yet in the points"):
        cells.volume.sum().backward()


@pytest.mark.parametrize("varying", [False, True])
def test_power_weights_reach_the_target_volumes(device, dtype, gen, varying):
    n = 1000
    points = _cloud(n, gen, dtype, device)
    volumes = None
    if varying:
        volumes = (1 + 2 * torch.rand(n, generator=gen, dtype=torch.float64)).to(dtype=dtype, device=device)
    result = torchvor.power_weights(points, BOX, volumes=volumes, tol=1e-6)
    assert result.error <= (1e-6 if dtype == torch.float64 else 1e-4) and result.iterations <= 20
    assert result.weights.dtype == dtype and result.weights.shape == (n,)
    target = (torch.full((n,), 1.0 / n, dtype=torch.float64) if volumes is None
              else volumes.double().cpu() / float(volumes.double().sum()))
    cells = torchvor.voronoi(points.double(), BOX, weights=result.weights.double())
    error = ((cells.volume.cpu() - target).abs() / target).max()
    assert abs(float(error) - result.error) <= 1e-3 * result.error + 1e-15
    torch.testing.assert_close(result.cells.volume.cpu(), cells.volume.to(dtype).cpu(), rtol=1e-12, atol=0)


def test_power_weights_errors(device):
    points = torch.rand(50, 3, dtype=torch.float64, device=device)
    with pytest.raises(ValueError, match="tol"):
        torchvor.power_weights(points, BOX, tol=0)
    with pytest.raises(ValueError, match="positive"):
        torchvor.power_weights(points, BOX, volumes=-torch.ones(50, dtype=torch.float64, device=device))
    copied = torch.cat([points, points[:1]])
    with pytest.raises(ValueError, match="distinct"):
        torchvor.power_weights(copied, BOX)
    with pytest.warns(RuntimeWarning, match="not converged"):
        result = torchvor.power_weights(points, BOX, max_iters=1, tol=1e-15)
    assert result.iterations == 1


def test_weights_argument_errors(device):
    points = torch.rand(20, 3, dtype=torch.float64, device=device)
    with pytest.raises(ValueError, match=r"shape \(20,\)"):
        torchvor.voronoi(points, BOX, weights=torch.zeros(19, dtype=torch.float64, device=device))
    with pytest.raises(TypeError, match="dtype"):
        torchvor.voronoi(points, BOX, weights=torch.zeros(20, dtype=torch.float32, device=device))
    with pytest.raises(ValueError, match="NaN"):
        torchvor.voronoi(points, BOX, weights=torch.full((20,), math.nan, dtype=torch.float64, device=device))
    with pytest.raises(TypeError, match="torch.Tensor"):
        torchvor.voronoi(points, BOX, weights=[0.0] * 20)
    with pytest.raises(NotImplementedError, match="not distributed"):
        torchvor.distributed.voronoi(points, BOX, weights=torch.zeros(20, dtype=torch.float64, device=device))
    with pytest.raises(ValueError, match="periodic needs a box"):
        torchvor.voronoi(points, None, weights=torch.zeros(20, dtype=torch.float64, device=device), periodic=True)
    with pytest.raises(ValueError, match="inside"):
        torchvor.voronoi(points + 2, BOX, weights=torch.zeros(20, dtype=torch.float64, device=device))


def test_empty_input(device):
    points = torch.empty(0, 3, dtype=torch.float64, device=device)
    cells = torchvor.voronoi(points, BOX, weights=torch.empty(0, dtype=torch.float64, device=device))
    assert cells.volume.shape == (0,)
    result = torchvor.power_weights(points, BOX)
    assert result.weights.shape == (0,) and result.iterations == 0


def test_opcheck_power_ops(device, dtype, gen):
    points = _cloud(30, gen, dtype, device)
    weights = _weights(30, 1.0, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    rows = torch.arange(30, device=device)
    weight_max = weights.double().max().expand(30).contiguous()  # per row: no point weighs more
    torch.library.opcheck(torch.ops.torchvor.power_cells.default, (points, weights, box, None, rows, weight_max, 1))
    if dtype == torch.float32:  # tier 0, float32 cells, on a jittered lattice: none sent on with NaN outputs
        lattice = torch.stack(torch.meshgrid(*[torch.arange(3.0)] * 3, indexing="ij"), -1).reshape(-1, 3)
        jittered = ((lattice + 0.5 + 0.3 * (torch.rand(27, 3, generator=gen) - 0.5)) / 3).to(device)
        small = weights[:27] * 0.1
        bound = small.double().max().expand(27).contiguous()
        out = torch.ops.torchvor.power_cells.default(jittered, small, box, None, rows[:27], bound, 0)
        assert bool((out[3] == CellStatus.SUCCESS).all())
        torch.library.opcheck(torch.ops.torchvor.power_cells.default, (jittered, small, box, None, rows[:27], bound, 0))
    # the cells claiming their faces' rows, in an order the threads decide: the
    # checks that compare two runs' outputs do not apply
    torch.library.opcheck(torch.ops.torchvor.power_cells.default, (points, weights, box, None, rows, weight_max, 1, 20),
                          test_utils=("test_autograd_registration", "test_faketensor"))
    counts = torch.ops.torchvor.power_cells.default(points, weights, box, None, rows, weight_max, 1)[6]
    offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)]).long()
    torch.library.opcheck(torch.ops.torchvor.power_faces.default,
                          (points, weights, box, None, rows, weight_max, 1, offsets))


def _sorted_faces(faces):
    """PowerFaces as a tuple of tensors in (cell, target) order."""
    order = torch.argsort(faces.cell * (1 << 32) + faces.target + 7)
    return tuple(t[order] for t in faces)


def test_claimed_faces_are_the_face_pass_faces(device, gen, monkeypatch):
    """The faces the cells' own pass writes (each cell claiming its rows) are the
    second pass's (power_faces), to the rounding of the two compiled copies (a * b
    + c fused in one, not in the other), also where the room runs out part of the
    way (the rest from the second pass)."""
    from torchvor import power

    points = _cloud(400, gen, torch.float64, device)
    weights = _weights(400, 2.0, gen, torch.float64, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64, device=device)
    _cells, claimed = power.power_cells(points, weights, box, faces=True)
    count = torch.ops.torchvor.power_cells.default(points, weights, box, None, torch.arange(400, device=device),
                                                   weights.max().expand(400).contiguous(), 1, 20)
    assert bool(((count[7] >= 0) == (count[6] > 0)).all()), "room for 20 faces a cell: every cell with faces claims"
    assert bool((count[3] == CellStatus.EMPTY).any())
    seen = []
    real_faces = power._faces
    monkeypatch.setattr(power, "_faces", lambda *a: seen.append(int((a[6] > 0).sum())) or real_faces(*a))
    monkeypatch.setattr(power, "FACE_ROOM", 6)  # fewer than the cells have on average: the room runs out
    _cells, mixed = power.power_cells(points, weights, box, faces=True)
    assert seen and 0 < seen[0] < 400, seen
    monkeypatch.setattr(power, "FACE_ROOM", 1)
    _cells, second = power.power_cells(points, weights, box, faces=True, memory_budget=1 << 12)
    for a, b, c in zip(_sorted_faces(claimed), _sorted_faces(mixed), _sorted_faces(second)):
        exact = not a.is_floating_point()  # the cells and targets
        torch.testing.assert_close(a, c, rtol=0 if exact else 1e-12, atol=0 if exact else 1e-18)
        torch.testing.assert_close(b, c, rtol=0 if exact else 1e-12, atol=0 if exact else 1e-18)


def test_larger_tiers_give_the_same_cells(device, gen):
    """Float64 tiers 1-5 (tiers 3-5 on the CPU, whatever the device) agree bit for
    bit; tiers 6-7 (double-double) to float64's rounding."""
    points = _cloud(60, gen, torch.float64, device)
    weights = _weights(60, 1.0, gen, torch.float64, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64, device=device)
    rows = torch.arange(60, device=device)
    weight_max = weights.max().expand(60).contiguous()
    results = {tier: torch.ops.torchvor.power_cells.default(points, weights, box, None, rows, weight_max, tier)
               for tier in range(1, 8)}
    # bit for bit within a processor (tiers 1-2 on the device, 3-5 on the CPU: on CUDA
    # the two compile a * b + c apart), to rounding across them
    for first, second in ((1, 2), (3, 4), (4, 5), (1, 3)):
        exact = first != 1 or second != 3 or device.type == "cpu"
        assert results[second][0].device == points.device
        torch.testing.assert_close(results[second][0], results[first][0], rtol=0 if exact else 1e-13, atol=0)
        torch.testing.assert_close(results[second][3], results[first][3], rtol=0, atol=0)
    torch.testing.assert_close(results[6][0], results[1][0], rtol=1e-12, atol=1e-16)
    torch.testing.assert_close(results[6][1], results[1][1], rtol=1e-12, atol=1e-14)
    torch.testing.assert_close(results[6][3], results[1][3], rtol=0, atol=0)
    torch.testing.assert_close(results[6][6], results[1][6], rtol=0, atol=0)
    torch.testing.assert_close(results[7][0], results[6][0], rtol=0, atol=0)


def test_float32_tier(device, gen):
    """Tier 0 computes float32 points' cells in float32: within float32's guarantee
    (1e-4 relative volume) of the float64 tier's on the same points, EMPTY only
    where float64 finds them empty, or sent on (ILL_CONDITIONED: a cell rounding
    could have emptied, BOUNDARY_ERROR: float predicates that disagree,
    TOO_MANY_PLANES, TOO_MANY_VERTICES); it takes no float64 points."""
    points = _cloud(2000, gen, torch.float32, device)
    weights = _weights(2000, 3.0, gen, torch.float32, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float32, device=device)
    rows = torch.arange(2000, device=device)
    weight_max = weights.double().max().expand(2000).contiguous()
    single = torch.ops.torchvor.power_cells.default(points, weights, box, None, rows, weight_max, 0)
    double = torch.ops.torchvor.power_cells.default(points, weights, box, None, rows, weight_max, 1)
    assert single[0].dtype == torch.float32
    done = single[3] == CellStatus.SUCCESS
    empty = single[3] == CellStatus.EMPTY
    assert float((done | empty).float().mean()) > 0.9 and bool(empty.any())
    sent_on = (CellStatus.ILL_CONDITIONED, CellStatus.BOUNDARY_ERROR, CellStatus.TOO_MANY_PLANES,
               CellStatus.TOO_MANY_VERTICES)
    assert bool(sum(single[3] == code for code in sent_on)[~(done | empty)].all()), single[3].unique()
    assert bool((double[3][done] == CellStatus.SUCCESS).all()) and bool((double[3][empty] == CellStatus.EMPTY).all())
    torch.testing.assert_close(single[0][done], double[0][done], rtol=1e-4, atol=0)
    scale = float(double[0][done].max()) ** (1 / 3)
    torch.testing.assert_close(single[1][done], double[1][done], rtol=0, atol=1e-4 * scale)
    with pytest.raises(ValueError, match="tier 0"):
        torch.ops.torchvor.power_cells.default(points.double(), weights.double(), box.double(), None, rows,
                                               weight_max, 0)


def test_float32_faces(device, gen):
    """Float32 points' faces computed in float32 (power_cells' float32_faces, for
    power_weights' first steps): the float64 faces' neighbours and areas, to
    1e-4 of a face's scale (a face that small may be missing on either side)."""
    from torchvor.power import graph_of_faces, power_cells

    n = 2000
    points = _cloud(n, gen, torch.float32, device)
    weights = _weights(n, 3.0, gen, torch.float32, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float32, device=device)
    areas = []
    for float32_faces in (True, False):
        cells, faces = power_cells(points, weights, box, faces=True, float32_faces=float32_faces)
        assert faces.area.dtype == torch.float32
        edge_index, area, _centroid, wall_area = graph_of_faces(n, faces, torch.float32)
        dense = torch.zeros(n * n, dtype=torch.float64, device=device)
        dense[edge_index[1] * n + edge_index[0]] = area.double()
        areas.append((cells, dense, wall_area.double()))
    (single, single_area, single_walls), (double, double_area, double_walls) = areas
    torch.testing.assert_close(single.status, double.status)
    scale = n ** (-2.0 / 3.0)
    assert float((single_area - double_area).abs().max()) <= 1e-4 * scale
    assert float((single_walls - double_walls).abs().max()) <= 1e-4 * scale


def test_power_lloyd_keeps_the_volumes_and_relaxes(device):
    """Capacity-constrained Lloyd: every cell keeps its target volume, the
    points move to their power cells' centroids, and the CVT energy drops."""
    gen = torch.Generator().manual_seed(3)
    points = _cloud(300, gen, torch.float64, device)
    moved, weights = torchvor.power_lloyd(points, BOX, iters=4)
    assert moved.shape == points.shape and weights.shape == (300,)
    assert bool(((moved >= 0) & (moved <= 1)).all())
    cells = torchvor.voronoi(moved, BOX, weights=weights)
    before = torchvor.voronoi(points, BOX).second_moment.sum()
    after = torchvor.voronoi(moved, BOX).second_moment.sum()
    assert float(after) < float(before)
    # the last weights give the last points' (pre-move) cells the target volumes; moved
    # points need new ones: solve again and check the capacity
    solved = torchvor.power_weights(moved, BOX, weights=weights)
    assert solved.error <= 1e-6 and solved.iterations <= 5
    assert bool((cells.status == CellStatus.SUCCESS).all())


def test_power_weights_warm_start(device):
    gen = torch.Generator().manual_seed(4)
    points = _cloud(500, gen, torch.float64, device)
    first = torchvor.power_weights(points, BOX)
    again = torchvor.power_weights(points, BOX, weights=first.weights + 0.25)
    assert again.iterations == 0 and again.error <= 1e-6
    torch.testing.assert_close(again.weights, first.weights, atol=1e-15, rtol=0)
    # a start that empties cells (Newton needs every cell nonempty) is halved towards zero weights
    wild = _weights(500, 40.0, gen, torch.float64, device)
    assert bool((torchvor.voronoi(points, BOX, weights=wild).status == CellStatus.EMPTY).any())
    rescued = torchvor.power_weights(points, BOX, weights=wild)
    assert rescued.error <= 1e-6 and bool((rescued.cells.status == CellStatus.SUCCESS).all())


def test_needle_cells_go_to_double_double(device):
    """The fuzzing campaign's case (seed 51, case 28): a jittered lattice in a box
    0.44 x 26.8 x 0.047, whose needle cells float64 does not resolve (ILL_CONDITIONED at
    tier 0): recomputed in double-double, with equal weights they are the Voronoi cells."""
    from fuzz_cases import make_case

    case = make_case(51, 28, max_n=3000, dtype="both")
    points, box, batch = case.arguments(device)
    weights = torch.zeros(case.n, dtype=case.dtype, device=device)
    power = torchvor.voronoi(points, box, batch=batch, weights=weights, on_failure="raise")
    plain = torchvor.voronoi(points, box, batch=batch)
    torch.testing.assert_close(power.status, plain.status)
    computed = power.status == CellStatus.SUCCESS
    torch.testing.assert_close(power.volume[computed], plain.volume[computed], rtol=1e-9, atol=0)


def test_lloyd_with_volumes_is_power_lloyd(device):
    gen = torch.Generator().manual_seed(5)
    points = _cloud(200, gen, torch.float64, device)
    volumes = (1 + torch.rand(200, generator=gen, dtype=torch.float64)).to(device)
    moved = torchvor.lloyd(points, BOX, iters=2, volumes=volumes)
    expected, _ = torchvor.power_lloyd(points, BOX, iters=2, volumes=volumes)
    # CUDA's index_add (the Newton steps' conjugate gradients) sums in no fixed order
    exact = 0 if device.type == "cpu" else 1e-12
    torch.testing.assert_close(moved, expected, rtol=0, atol=exact)
    # a tolerance that any move meets stops after the first iteration
    once, _ = torchvor.power_lloyd(points, BOX, iters=1, volumes=volumes)
    torch.testing.assert_close(torchvor.lloyd(points, BOX, iters=5, volumes=volumes, tol=1.0), once, rtol=0,
                               atol=exact)
    with pytest.raises(ValueError, match="does not take batch"):
        torchvor.lloyd(points, BOX, volumes=volumes, batch=torch.zeros(200, dtype=torch.int64, device=device))
    with pytest.raises(ValueError, match="does not take callback"):
        torchvor.lloyd(points, BOX, volumes=volumes, callback=lambda *_: None)


def test_power_weights_float32_first_steps(device, monkeypatch):
    """Float32 points: the first steps' cells are computed in float32, which
    changes neither the steps taken nor, beyond rounding, the error; float64
    points never compute in float32."""
    import torchvor.power as power
    import torchvor.transport as transport

    gen = torch.Generator().manual_seed(7)
    points = _cloud(3000, gen, torch.float32, device)
    dtypes = []
    original = power.power_cells

    def recorded(cell_points, *args, **kwargs):
        dtypes.append(cell_points.dtype)
        return original(cell_points, *args, **kwargs)

    monkeypatch.setattr(power, "power_cells", recorded)
    monkeypatch.setattr(transport, "ROUNDING_SHARE", 0.0)  # Newton to tol
    early = torchvor.power_weights(points, BOX, tol=1e-9)
    assert torch.float32 in dtypes and torch.float64 in dtypes
    monkeypatch.setattr(transport, "SINGLE_ERROR", math.inf)
    dtypes.clear()
    late = torchvor.power_weights(points, BOX, tol=1e-9)
    assert torch.float32 not in dtypes
    assert early.iterations == late.iterations and early.error <= 1.5 * late.error
    dtypes.clear()
    torchvor.power_weights(points.double(), BOX, tol=1e-9)
    assert set(dtypes) == {torch.float64}


def test_float32_weights_predict_their_rounding(device, gen, monkeypatch):
    """_float32_weights' prediction (the Jacobian times the rounding) is the
    error that rounding float64 weights to float32 adds, measured on the
    float64 cells of the rounded weights, and its shifted rounding errs no more
    than the plain one; where the rounding decides the error, float32 points'
    Newton stops early, warning of nothing."""
    import torchvor.power as power
    import torchvor.transport as transport

    n = 3000
    points = _cloud(n, gen, torch.float64, device)
    solved = torchvor.power_weights(points, BOX, tol=1e-11)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64, device=device)
    _cells, faces = power.power_cells(points, solved.weights, box, faces=True)
    jacobian = transport._Jacobian.of_faces(n, faces, points)
    target = torch.full((n,), 1.0 / n, dtype=torch.float64, device=device)
    measured = {}
    for shifts in (1, transport.ROUNDING_SHIFTS):
        monkeypatch.setattr(transport, "ROUNDING_SHIFTS", shifts)
        rounded, predicted = transport._float32_weights(jacobian, solved.weights, target)
        assert rounded.dtype == torch.float32
        cells = torchvor.voronoi(points, BOX, weights=rounded.double())
        measured[shifts] = float(((cells.volume - target).abs() / target).max())
        assert measured[shifts] > 100 * solved.error and abs(predicted - measured[shifts]) <= 0.2 * measured[shifts]
    assert measured[shifts] <= 1.2 * measured[1]
    single = points.float()
    monkeypatch.setattr(transport, "ROUNDING_SHARE", 0.0)  # Newton to tol
    full = torchvor.power_weights(single, BOX, tol=1e-9)
    monkeypatch.setattr(transport, "ROUNDING_SHARE", 100.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        stopped = torchvor.power_weights(single, BOX, tol=1e-9)
    # stopped at 100 roundings' error: at most 101 of them (two roundings' errors are within 1.5x)
    assert stopped.iterations < full.iterations and stopped.error <= 1.5 * 101 * full.error


def test_power_weights_warn_of_nothing(device, gen):
    """No notice of torch's (the sparse CSR Jacobian's beta status) reaches the caller."""
    points = _cloud(300, gen, torch.float64, device)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        result = torchvor.power_weights(points, BOX, tol=1e-8)
    assert result.error <= 1e-8


def test_jacobian_is_the_laplacian_of_the_faces(device, gen):
    """(J x)_i = sum over faces (j, i) of c_ij (x_i - x_j), repeated pairs included
    (a periodic cell can meet two images of one neighbour)."""
    from torchvor.transport import _Jacobian

    n, faces = 50, 400
    j = torch.randint(0, n, (faces,), generator=gen)
    i = torch.randint(0, n, (faces,), generator=gen)
    c = torch.rand(faces, generator=gen, dtype=torch.float64)
    x = torch.randn(n, generator=gen, dtype=torch.float64)
    expected = torch.zeros(n, dtype=torch.float64)
    for e in range(faces):
        expected[i[e]] += c[e] * (x[i[e]] - x[j[e]])
    jacobian = _Jacobian.of(n, torch.stack([j, i]).to(device), c.to(device))
    torch.testing.assert_close(jacobian.apply(x.to(device)).cpu(), expected, rtol=1e-12, atol=1e-12)


def test_jacobian_of_the_faces_is_the_graphs(device, gen):
    """The Jacobian from the cells' own faces (one sort of their keys and their
    reverses) is bit for bit the one from graph_of_faces' symmetric graph,
    faces listed by one side only included; a face listed three times sums its
    areas in another order (to rounding)."""
    from torchvor.power import PowerFaces, graph_of_faces, power_cells
    from torchvor.transport import _Jacobian

    n = 400
    points = _cloud(n, gen, torch.float64, device)
    box = torch.tensor([BOX], dtype=torch.float64, device=device)
    weights = _weights(n, 3.0, gen, torch.float64, device)
    _, faces = power_cells(points, weights, box, None, faces=True)

    def from_graph(f):
        edge_index, area, _centroid, _walls = graph_of_faces(n, f, torch.float64)
        j, i = edge_index
        return _Jacobian.of(n, edge_index, area / (2 * (points[i] - points[j]).norm(dim=1)))

    off = ~torch.eye(n, dtype=torch.bool, device=device)

    def assert_same(a, b, exact=True):
        """The same entries off the diagonal, bit for bit; the diagonals are row
        sums, whose order of addition the device's atomics choose."""
        dense_a, dense_b = a.matrix.to_dense(), b.matrix.to_dense()
        if exact:
            assert torch.equal(dense_a[off], dense_b[off]) and torch.equal(dense_a, dense_a.T)
        else:
            torch.testing.assert_close(dense_a[off], dense_b[off], rtol=1e-15, atol=0)
        assert torch.equal(dense_a.diagonal(), a.diagonal) and torch.equal(dense_b.diagonal(), b.diagonal)
        torch.testing.assert_close(a.diagonal, b.diagonal, rtol=1e-13, atol=0)

    jacobian = _Jacobian.of_faces(n, faces, points)
    assert_same(jacobian, from_graph(faces))
    x = torch.ones(n, dtype=torch.float64, device=device)  # the rows sum to zero
    assert float(jacobian.apply(x).abs().max()) <= 1e-12 * float(jacobian.diagonal.max())
    inner = torch.nonzero(faces.target >= 0).flatten()
    one_sided = PowerFaces(*(t[torch.cat([inner[1:], torch.nonzero(faces.target < 0).flatten()])] for t in faces))
    assert_same(_Jacobian.of_faces(n, one_sided, points), from_graph(one_sided))
    listed_twice = PowerFaces(*(torch.cat([t, t[inner[:5]]]) for t in faces))
    assert_same(_Jacobian.of_faces(n, listed_twice, points), from_graph(listed_twice), exact=False)


def test_conjugate_gradient_solves_the_laplacian(device, gen):
    """The CG's solution of J x = b (b of sum 0) meets its relative residual;
    a right-hand side of zeros gives zeros."""
    from torchvor.power import power_cells
    from torchvor.transport import _conjugate_gradient, _Jacobian

    n = 300
    points = _cloud(n, gen, torch.float64, device)
    box = torch.tensor([BOX], dtype=torch.float64, device=device)
    _, faces = power_cells(points, torch.zeros(n, dtype=torch.float64, device=device), box, None, faces=True)
    jacobian = _Jacobian.of_faces(n, faces, points)
    rhs = torch.randn(n, generator=gen, dtype=torch.float64).to(device)
    rhs = rhs - rhs.mean()
    for rtol in (1e-2, 1e-8):
        x = _conjugate_gradient(jacobian, rhs, rtol, 10 * n)
        assert float((jacobian.apply(x) - rhs).norm()) <= rtol * float(rhs.norm())
        assert abs(float(x.mean())) <= 1e-12 * float(x.abs().max())
    assert bool((_conjugate_gradient(jacobian, torch.zeros_like(rhs), 1e-8, 100) == 0).all())


def test_power_weights_sampled_trials_change_nothing(device, monkeypatch):
    """Trial steps tried first on a sample of the cells (far from the solution,
    where white noise's first steps are halved) give the weights, iterations
    and error of full evaluations alone, and spare some of those."""
    import torchvor.power as power
    import torchvor.transport as transport

    gen = torch.Generator().manual_seed(5)
    points = _cloud(3000, gen, torch.float64, device)
    calls = []
    original = power.power_cells

    def counted(*args, rows=None, **kwargs):
        calls.append(rows is None)
        return original(*args, rows=rows, **kwargs)

    monkeypatch.setattr(power, "power_cells", counted)
    results = {}
    for least in (10**9, 0):
        monkeypatch.setattr(transport, "SAMPLE_MIN_POINTS", least)
        calls.clear()
        results[least] = torchvor.power_weights(points, BOX, tol=1e-9), calls.count(True), calls.count(False)
    (plain, plain_full, plain_samples), (sampled, sampled_full, samples) = results[10**9], results[0]
    assert plain_samples == 0 and samples > 0 and sampled_full < plain_full
    # the same steps (the device's atomic sums round differently from call to call)
    assert sampled.iterations == plain.iterations and sampled.error <= 1e-9 and plain.error <= 1e-9
    scale = float(plain.weights.abs().max())
    torch.testing.assert_close(sampled.weights, plain.weights, rtol=0, atol=1e-9 * scale)
