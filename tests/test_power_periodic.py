"""Power diagrams in periodic boxes: torchvor.voronoi / voronoi_graph /
voronoi_laplacian / cvt_energy with weights and periodic, power_weights,
power_lloyd and lloyd(volumes=...) with periodic, against the half-space
oracle over the points' images with power bisectors
(oracles.periodic_cell_oracle with weights)."""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor
from torchvor import CellStatus
from oracles import periodic_cell_oracle

# a box at the origin (images exact: one-sided padding) and an offset one (two-sided)
BOXES = {"origin": ((0.0, 0.0, 0.0), (1.0, 1.5, 1.0)), "offset": ((0.3, -1.1, 2.0), (1.3, 0.4, 3.0))}
AXES = [(True, True, True), (True, False, True), (False, True, False)]


def _cloud(n, box, gen, dtype, device):
    lo, hi = (torch.tensor(c, dtype=torch.float64) for c in box)
    return (lo + torch.rand(n, 3, generator=gen, dtype=torch.float64) * (hi - lo)).to(dtype=dtype, device=device)


def _weights(n, box, spread, gen, dtype, device):
    """Weights uniform in [0, spread * s^2], s the mean spacing of n points in `box`."""
    volume = float(np.prod(np.subtract(box[1], box[0])))
    scale = spread * (volume / n) ** (2.0 / 3.0)
    return (torch.rand(n, generator=gen, dtype=torch.float64) * scale).to(dtype=dtype, device=device)


def _box_tensor(box, dtype, device):
    return torch.tensor(box, dtype=dtype, device=device)


@pytest.mark.parametrize("where", sorted(BOXES))
@pytest.mark.parametrize("axes", AXES, ids=["xyz", "xz", "y"])
@pytest.mark.parametrize("spread", [0.5, 3.0])
def test_periodic_power_cells_match_the_oracle(device, dtype, gen, where, axes, spread):
    """Every cell of 150 points against the oracle over the images; spread 3
    empties many cells (whose images bound nothing)."""
    n, box = 150, BOXES[where]
    points = _cloud(n, box, gen, dtype, device)
    weights = _weights(n, box, spread, gen, dtype, device)
    box_tensor = _box_tensor(box, dtype, device)
    cells = torchvor.voronoi(points, box_tensor, periodic=axes, weights=weights, k=8)
    status = cells.status.cpu().numpy()
    assert set(status.tolist()) <= {int(CellStatus.SUCCESS), int(CellStatus.EMPTY)}
    volume = cells.volume.double().cpu().numpy()
    lo, hi = box_tensor.double().cpu().numpy()  # the box as given (float32: rounded), whose edges are the periods
    rtol = 1e-9 if dtype == torch.float64 else 1e-5
    assert abs(volume.sum() - np.prod(hi - lo)) <= rtol * np.prod(hi - lo)
    pts, w = points.double().cpu().numpy(), weights.double().cpu().numpy()
    centroid = cells.centroid.double().cpu().numpy()
    for i in range(n):
        oracle = periodic_cell_oracle(pts, i, (lo, hi), axes, weights=w)
        if oracle.empty or oracle.volume < 1e-13:
            assert status[i] == CellStatus.EMPTY or volume[i] < 1e-12, (i, status[i], volume[i])
            if status[i] == CellStatus.EMPTY:
                assert volume[i] == 0
                np.testing.assert_array_equal(centroid[i], pts[i])
            continue
        assert status[i] == CellStatus.SUCCESS, (i, status[i])
        assert abs(volume[i] - oracle.volume) <= rtol * max(oracle.volume, 1e-6), (i, volume[i], oracle.volume)
        # the centroid next to the point (the oracle's too: the images are around the box)
        assert np.abs(centroid[i] - oracle.centroid).max() <= (1e-8 if dtype == torch.float64 else 1e-5), i


def test_periodic_power_faces_match_the_oracle(device, gen):
    n, box, axes = 80, BOXES["offset"], (True, True, False)
    points = _cloud(n, box, gen, torch.float64, device)
    weights = _weights(n, box, 1.0, gen, torch.float64, device)
    graph = torchvor.voronoi_graph(points, _box_tensor(box, torch.float64, device), periodic=axes, weights=weights)
    lo, hi = (np.array(c) for c in box)
    j_all, i_all = graph.edge_index.cpu().numpy()
    shift, area = graph.shift.cpu().numpy(), graph.area.cpu().numpy()
    wall = graph.wall_area.cpu().numpy()
    assert np.all(wall[:, :4] == 0)  # no wall faces on the periodic axes x, y
    pts, w = points.cpu().numpy(), weights.cpu().numpy()
    for i in range(0, n, 7):
        oracle = periodic_cell_oracle(pts, i, (lo, hi), axes, weights=w)
        expected = {key: value[0] for key, value in (oracle.faces or {}).items()
                    if key[0] >= 0 and value[0] > 1e-12}
        mine = {(int(j), tuple(int(v) for v in s)): float(a)
                for j, s, a, c in zip(j_all, shift, area, i_all) if c == i}
        assert set(mine) == set(expected), i
        for key, value in expected.items():
            assert abs(mine[key] - value) <= 1e-9 * max(value, 1e-3), (i, key)
    laplacian = torchvor.voronoi_laplacian(points, _box_tensor(box, torch.float64, device), periodic=axes,
                                           weights=weights).to_dense()
    torch.testing.assert_close(laplacian.sum(1), torch.zeros(n, dtype=torch.float64, device=device), atol=1e-12,
                               rtol=0)
    torch.testing.assert_close(laplacian, laplacian.T)


def test_periodic_gradients_in_the_weights(device):
    n, box = 40, BOXES["offset"]
    gen = torch.Generator().manual_seed(3)
    points = _cloud(n, box, gen, torch.float64, device)
    weights = _weights(n, box, 0.5, gen, torch.float64, device).requires_grad_()
    boxt = _box_tensor(box, torch.float64, device)

    def outputs(w):
        cells = torchvor.voronoi(points, boxt, periodic=(True, False, True), weights=w)
        return cells.volume, cells.centroid, cells.second_moment

    nondet = 1e-12 if device.type == "cuda" else 0.0
    assert torch.autograd.gradcheck(outputs, (weights,), eps=1e-7, atol=1e-5, rtol=1e-4, nondet_tol=nondet)
    energy = torchvor.cvt_energy(points, boxt, periodic=True, weights=weights)
    cells = torchvor.voronoi(points, boxt, periodic=True, weights=weights.detach())
    torch.testing.assert_close(energy.detach(), cells.second_moment.sum())
    assert torch.autograd.gradcheck(lambda w: torchvor.cvt_energy(points, boxt, periodic=True, weights=w),
                                    (weights,), eps=1e-7, atol=1e-6, rtol=1e-4, nondet_tol=nondet)
    with pytest.raises(RuntimeError, match="points"):
        torchvor.voronoi(points.clone().requires_grad_(), boxt, periodic=True, weights=weights).volume.sum().backward()


def test_cvt_energy_with_weights(device, gen):
    points = _cloud(100, BOXES["origin"], gen, torch.float64, device)
    boxt = _box_tensor(BOXES["origin"], torch.float64, device)
    zero = torch.zeros(100, dtype=torch.float64, device=device)
    torch.testing.assert_close(torchvor.cvt_energy(points, boxt, weights=zero), torchvor.cvt_energy(points, boxt))
    torch.testing.assert_close(torchvor.cvt_energy(points, boxt, weights=zero, periodic=True),
                               torchvor.cvt_energy(points, boxt, periodic=True))


def test_few_points_in_a_large_periodic_box(device, dtype):
    """Clouds smaller than the neighbourhood a cell needs: exact cells from the images."""
    box = ((0.0, 0.0, 0.0), (2.0, 3.0, 5.0))
    points = torch.tensor([[0.1, 0.2, 0.3], [1.5, 2.5, 4.0], [1.0, 0.1, 2.0]], dtype=dtype, device=device)
    weights = torch.tensor([0.0, 0.4, -0.2], dtype=dtype, device=device)
    cells = torchvor.voronoi(points, _box_tensor(box, dtype, device), periodic=True, weights=weights)
    lo, hi = np.zeros(3), np.array(box[1])
    for i in range(3):
        oracle = periodic_cell_oracle(points.double().cpu().numpy(), i, (lo, hi), (True,) * 3,
                                      weights=weights.double().cpu().numpy())
        assert abs(float(cells.volume[i]) - oracle.volume) <= 1e-5 * 30
    assert abs(float(cells.volume.double().sum()) - 30.0) <= (1e-9 if dtype == torch.float64 else 1e-6) * 30
    single = torchvor.voronoi(points[:1], _box_tensor(box, dtype, device), periodic=True, weights=weights[:1])
    assert float(single.volume[0]) == pytest.approx(30.0, rel=1e-6)


@pytest.mark.parametrize("varying", [False, True])
def test_periodic_power_weights(device, gen, varying):
    n, box = 400, BOXES["offset"]
    points = _cloud(n, box, gen, torch.float64, device)
    boxt = _box_tensor(box, torch.float64, device)
    volumes = (1 + 2 * torch.rand(n, generator=gen, dtype=torch.float64)).to(device) if varying else None
    result = torchvor.power_weights(points, boxt, volumes=volumes, periodic=(True, True, False), tol=1e-9)
    assert result.error <= 1e-9
    target = torch.full((n,), 1.5 / n, dtype=torch.float64, device=device) if volumes is None else \
        volumes * (1.5 / float(volumes.sum()))
    cells = torchvor.voronoi(points, boxt, periodic=(True, True, False), weights=result.weights)
    assert float(((cells.volume - target).abs() / target).max()) <= 1e-9
    assert abs(float(result.weights.mean())) <= 1e-12


def test_periodic_power_weights_float32_and_errors(device, gen):
    box = BOXES["offset"]
    points = _cloud(300, box, gen, torch.float32, device)
    boxt = _box_tensor(box, torch.float32, device)
    result = torchvor.power_weights(points, boxt, periodic=True, tol=1e-6)
    assert result.weights.dtype == torch.float32 and result.error <= 2e-5
    with pytest.raises(ValueError, match="box"):
        torchvor.power_weights(points, None, periodic=True)
    # points outside the box along a periodic axis are their images inside
    moved = points.clone()
    moved[:, 0] += 1.0  # one period along x
    again = torchvor.power_weights(moved, boxt, periodic=True, tol=1e-6)
    assert again.error <= 2e-5


def test_periodic_power_lloyd(device, gen):
    n, box = 200, BOXES["offset"]
    points = _cloud(n, box, gen, torch.float64, device)
    boxt = _box_tensor(box, torch.float64, device)
    volumes = (1 + torch.rand(n, generator=gen, dtype=torch.float64)).to(device)
    moved, weights = torchvor.power_lloyd(points, boxt, 3, volumes=volumes, periodic=True)
    lo, hi = boxt[0], boxt[1]
    assert bool(((moved >= lo) & (moved < hi)).all())
    assert weights.shape == (n,)
    via_lloyd = torchvor.lloyd(points, boxt, 3, volumes=volumes, periodic=True)
    torch.testing.assert_close(via_lloyd, moved, rtol=0, atol=0 if device.type == "cpu" else 1e-12)
    cells = torchvor.voronoi(moved, boxt, periodic=True)
    plain = torchvor.voronoi(points, boxt, periodic=True)
    # relaxation evens the cells out: the energy falls
    assert float(torchvor.cvt_energy(moved, boxt, periodic=True)) < float(torchvor.cvt_energy(points, boxt,
                                                                                            periodic=True))
    assert float(cells.volume.sum()) == pytest.approx(float(plain.volume.sum()), rel=1e-12)
