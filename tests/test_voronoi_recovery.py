"""The passes after the first and what they must not change: retries with
more neighbours (small k), the speculative first retry, cells finished by
the empty balls of their vertices, chunking under a memory budget, a cell
that no pass writes, and the tuning variables (pilot quantile, grid
density) that change no result.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor
from torchvor import samples

from voronoi_checks import (
    RTOL, UNIT, VORONOI_FIELDS, assert_same_integrals, box_of, check_against_oracle, check_global, pick_cells, rand,
    run,
)


# ------------------------------------------------------ retries and chunking


def test_unwritten_cell_reads_not_computed(device, dtype, monkeypatch):
    """Only the statuses are poisoned before the passes; a cell that no pass
    writes (simulated: the first pass's result for one grid position is
    dropped and its record zeroed) must come out NOT_COMPUTED with NaN
    outputs and 0 neighbours, not as the zeroed record. On a jittered lattice
    every cell succeeds in the first pass, so no retry recomputes it."""
    gen = torch.Generator().manual_seed(0)
    axis = (torch.arange(4, dtype=torch.float64) + 0.5) / 4
    lattice = torch.stack(torch.meshgrid(axis, axis, axis, indexing="ij"), -1).reshape(-1, 3)
    points = (lattice + 0.05 * (torch.rand(lattice.shape, generator=gen, dtype=torch.float64) - 0.5) / 4)
    points = points.to(dtype).to(device)
    monkeypatch.setenv("TORCHVOR_TEST_UNWRITTEN_CELL", "5")
    cells = torchvor.voronoi(points, UNIT, k=26, on_failure="flag")
    not_computed = cells.status == int(torchvor.CellStatus.NOT_COMPUTED)
    assert int(not_computed.sum()) == 1
    assert (cells.status[~not_computed] == int(torchvor.CellStatus.SUCCESS)).all()
    row = int(not_computed.nonzero()[0, 0])
    assert torch.isnan(cells.volume[row]) and torch.isnan(cells.centroid[row]).all()
    assert torch.isnan(cells.second_moment[row]) and int(cells.neighbors_needed[row]) == 0
    assert torch.isfinite(cells.volume[~not_computed]).all()
    # the other cells are those of a run without the hook
    monkeypatch.delenv("TORCHVOR_TEST_UNWRITTEN_CELL")
    reference = torchvor.voronoi(points, UNIT, k=26, on_failure="flag")
    torch.testing.assert_close(cells.volume[~not_computed], reference.volume[~not_computed], rtol=0, atol=0)
    monkeypatch.setenv("TORCHVOR_TEST_UNWRITTEN_CELL", "5")
    with pytest.raises(RuntimeError, match=r"1 cell\(s\) could not be computed \(NOT_COMPUTED\)"):
        torchvor.voronoi(points, UNIT, k=26, on_failure="raise")


def test_small_k_recovery(device, dtype, gen, cells_impl, vertex_balls):
    """k=4 is far too few for any cell: the retry passes must give the exact cells."""
    points = rand(800, gen, dtype, device)
    cells = run(points, UNIT, k=4)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    assert (cells.neighbors_needed > 4).any()
    check_against_oracle(cells, points, lohi, pick_cells(points, 40, gen, *lohi), RTOL[dtype])
    ref = run(points, UNIT)
    # same cells as with the default k (integrals agree to rounding)
    torch.testing.assert_close(cells.volume, ref.volume, rtol=RTOL[dtype], atol=0)
    assert torch.equal(cells.status, ref.status)


@pytest.mark.parametrize("capacity", ["0", "16", "default"])
def test_speculative_retry_changes_no_cell(monkeypatch, device, dtype, gen, cells_impl, capacity):
    """The first retry runs before the host reads how many cells failed, on
    the device's list of them (ops::speculative_retry), if they fit its
    capacity (TORCHVOR_SPECULATIVE_CELLS: 16384 by default, 0 never). When
    the first pass's cells ask only for more neighbours, as here (k=10, no
    cell near 32 planes), that is the retry the host would have run: the
    outputs are bitwise those without it, whether it ran (the default: every
    failed cell fits) or ran no cell at all (they overflow 16)."""
    points = rand(3000, gen, dtype, device)
    k = 10
    monkeypatch.setenv("TORCHVOR_SPECULATIVE_CELLS", "0")
    plain = run(points, UNIT, k=k)
    failed_first = int((plain.neighbors_needed > k).sum())  # the cells that needed more than the first pass had
    assert 16 < failed_first <= 16384
    if capacity == "default":
        monkeypatch.delenv("TORCHVOR_SPECULATIVE_CELLS")
    else:
        monkeypatch.setenv("TORCHVOR_SPECULATIVE_CELLS", capacity)
    cells = run(points, UNIT, k=k)
    for name, got, expected in zip(VORONOI_FIELDS, cells, plain):
        assert torch.equal(got, expected), name
    check_global(cells, points, [box_of(points, UNIT)], dtype)


def test_clusters_with_voids(monkeypatch, device, dtype, seed, gen):
    """Dense clusters with empty space between them: the cells at a cluster's
    edge reach far into the void, and the radius of security would ask for
    every point within twice their farthest vertex, whole clusters. Past 256
    neighbours a retry finishes them by the empty balls of their vertices
    instead (core::finish_by_vertex_balls): the exact cells, the largest ones
    (in the voids) checked against the oracle, and the same cells, up to
    rounding, as asking for neighbours until the radius of security holds."""
    points = samples.clustered(3000, clusters=20, spread=0.02, seed=seed, dtype=torch.float64).to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    largest = torch.argsort(cells.volume.cpu(), descending=True)[:15].numpy()
    subset = np.unique(np.concatenate([largest, pick_cells(points, 25, gen, *lohi)]))
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", str(10 ** 9))
    by_radius = run(points, UNIT)
    assert int(by_radius.neighbors_needed.max()) > 1000  # what the vertex balls spared
    assert_same_integrals(cells, by_radius, dtype)


def wall_layer(gen, inner=2000, on_wall=20000, close=50):
    """Sparse points in the unit cube, a dense layer of points on its wall z = 0
    (as in a cloud clamped into its box) and points just above that layer, whose
    cells reach down to it and have hundreds of faces."""
    points = torch.rand(inner + on_wall + close, 3, generator=gen, dtype=torch.float64)
    points[inner:inner + on_wall, 2] = 0.0
    points[inner + on_wall:, 2] = 10 ** (-4 * torch.rand(close, generator=gen, dtype=torch.float64) - 1)
    return points


def test_cells_beside_a_dense_wall_layer(device, dtype, gen):
    """Cells with more faces than the device's largest tier holds are finished on
    the host at larger tiers: every cell computed, the many-faced ones exact."""
    points = wall_layer(gen).to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    many_faced = torch.argsort(cells.neighbors_needed.cpu(), descending=True)[:12].numpy()
    subset = np.unique(np.concatenate([many_faced, np.arange(points.shape[0] - 12, points.shape[0])]))
    check_against_oracle(cells, points, lohi, subset, RTOL[dtype])


@pytest.mark.parametrize("most", ["1", "8", "0", "-3", "8x"])
def test_vertex_balls_k_changes_no_cell(monkeypatch, device, dtype, gen, most):
    """TORCHVOR_VERTEX_BALLS_K sets the most neighbours a retry asks for
    before it finishes its cells by their vertices' balls (values that are
    not an integer >= 1 keep the default, 256). Either way the cells are
    exact: the same statuses and integrals up to rounding (the planes come
    in another order); only `neighbors_needed` counts other work."""
    points = rand(4000, gen, dtype, device)
    default = run(points, UNIT, k=6)
    monkeypatch.setenv("TORCHVOR_VERTEX_BALLS_K", most)
    cells = run(points, UNIT, k=6)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_same_integrals(cells, default, dtype)
    if most in ("1", "8"):
        assert not torch.equal(cells.neighbors_needed, default.neighbors_needed)


@pytest.mark.parametrize("k", [1, 2, 10000])
def test_tiny_k(device, gen, k):
    points = rand(300, gen, torch.float64, device)
    cells = run(points, UNIT, k=k)
    check_global(cells, points, [box_of(points, UNIT)], torch.float64)


def test_tiny_memory_budget(device, dtype, gen, cells_impl):
    """memory_budget=1 forces the smallest chunks (at most 1024 cells): identical results."""
    points = rand(2600, gen, dtype, device)
    ref = run(points, UNIT)
    cells = run(points, UNIT, memory_budget=1)
    for a, b in zip(cells, ref):
        assert torch.equal(a, b)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, pick_cells(points, 30, gen, *lohi), RTOL[dtype])
    small_k = run(points, UNIT, memory_budget=1, k=4)
    torch.testing.assert_close(small_k.volume, ref.volume, rtol=RTOL[dtype], atol=0)


def test_deterministic(device, dtype, seed):
    points = samples.clustered(3000, seed=seed, dtype=dtype).to(device)
    a, b = run(points, UNIT), run(points, UNIT)
    for x, y in zip(a, b):
        assert torch.equal(x, y)


# ------------------------------------ tuning variables that change no result


def assert_cells_unchanged(cells, default_cells, dtype, same_passes=True):
    """The same statuses; in float64 the same neighbour counts and integrals,
    bit for bit. In float32 the integrals agree up to rounding: equally far
    neighbours may be clipped in another order, and with
    `same_passes=False` (another first pass's k) a cell may end in another
    pass, as in assert_same_cloud: a thread cell of the first tier (vertices
    held to 18 mantissa bits, CompactTriangles) in one run and a retry of a
    higher tier in the other. Its neighbour count may then move by one (the
    radius of security comes from the vertices). Such differences are rare
    and small: float32 integrals are held to 1e-5 relative, the second
    moment (whose terms cancel the most) to 5e-5."""
    assert torch.equal(default_cells.status, cells.status), "status"
    if dtype == torch.float32 and not same_passes:
        assert int((default_cells.neighbors_needed - cells.neighbors_needed).abs().max()) <= 1, "neighbors_needed"
    else:
        assert torch.equal(default_cells.neighbors_needed, cells.neighbors_needed), "neighbors_needed"
    for name, rtol in (("volume", 1e-5), ("centroid", 1e-5), ("second_moment", 5e-5)):
        if dtype == torch.float64:
            assert torch.equal(getattr(default_cells, name), getattr(cells, name)), name
        else:
            torch.testing.assert_close(getattr(cells, name), getattr(default_cells, name), rtol=rtol, atol=0)


@pytest.mark.parametrize("scale", ["0.3", "3"])
def test_grid_density_changes_no_result(monkeypatch, device, dtype, gen, scale):
    """TORCHVOR_POINTS_PER_CELL_SCALE scales the points per grid cell of the
    kNN searches: another grid finds the same neighbours (ties go to the
    lower index), so the kNN is equal to the default's, bit for bit, and so
    are the cells in float64. In float32, two neighbours of a cell can be
    exactly equally far (one cell in 5000 with some seeds, e.g.
    TORCHVOR_TEST_SEED=1800692895); voronoi's kNN numbers points by their
    grid position, so such a pair is clipped in an order that depends on the
    grid: the same cell, its sums rounded in another order."""
    points = rand(5000, gen, dtype, device)
    default_cells = torchvor.voronoi(points, UNIT, k=24)
    default_knn = torchvor.knn(points, 16)
    monkeypatch.setenv("TORCHVOR_POINTS_PER_CELL_SCALE", scale)
    cells = torchvor.voronoi(points, UNIT, k=24)
    knn = torchvor.knn(points, 16)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_cells_unchanged(cells, default_cells, dtype)
    assert torch.equal(default_knn.idx, knn.idx)
    assert torch.equal(default_knn.dist2, knn.dist2)


@pytest.mark.parametrize("quantile", ["0.5", "1", "2", "nonsense"])
def test_pilot_quantile_changes_no_result(monkeypatch, device, dtype, gen, quantile):
    """TORCHVOR_PILOT_QUANTILE sets the share of the pilot's cells that the
    default first-pass k covers (0.98; values outside (0, 1] keep it).
    Another k retries other cells, but each cell stops at the same
    neighbour: the same cells, bit for bit in float64. In float32 the
    grid follows k, and equally far neighbours may be clipped in another
    order, as in test_grid_density_changes_no_result; a cell may also end in
    another pass, whose vertices round otherwise, and count one neighbour
    more or fewer (e.g. TORCHVOR_TEST_SEED=2526752964 with 0.5)."""
    points = rand(5000, gen, dtype, device)
    default_cells = torchvor.voronoi(points, UNIT)
    monkeypatch.setenv("TORCHVOR_PILOT_QUANTILE", quantile)
    cells = torchvor.voronoi(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    assert_cells_unchanged(cells, default_cells, dtype, same_passes=False)


def test_a_cell_with_thousands_of_faces(monkeypatch, device, dtype, gen):
    """A point above a dense layer of points on a wall faces every point of
    the layer, more faces than any fixed tier holds: its cell is finished on the
    host without bounds (core::UnboundedCell), exact, as are the layer's."""
    on_wall = 20000
    points = torch.rand(on_wall + 1, 3, generator=gen, dtype=torch.float64)
    points[:on_wall, 2] *= 1e-3
    points[on_wall] = torch.tensor([0.5, 0.5, 0.5], dtype=torch.float64)
    points = points.to(dtype).to(device)
    cells = run(points, UNIT)
    lohi = box_of(points, UNIT)
    check_global(cells, points, [lohi], dtype)
    check_against_oracle(cells, points, lohi, [on_wall, 0, 1, on_wall - 1], RTOL[dtype])
    monkeypatch.setenv("TORCHVOR_TEST_BOUNDED_CELLS", "1")  # the largest fixed tier overflows
    bounded = torchvor.voronoi(points, UNIT, on_failure="flag").status.cpu()
    assert bounded[on_wall] in (torchvor.CellStatus.TOO_MANY_PLANES, torchvor.CellStatus.TOO_MANY_VERTICES)
