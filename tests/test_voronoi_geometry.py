"""torchvor.voronoi on lattices (every cell known exactly) and on awkward
boxes and point sets: flat, offset and oversized boxes, nearly planar
points, close pairs, seeds on the box, a few points, exact duplicates.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

from torchvor import CellStatus, samples

from voronoi_checks import RTOL, UNIT, box_of, check_against_oracle, check_global, pick_cells, rand, run


# ------------------------------------------------------------------ lattices


def lattice_expectations(cells, points, edge, dtype, rtol):
    vol = cells.volume.cpu().double()
    cen = cells.centroid.cpu().double()
    m2 = cells.second_moment.cpu().double()
    p = points.cpu().double()
    a = np.asarray(edge, dtype=np.float64)
    volume = float(np.prod(a))
    moment = volume * float((a ** 2).sum()) / 12  # integral of |x - centre|^2 over a box
    assert (cells.status.cpu() == CellStatus.SUCCESS).all()
    err = (vol - volume).abs().max().item()
    assert err <= rtol * volume, f"lattice volumes off by {err:.3e} (cell volume {volume:.3e})"
    err = (cen - p).abs().max().item()
    assert err <= rtol * a.max(), f"lattice centroids off by {err:.3e} (cell size {a.max():.3e})"
    err = (m2 - moment).abs().max().item()
    assert err <= rtol * moment, f"lattice second moments off by {err:.3e} (expected {moment:.3e})"


@pytest.mark.parametrize("m", [3, 7, 10])
def test_lattice_exact(device, dtype, m, cells_impl):
    """samples.lattice(m): every cell is a cube of volume 1/m^3 centred on its point."""
    points = samples.lattice(m, dtype=dtype).to(device)
    cells = run(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    lattice_expectations(cells, points, [1 / m] * 3, dtype, {torch.float64: 1e-12, torch.float32: 1e-5}[dtype])


def test_lattice_cells_do_not_depend_on_the_grid(device, dtype, cells_impl):
    """Equally distant neighbours (every lattice cell has six) are clipped in
    the caller's row order, not the grid's: the same cells bit for bit
    whatever k sets the grid's density."""
    points = samples.lattice(12, dtype=dtype).to(device)
    first = run(points, UNIT, k=40)
    for k in (60, 100, None):
        again = run(points, UNIT, k=k)
        for name, a, b in zip(first._fields, first, again):
            assert torch.equal(a, b), (k, name)


def test_lattice_scaled_offset_float64(device, gen):
    """Lattice scaled by 1e-3 and moved to 1e4: relative to the cell size the
    inputs carry ~1e-8 rounding, so the cube volumes hold to ~1e-7 and the
    oracle (same rounded inputs) to 1e-10."""
    m = 6
    points = (samples.lattice(m) * 1e-3 + 1e4).to(device)
    box = ([1e4] * 3, [1e4 + 1e-3] * 3)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], torch.float64)
    lattice_expectations(cells, points, [1e-3 / m] * 3, torch.float64, 1e-7)
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), 1e-10)


def test_lattice_flat_box(device, dtype, cells_impl):
    """Lattice squeezed into a 1 x 1 x 0.001 box: flat cells of 1/m x 1/m x 0.001/m."""
    m = 6
    scale = torch.tensor([1.0, 1.0, 1e-3], dtype=torch.float64)
    points = (samples.lattice(m) * scale).to(dtype).to(device)
    box = torch.tensor([[0.0, 0.0, 0.0], [1.0, 1.0, 1e-3]], dtype=dtype, device=device)
    cells = run(points, box)
    check_global(cells, points, [box_of(points, box)], dtype)
    lattice_expectations(cells, points, [1 / m, 1 / m, 1e-3 / m], dtype,
                         {torch.float64: 1e-10, torch.float32: 1e-4}[dtype])


def test_lattice_single_layer(device, dtype):
    """One layer of an m x m grid in a cube: square columns spanning the box."""
    m = 8
    axis = (torch.arange(m, dtype=torch.float64) + 0.5) / m
    y, x = torch.meshgrid(axis, axis, indexing="ij")
    points = torch.stack([x.flatten(), y.flatten(), torch.full((m * m,), 0.5, dtype=torch.float64)], 1)
    points = points.to(dtype).to(device)
    cells = run(points, UNIT)
    lattice_expectations(cells, points, [1 / m, 1 / m, 1.0], dtype,
                         {torch.float64: 1e-12, torch.float32: 1e-5}[dtype])


# ---------------------------------------------- awkward boxes and point sets


def test_flat_box_random(device, dtype, gen, cells_impl):
    lo, hi = [0.0, 0.0, 0.0], [1.0, 1.0, 1e-3]
    points = rand(600, gen, dtype, device, lo, hi)
    box = (lo, hi)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 50, gen, *lohi), RTOL[dtype])


def test_nearly_planar_points(device, gen):
    """z = 0.5 + 1e-9 * noise: every cell is a column through the unit cube."""
    points = rand(400, gen, torch.float64, device)
    points[:, 2] = 0.5 + 1e-9 * (2 * torch.rand(400, generator=gen, dtype=torch.float64) - 1).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], torch.float64)
    check_against_oracle(cells, points, lohi, pick_cells(points, 50, gen, *lohi), 1e-10)


def test_close_pairs(device, dtype, gen, cells_impl):
    """Points 1e-7 apart (float64) or a few ulps apart (float32)."""
    base = rand(300, gen, torch.float64, "cpu", 0.1, 0.9)
    direction = torch.nn.functional.normalize(torch.randn(20, 3, generator=gen, dtype=torch.float64), dim=1)
    gap = 1e-7 if dtype == torch.float64 else 3e-6
    partners = base[:20] + gap * direction
    points = torch.cat([base, partners]).to(dtype)
    assert ((points[:20] - points[300:]).abs().sum(1) > 0).all()  # not rounded together
    points = points.to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    subset = np.concatenate([np.arange(20), np.arange(300, 320), np.arange(20, 300, 15)])
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])


def test_points_on_box_boundary(device, dtype, gen):
    """Seeds on faces, edges and corners of the box."""
    points = rand(300, gen, dtype, device)
    points[:6, 0] = 0.0
    points[6:12, 1] = 1.0
    points[12:16, :2] = 0.0
    points[16] = torch.tensor([1.0, 1.0, 1.0])
    points[17] = torch.tensor([0.0, 1.0, 0.0])
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, np.arange(40), RTOL[dtype])


@pytest.mark.parametrize("n", [1, 2, 5])
def test_few_points(device, dtype, gen, n, cells_impl):
    lo, hi = [-1.0, 0.0, 2.0], [1.0, 0.5, 5.0]
    points = rand(n, gen, dtype, device, lo, hi)
    cells = run(points, (lo, hi))
    lohi = box_of(points, (lo, hi))
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, range(n), RTOL[dtype])
    if n == 1:  # the whole box
        size = np.array(hi) - np.array(lo)
        assert cells.volume.item() == pytest.approx(float(np.prod(size)), rel=RTOL[dtype], abs=0)
        # a sum of signed tetrahedra: a few ulps of the coordinates (float32
        # gives 8 ulps at z = 3.5, i.e. 1.9e-6, with TORCHVOR_TEST_SEED=3952057584)
        scale = float(np.abs(np.array(lo + hi)).max())
        torch.testing.assert_close(cells.centroid[0].cpu().double(),
                                   torch.tensor((np.array(lo) + np.array(hi)) / 2), rtol=0,
                                   atol=32 * torch.finfo(dtype).eps * scale)
        assert cells.neighbors_needed.item() == 0


def test_two_points_halves(device, dtype):
    points = torch.tensor([[0.25, 0.5, 0.5], [0.75, 0.5, 0.5]], dtype=dtype, device=device)
    cells = run(points, UNIT)
    torch.testing.assert_close(cells.volume, torch.full((2,), 0.5, dtype=dtype, device=device))
    torch.testing.assert_close(cells.centroid, points)
    expected = 0.5 * (0.25 + 1 + 1) / 12  # box 0.5 x 1 x 1 about its centre
    torch.testing.assert_close(cells.second_moment, torch.full((2,), expected, dtype=dtype, device=device))


@pytest.mark.parametrize("box", [([-1.0, 0.0, 0.2], [2.0, 1.5, 0.7]), ([-100.0] * 3, [100.0] * 3)],
                         ids=["near", "huge"])
def test_explicit_larger_box(device, dtype, gen, box, vertex_balls):
    """A box well beyond the points: hull cells reach the box and need (almost) all
    points. In the huge box they are cones ~100 long whose faces come from points
    ~0.03 apart: float32 gets the conditioning allowance of test_tight_clusters
    (on CUDA up to 4e-4 relative on a 6.3-volume cone, ~2 eps R A)."""
    points = rand(500, gen, dtype, device, 0.3, 0.6)
    cells = run(points, box)
    lohi = box_of(points, box)
    check_global(cells, points, [lohi], dtype)
    huge32 = dtype == torch.float32 and box[1][0] > 10
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype],
                         conditioning=256.0 if huge32 else 0.0)


def test_quantised_offset_float32(device, gen):
    """float32 points at 1e4 with spread 0.01: coordinates snap to ~10 values per
    axis (ulp 1e-3), so the set is a degenerate lattice full of exact duplicates."""
    points = (1e4 + 0.01 * torch.rand(2000, 3, generator=gen, dtype=torch.float64)).float().to(device)
    assert len(points.unique(dim=0)) < 1500
    cells = run(points)
    lohi = box_of(points, None)
    check_global(cells, points, [lohi], torch.float32)
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[torch.float32])


def test_large_offset_box(device, dtype, gen):
    """Points and box near 1e4 (relative coordinates keep the precision)."""
    lo, hi = [1e4, 1e4, 1e4], [1e4 + 1, 1e4 + 1, 1e4 + 1]
    points = rand(500, gen, dtype, device, lo, hi)
    for box in ((lo, hi), None):
        cells = run(points, box)
        lohi = box_of(points, box)
        check_global(cells, points, [lohi], dtype)
        check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype])


# ---------------------------------------------------------- exact duplicates


def test_duplicates(device, dtype, gen, cells_impl, vertex_balls):
    """Exact copies: the lowest index keeps the whole cell; later copies are
    DUPLICATE with volume 0, centroid = the point and second moment 0."""
    base = rand(200, gen, dtype, "cpu")
    copies = torch.randint(0, 200, (100,), generator=gen)
    points = torch.cat([base, base[copies], base[copies[:30]]])
    perm = torch.randperm(len(points), generator=gen)
    points = points[perm].to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    p = points.cpu()
    first = {}
    for i, row in enumerate(map(tuple, p.tolist())):
        first.setdefault(row, i)
    expected_dup = torch.tensor([first[tuple(r)] != i for i, r in enumerate(p.tolist())])
    status = cells.status.cpu()
    assert torch.equal(status == CellStatus.DUPLICATE, expected_dup)
    assert (status[~expected_dup] == CellStatus.SUCCESS).all()
    owners = sorted(set(first.values()))
    subset = np.concatenate([np.array(owners)[:: max(1, len(owners) // 40)],
                             torch.nonzero(expected_dup).flatten().numpy()[:20]])
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])


def test_points_copied_thousands_of_times(device, dtype, gen, cells_impl):
    """30 points, each copied up to ~1000 times in random order, in two
    clouds of a batch that share them (copies across clouds are not
    duplicates): in each cloud the lowest index of each point keeps its cell,
    which is right; the others are DUPLICATE. Without setting the copies
    aside, each kept cell's neighbour lists fill with copies of one point."""
    base = rand(30, gen, dtype, "cpu")
    pick = torch.randint(0, 30, (6000,), generator=gen)
    pick[:30] = torch.arange(30)
    cloud = base[pick[torch.randperm(6000, generator=gen)]]
    points = torch.cat([cloud, cloud[torch.randperm(6000, generator=gen)]]).to(device)
    batch = torch.arange(2).repeat_interleave(6000).to(device)
    cells = run(points, UNIT, batch=batch)
    p = points.cpu()
    for b in range(2):
        rows = range(6000 * b, 6000 * (b + 1))
        first = {}
        for i in rows:
            first.setdefault(tuple(p[i].tolist()), i)
        owners = torch.tensor(sorted(first.values()))
        status = cells.status.cpu()[6000 * b: 6000 * (b + 1)]
        expected = torch.full((6000,), int(CellStatus.DUPLICATE), dtype=torch.int8)
        expected[owners - 6000 * b] = int(CellStatus.SUCCESS)
        assert torch.equal(status, expected)
        assert cells.volume[owners].sum().item() == pytest.approx(1.0, rel=RTOL[dtype])
        sub = p[owners].to(device)
        check_against_oracle(run(sub, UNIT), sub, box_of(sub, UNIT), range(len(owners)), RTOL[dtype])
        np.testing.assert_array_equal(cells.volume[owners].cpu().numpy(), run(sub, UNIT).volume.cpu().numpy())
    copies = cells.status == CellStatus.DUPLICATE
    assert (cells.volume[copies] == 0).all() and torch.equal(cells.centroid[copies], points[copies])
    assert (cells.neighbors_needed[copies] == 1).all()


def test_duplicates_many(device, dtype, gen):
    """Many exact copies (each cloud: 300 points, half of them copied once, a
    sixth twice): global identities and no NaN in SUCCESS cells. A cell whose
    neighbours include two copies of one point is cut twice by the same plane."""
    for _ in range(12):
        base = rand(300, gen, dtype, "cpu")
        points = torch.cat([base, base[:150], base[:50]]).to(device)
        cells = run(points, UNIT)
        check_global(cells, points, [box_of(points, UNIT)], dtype)


@pytest.mark.parametrize("dtype_", [torch.float32, torch.float64], ids=["float32", "float64"])
def test_duplicate_neighbours_regression(device, dtype_):
    """A minimal case of test_duplicates: points 0 and 3 are exact copies, so
    cell 1 is clipped twice by the same bisector. In float32 that must not
    leave cell 1 a NaN volume with status SUCCESS (silent poison)."""
    points = torch.tensor([
        [0.4551128149032593, 0.1561974287033081, 0.6241004467010498],
        [0.7751314640045166, 0.5810326933860779, 0.3472025990486145],
        [0.556449830532074, 0.1850108951330185, 0.41748368740081787],
        [0.4551128149032593, 0.1561974287033081, 0.6241004467010498],
        [0.7269694209098816, 0.7763248085975647, 0.6628854274749756]], dtype=torch.float32)
    points = points.to(dtype_).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype_)
    check_against_oracle(cells, points, lohi, range(5), RTOL[dtype_])


def test_all_points_identical(device, dtype, cells_impl):
    points = torch.full((5, 3), 0.25, dtype=dtype, device=device)
    cells = run(points, UNIT)
    assert cells.status.tolist() == [CellStatus.SUCCESS] + [CellStatus.DUPLICATE] * 4
    assert cells.volume[0].item() == pytest.approx(1.0)
    assert (cells.volume[1:] == 0).all()
