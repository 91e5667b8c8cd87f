"""What torchvor.voronoi accepts and rejects: batches of clouds with their
own boxes, the spellings of a box, strided inputs, bad values, shapes, types
and devices, empty input; and how cells that cannot be computed are
reported (on_failure).
"""
from __future__ import annotations

import warnings

import numpy as np
import pytest
import torch

import torchvor
from torchvor import CellStatus

from voronoi_checks import (
    RTOL, UNIT, assert_same_cloud, assert_same_integrals, box_of, check_against_oracle, check_global, has_cuda,
    pick_cells, ragged_batch, rand, run,
)


# ------------------------------------------------- batches and box spellings


def test_batch_per_cloud_boxes(device, dtype, gen, cells_impl, vertex_balls):
    sizes = [300, 1, 0, 150, 2]
    batch = ragged_batch(sizes, device)
    los = torch.tensor([[0.0, 0.0, 0.0], [5.0, 5.0, 5.0], [0.0, 0.0, 0.0], [-2.0, 1.0, 0.0], [0.0, 0.0, 10.0]],
                       dtype=torch.float64)
    his = los + torch.tensor([[1.0, 1.0, 1.0], [1.0, 2.0, 3.0], [1.0, 1.0, 1.0], [0.5, 4.0, 1.0], [1.0, 1.0, 0.1]],
                             dtype=torch.float64)
    parts = [rand(s, gen, torch.float64, "cpu", lo, hi) for s, lo, hi in zip(sizes, los, his)]
    points = torch.cat(parts).to(dtype).to(device)
    box = torch.stack([los, his], 1).to(dtype).to(device)  # (B, 2, 3)
    cells = run(points, box, batch=batch)
    boxes = [(b[0].cpu().double().numpy(), b[1].cpu().double().numpy()) for b in box]
    check_global(cells, points, boxes, dtype, batch)
    start = 0
    for s, lohi in zip(sizes, boxes):
        if s:
            part = points[start:start + s]
            sub = run(part, torch.stack([torch.as_tensor(lohi[0]), torch.as_tensor(lohi[1])]).to(dtype).to(device))
            # each cloud is its own diagram: same as computing it alone
            if vertex_balls == "every retry":
                # which cells a retry takes follows the first pass's k, the
                # pilot's, which follows the whole batch; the vertex balls
                # clip in another order than the radius of security
                assert_same_integrals(type(sub)(*(a[start:start + s] for a in cells)), sub, dtype)
            else:
                assert_same_cloud(type(sub)(*(a[start:start + s] for a in cells)), sub, dtype)
            check_against_oracle(sub, part, lohi, pick_cells(part, 25, gen, *lohi), RTOL[dtype], tag=f"cloud@{start}")
        start += s


def test_batch_bounding_boxes(device, dtype, gen):
    """box=None with a batch: each cloud clipped to its own bounding box."""
    sizes = [200, 0, 120, 3]
    batch = ragged_batch(sizes, device)
    points = torch.cat([rand(200, gen, dtype, device), rand(120, gen, dtype, device, 3.0, 3.5),
                        rand(3, gen, dtype, device, -1.0, 0.0)])
    cells = run(points, batch=batch)
    boxes, start = [], 0
    for s in sizes:
        part = points[start:start + s].cpu().double().numpy()
        boxes.append((part.min(0), part.max(0)) if s else (np.zeros(3), np.zeros(3)))
        start += s
    check_global(cells, points, boxes, dtype, batch)
    part = points[200:320]
    sub = run(part)
    assert_same_cloud(type(sub)(*(a[200:320] for a in cells)), sub, dtype)
    check_against_oracle(sub, part, boxes[2], pick_cells(part, 30, gen, *boxes[2]), RTOL[dtype])


def test_batch_single_cloud_box_shapes(device, dtype, gen):
    """All box spellings give the same result."""
    points = rand(300, gen, dtype, device)
    ref = run(points, UNIT)
    spellings = [
        torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=dtype, device=device),
        torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device),
        (torch.zeros(3), torch.ones(3)),
        [[0, 0, 0], [1, 1, 1]],
    ]
    for box in spellings:
        got = run(points, box)
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
    batch = torch.zeros(300, dtype=torch.long, device=device)
    got = run(points, spellings[1], batch=batch)
    for a, b in zip(got, ref):
        assert torch.equal(a, b)


def test_one_box_for_every_cloud(device, dtype, gen):
    """A single box with a batch of several clouds applies to each cloud."""
    sizes = [150, 90, 60]
    batch = ragged_batch(sizes, device)
    points = rand(sum(sizes), gen, dtype, device)
    boxes = torch.tensor([[0.0, 0, 0], [1, 1, 1]], dtype=dtype, device=device).expand(3, 2, 3)
    ref = run(points, boxes, batch=batch)
    for box in (UNIT, boxes[:1], boxes[0]):
        got = run(points, box, batch=batch)
        for a, b in zip(got, ref):
            assert torch.equal(a, b)
    moved = torchvor.lloyd(points, UNIT, iters=2, batch=batch)
    assert torch.equal(moved, torchvor.lloyd(points, boxes, iters=2, batch=batch))
    with pytest.raises(ValueError, match="batch refers to 3 point clouds but box holds 2"):
        torchvor.voronoi(points, boxes[:2], batch=batch)


def test_flat_box_is_an_error(device, dtype, gen):
    """A box of zero size along an axis holds no volume: an error naming the axis,
    whether the box is given or derived from coplanar points (box=None)."""
    points = rand(50, gen, dtype, device)
    points[:, 2] = 0.5
    with pytest.raises(ValueError, match="flat along z .*box=None"):
        torchvor.voronoi(points)
    with pytest.raises(ValueError, match="flat along z"):
        torchvor.voronoi(points, ([0, 0, 0.5], [1, 1, 0.5]))
    with pytest.raises(ValueError, match="flat along x"):
        torchvor.voronoi(points[:1])  # one point: its bounding box is a point
    with pytest.raises(ValueError, match="flat along z"):
        torchvor.cvt_energy(points)
    with pytest.raises(ValueError, match="flat along z"):
        torchvor.lloyd(points, iters=1)
    # An empty cloud's box is never used: a flat one is fine.
    batch = torch.tensor([0] * 50, device=device)
    boxes = torch.tensor([[[0.0, 0, 0], [1, 1, 1]], [[0.0, 0, 0], [0, 0, 0]]], dtype=dtype, device=device)
    cells = torchvor.voronoi(points, boxes, batch=batch)
    assert torch.isclose(cells.volume.double().sum(), torch.tensor(1.0, dtype=torch.float64, device=device))


def test_nan_points_named_with_a_derived_box(device, dtype):
    """box=None derives a NaN box from NaN points: the error names the points."""
    points = torch.rand(30, 3, dtype=dtype, device=device)
    points[7, 0] = float("nan")
    with pytest.raises(ValueError, match="points contains NaN"):
        torchvor.voronoi(points)
    batch = torch.tensor([0] * 15 + [1] * 15, device=device)
    with pytest.raises(ValueError, match="points contains NaN"):
        torchvor.voronoi(points, batch=batch)


def test_non_contiguous_points(device, dtype, gen):
    points = rand(400, gen, dtype, device).t().contiguous().t()
    assert not points.is_contiguous()
    cells = run(points, UNIT)
    ref = run(points.contiguous(), UNIT)
    for a, b in zip(cells, ref):
        assert torch.equal(a, b)
    # strided batch vector and box
    batch = ragged_batch([150, 250], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 2, dtype=dtype, device=device)
    ref = run(points.contiguous(), box, batch=batch)
    batch_view = torch.stack([batch, batch], 1)[:, 0]
    box_view = box.transpose(1, 2).contiguous().transpose(1, 2)
    assert not batch_view.is_contiguous() and not box_view.is_contiguous()
    for a, b in zip(run(points, box_view, batch=batch_view), ref):
        assert torch.equal(a, b)


# ----------------------------------------------------------------- bad input


def test_points_outside_box(device, dtype, gen):
    points = rand(50, gen, dtype, device)
    bad = points.clone()
    bad[10, 2] = 1.5
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(bad, UNIT)
    bad = points.clone()
    bad[3, 0] = -1e-3
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(bad, UNIT)
    # a batch element outside its own box (but inside another's)
    batch = ragged_batch([25, 25], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]], [[2.0, 2, 2], [3, 3, 3]]], dtype=dtype, device=device)
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(points, box, batch=batch)


def test_bad_values(device, dtype):
    points = torch.rand(30, 3, dtype=dtype, device=device)
    for value in (float("nan"), float("inf"), -float("inf")):
        bad = points.clone()
        bad[4, 1] = value
        with pytest.raises(ValueError, match="points"):
            torchvor.voronoi(bad, UNIT)
        with pytest.raises(ValueError, match="box"):
            torchvor.voronoi(points, ([0, 0, 0], [1, value, 1]))
    with pytest.raises(ValueError, match="box"):
        torchvor.voronoi(points, ([0, 0, 1], [1, 1, 0]))  # lo > hi
    with pytest.raises(ValueError, match="k"):
        torchvor.voronoi(points, UNIT, k=0)
    with pytest.raises(ValueError, match="memory_budget"):
        torchvor.voronoi(points, UNIT, memory_budget=0)


def test_bad_values_with_batch(device, dtype):
    """With a batch, NaN/Inf points are caught by their own check; without one,
    by the bounds (point_bounds). Both say "points", whichever element holds
    them, also next to an empty batch element."""
    points = torch.rand(40, 3, dtype=dtype, device=device)
    batch = torch.tensor([0] * 20 + [2] * 20, device=device)  # element 1 is empty
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 3, dtype=dtype, device=device)
    assert run(points, box, batch=batch).status.eq(CellStatus.SUCCESS).all()
    for value in (float("nan"), float("inf"), -float("inf")):
        for row in (3, 33):
            bad = points.clone()
            bad[row, 2] = value
            with pytest.raises(ValueError, match="points contains NaN or Inf"):
                torchvor.voronoi(bad, box, batch=batch)
            with pytest.raises(ValueError, match="points contains NaN or Inf"):
                torchvor.voronoi(bad, UNIT)


def test_box_of_numbers_copied_once(device):
    """A box given as numbers reaches the op through one device copy per (values,
    dtype, device), kept for later calls (ops._box_for_call); other boxes are
    converted on every call. The results equal as_box's either way."""
    from torchvor.ops import _DEVICE_BOXES, _box_for_call, as_box

    _DEVICE_BOXES.clear()  # other tests' boxes would otherwise fill the cache, which then starts over
    points = torch.rand(20, 3, device=device)
    first = _box_for_call(points, UNIT, None)
    assert _box_for_call(points, ([0, 0, 0], [1, 1, 1]), None) is first  # equal numbers, one copy
    torch.testing.assert_close(first, as_box(points, UNIT), rtol=0, atol=0)
    assert first.shape == (1, 2, 3) and first.dtype == points.dtype and first.device == points.device
    wide = _box_for_call(points, ([-1.0, 0, 0], [1.0, 1, 1]), None)
    assert wide is not first and wide[0, 0, 0].item() == -1.0
    as_double = _box_for_call(points.double(), UNIT, None)
    assert as_double is not first and as_double.dtype == torch.float64
    # Tensors, batches and malformed boxes take as_box on every call.
    given = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], device=device)
    assert _box_for_call(points, given, None) is given
    batch = torch.zeros(20, dtype=torch.int64, device=device)
    assert _box_for_call(points, UNIT, batch) is not _box_for_call(points, UNIT, batch)
    with pytest.raises(ValueError, match="box"):
        _box_for_call(points, ([0, 0], [1, 1]), None)
    # The op never writes its box: a cached box stays as made after calls.
    cells = torchvor.voronoi(points, UNIT)
    assert _box_for_call(points, UNIT, None) is first and first.flatten().tolist() == [0, 0, 0, 1, 1, 1]
    assert cells.volume.sum().item() == pytest.approx(1.0, rel=1e-5)


def test_bad_shapes_and_types(device):
    points = torch.rand(30, 3, device=device)
    for shape in [(30, 2), (30,), (30, 3, 1), (90,)]:
        with pytest.raises(ValueError, match="points"):
            torchvor.voronoi(torch.rand(shape, device=device), UNIT)
    for box in [torch.zeros(3, 2), torch.zeros(2, 2, 2), torch.zeros(6), ([0, 0], [1, 1])]:
        with pytest.raises(ValueError, match="box"):
            torchvor.voronoi(points, box)
    for dt in (torch.int64, torch.int32, torch.float16, torch.bool):
        with pytest.raises(TypeError, match="points"):
            torchvor.voronoi(points.to(dt), UNIT)
    with pytest.raises(TypeError, match="points"):
        torchvor.voronoi(points.tolist(), UNIT)
    with pytest.raises(TypeError, match="box"):  # the op itself: box dtype must match
        torch.ops.torchvor.voronoi_cells(points, torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64,
                                                              device=device))


def test_bad_batch(device):
    points = torch.rand(20, 3, device=device)
    good = ragged_batch([10, 10], device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]] * 2, device=device)
    run(points, box, batch=good)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good.flip(0))
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good - 1)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, box, batch=good[:-1])
    with pytest.raises(TypeError, match="batch"):
        torchvor.voronoi(points, box, batch=good.int())
    with pytest.raises(ValueError, match="box holds 2"):  # 3 clouds, 2 boxes
        torchvor.voronoi(points, box, batch=ragged_batch([5, 5, 10], device))
    with pytest.raises(ValueError, match="box"):  # several boxes without batch
        torchvor.voronoi(points, box)


# --------------------------------------------------------- failure reporting


def test_on_failure_values(device, gen):
    points = rand(100, gen, torch.float64, device)
    with pytest.raises(ValueError, match="on_failure"):
        torchvor.voronoi(points, UNIT, on_failure="ignore")
    with pytest.raises(ValueError, match="on_failure"):
        torchvor.voronoi(points, UNIT, on_failure=None)
    results = []
    for mode in ("raise", "warn", "flag"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            results.append(torchvor.voronoi(points, UNIT, on_failure=mode))
    for other in results[1:]:
        for a, b in zip(results[0], other):
            assert torch.equal(a, b)


def sphere_around_centre(n, dtype, device):
    """A point at the centre of the unit cube and n points on a sphere around it
    (Fibonacci spiral): the centre cell has n facets."""
    i = torch.arange(n, dtype=torch.float64) + 0.5
    phi = torch.acos(1 - 2 * i / n)
    theta = np.pi * (1 + 5 ** 0.5) * i
    s = torch.stack([torch.cos(theta) * torch.sin(phi), torch.sin(theta) * torch.sin(phi), torch.cos(phi)], 1)
    return torch.cat([torch.full((1, 3), 0.5, dtype=torch.float64), 0.5 + 0.3 * s]).to(dtype).to(device)


def test_many_faced_cell_computed(device, dtype, gen, cells_impl):
    """A cell of 400 facets, more than the device's arrays hold, is finished at the
    host's larger tiers: exact, like the cells around it."""
    points = sphere_around_centre(400, dtype, device)
    cells = run(points, UNIT)
    check_global(cells, points, [box_of(points, UNIT)], dtype)
    check_against_oracle(cells, points, box_of(points, UNIT), [0, *range(1, 401, 23)], RTOL[dtype])


def test_failure_reporting(monkeypatch, device, gen):
    """A cell that cannot be computed is reported, never silent: "raise" ->
    RuntimeError, "warn" -> RuntimeWarning, "flag" -> quiet; a failure status and
    NaN outputs for that cell, exact results for the others. (Such a cell: 4200
    facets, more than the largest tier holds, with the unbounded cells that
    finish it turned off.)"""
    dtype = torch.float32
    points = sphere_around_centre(4200, dtype, device)
    assert (run(points, UNIT).status == CellStatus.SUCCESS).all()
    monkeypatch.setenv("TORCHVOR_TEST_BOUNDED_CELLS", "1")
    with pytest.raises(RuntimeError, match="could not be computed"):
        torchvor.voronoi(points, UNIT, on_failure="raise")
    with pytest.warns(RuntimeWarning, match="could not be computed"):
        warned = torchvor.voronoi(points, UNIT, on_failure="warn")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cells = torchvor.voronoi(points, UNIT, on_failure="flag")
    for a, b in zip(warned, cells):
        torch.testing.assert_close(a, b, rtol=0, atol=0, equal_nan=True)
    status = cells.status.cpu()
    failed = (status != CellStatus.SUCCESS) & (status != CellStatus.DUPLICATE)
    assert failed[0] and not failed[1:].any(), status
    assert status[0] in (CellStatus.TOO_MANY_PLANES, CellStatus.TOO_MANY_VERTICES)
    assert torch.isnan(cells.volume[0]) and torch.isnan(cells.centroid[0]).all()
    assert torch.isnan(cells.second_moment[0])
    assert torch.isfinite(cells.volume[1:]).all() and torch.isfinite(cells.centroid[1:]).all()
    check_against_oracle(cells, points, box_of(points, UNIT), range(1, 4201, 400), RTOL[dtype])


@pytest.mark.skipif(not has_cuda, reason="needs CUDA")
def test_device_mismatch():
    points = torch.rand(20, 3)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]])
    with pytest.raises(ValueError, match="box"):
        torch.ops.torchvor.voronoi_cells(points.cuda(), box)
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points.cuda(), UNIT, batch=torch.zeros(20, dtype=torch.long))
    with pytest.raises(ValueError, match="box"):
        torch.ops.torchvor.voronoi_cells(points, box.cuda())
    with pytest.raises(ValueError, match="batch"):
        torchvor.voronoi(points, UNIT, batch=torch.zeros(20, dtype=torch.long, device="cuda"))


def test_empty_points(device, dtype):
    cells = torchvor.voronoi(torch.empty(0, 3, dtype=dtype, device=device), UNIT)
    assert cells.volume.shape == (0,) and cells.centroid.shape == (0, 3)
    cells = torchvor.voronoi(torch.empty(0, 3, dtype=dtype, device=device))
    assert cells.status.shape == (0,)
