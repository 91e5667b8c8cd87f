"""The registered ops behind torchvor.voronoi: torch.library.opcheck, the
schemas' defaults, torch.compile, and the grid-order op (torchvor.lloyd's)
against voronoi_cells, including the outputs written back to the caller's
rows in ranges.
"""
from __future__ import annotations

import numpy as np
import pytest
import torch

import torchvor

from voronoi_checks import RTOL, UNIT, VORONOI_FIELDS, check_against_oracle, pick_cells, ragged_batch, rand


def test_opcheck_voronoi(device, dtype, gen):
    points = rand(30, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, box, None, 40, 1 << 20))
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, box, None, 3, 1))
    batch = ragged_batch([12, 0, 18], device)
    boxes = box.expand(3, 2, 3).contiguous()
    torch.library.opcheck(torch.ops.torchvor.voronoi_cells.default, (points, boxes, batch, 8, 1 << 20))


def test_memory_budget_default_matches_the_schemas():
    """The Python wrappers' default memory_budget is the ops' schema default."""
    for op in (torch.ops.torchvor.voronoi_cells.default, torch.ops.torchvor.voronoi_cells_grid_order.default):
        budget = next(a for a in op._schema.arguments if a.name == "memory_budget")
        assert budget.default_value == torchvor.ops.DEFAULT_MEMORY_BUDGET


def test_opcheck_voronoi_grid_order(device, dtype, gen):
    points = rand(30, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    op = torch.ops.torchvor.voronoi_cells_grid_order.default
    torch.library.opcheck(op, (points, box, None, 40, 1 << 20))
    torch.library.opcheck(op, (points, box, None, 3, 1))
    batch = ragged_batch([12, 0, 18], device)
    torch.library.opcheck(op, (points, box.expand(3, 2, 3).contiguous(), batch, 8, 1 << 20))


@pytest.mark.parametrize("k", [3, None])
def test_grid_order_gives_the_same_cells_in_that_order(device, dtype, gen, k):
    """torchvor::voronoi_cells_grid_order (torchvor.lloyd's) computes the cells
    of voronoi_cells, bit for bit, row i for points[order[i]]: order is a
    permutation, sorted by batch element, that keeps exact duplicates in the
    caller's order (the lowest index keeps the cell). k=3 retries every cell."""
    from torchvor.ops import _voronoi_in_grid_order, as_box
    points = rand(900, gen, dtype, device)
    points[600:650] = points[100:150]  # exact duplicates, later rows
    batch = ragged_batch([400, 0, 500], device)
    for use_batch in (False, True):
        b = batch if use_batch else None
        box = as_box(points, None, b)
        reference = torchvor.voronoi(points, box, batch=b, k=k, on_failure="flag")
        cells, order = _voronoi_in_grid_order(points, box, b, k)
        assert order.dtype == torch.int64 and order.device == points.device
        assert torch.equal(torch.sort(order).values, torch.arange(900, device=device))
        for name in VORONOI_FIELDS:
            assert torch.equal(getattr(cells, name), getattr(reference, name)[order]), name
        if use_batch:
            assert bool((batch[order].diff() >= 0).all())
        rank = torch.empty_like(order).index_copy_(0, order, torch.arange(900, device=device))
        assert bool((rank[100:150] < rank[600:650]).all())
    cells, order = _voronoi_in_grid_order(points[:0], as_box(points, UNIT))
    assert order.shape == (0,) and order.dtype == torch.int64 and cells.centroid.shape == (0, 3)


def test_inverse_order_in_ranges(device, dtype, gen, monkeypatch):
    """The inverse of the grid order is written in ranges of rows that fit
    the GPU's L2 cache (a single range unless the input is very large):
    TORCHVOR_TEST_SCATTER_BYTES=1000 splits 3000 points into 12 ranges, and
    the outputs, in the caller's rows, are those of one range bit for bit."""
    points = rand(3000, gen, dtype, device)
    reference = torchvor.voronoi(points, UNIT, on_failure="flag")
    monkeypatch.setenv("TORCHVOR_TEST_SCATTER_BYTES", "1000")
    cells = torchvor.voronoi(points, UNIT, on_failure="flag")
    for name in ("volume", "centroid", "second_moment", "status", "neighbors_needed", "radius"):
        assert torch.equal(getattr(cells, name), getattr(reference, name)), name
    check_against_oracle(cells, points, (np.zeros(3), np.ones(3)), pick_cells(points, 20, gen, np.zeros(3), np.ones(3)),
                         RTOL[dtype])


def test_compile_voronoi_grid_order(device, dtype, gen):
    from torchvor.ops import _voronoi_in_grid_order
    torch._dynamo.reset()
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)

    def f(p):
        cells, order = _voronoi_in_grid_order(p, box)
        return cells.centroid - p[order], order

    compiled = torch.compile(f, fullgraph=True)
    for n in (150, 260):
        points = rand(n, gen, dtype, device)
        for a, b in zip(compiled(points), f(points)):
            assert torch.equal(a, b)


def test_compile_voronoi(device, dtype, gen):
    torch._dynamo.reset()

    def f(p):
        cells = torchvor.voronoi(p, UNIT)
        return cells.volume, cells.centroid, cells.second_moment, cells.status, cells.neighbors_needed

    def g(p):  # default (bounding) box and arithmetic around the op
        cells = torchvor.voronoi(p)
        return (cells.volume * 2).sum(), cells.centroid - p

    compiled_f = torch.compile(f, fullgraph=True)
    compiled_g = torch.compile(g, fullgraph=True)
    for n in (150, 260):
        points = rand(n, gen, dtype, device)
        for a, b in zip(compiled_f(points), f(points)):
            assert torch.equal(a, b)
        for a, b in zip(compiled_g(points), g(points)):
            torch.testing.assert_close(a, b)


def test_outputs_marked_non_differentiable(device, dtype, gen):
    """Outputs without a backward do not look differentiable: a loss through
    them raises instead of silently getting no gradient. (voronoi's volume,
    centroid and second moment have one: test_voronoi_gradients.py.)"""
    points = rand(200, gen, dtype, device).requires_grad_()
    cells = torchvor.voronoi(points, UNIT)
    assert not cells.status.requires_grad and not cells.neighbors_needed.requires_grad
    graph = torchvor.voronoi_graph(points, UNIT)
    for value in (graph.area, graph.centroid, graph.wall_area):
        assert not value.requires_grad
    with pytest.raises(RuntimeError, match="does not require grad"):
        graph.area.sum().backward()
    moved = torchvor.lloyd(points, UNIT, iters=1)
    assert not moved.requires_grad


@pytest.mark.parametrize("k", [3, None])
def test_rows_compute_those_cells_alone(device, dtype, gen, k):
    """voronoi_cells with rows computes those cells as the full call does (bit
    for bit in float64, where no cell depends on the pass it was computed in)
    and returns them alone, in the rows' order (a row asked twice twice).
    k=3 retries every cell."""
    from torchvor.ops import _voronoi_rows, as_box
    points = rand(900, gen, dtype, device)
    points[600:650] = points[100:150]  # exact copies
    batch = ragged_batch([400, 0, 500], device)
    for use_batch in (False, True):
        b = batch if use_batch else None
        box = as_box(points, None, b)
        full = torchvor.voronoi(points, box, batch=b, k=k, on_failure="flag")
        rows = torch.randperm(900, generator=gen)[:300].to(device)
        rows = torch.cat([rows, torch.tensor([120, 620, 120], device=device)])  # a copy, its original (twice)
        some = _voronoi_rows(points, box, rows, b, k)
        for name, got, want in zip(VORONOI_FIELDS, some, full):
            assert got.shape[0] == rows.numel(), name
            if dtype == torch.float64 or got.dtype not in (torch.float32, torch.float64):
                assert torch.equal(got, want[rows]), name
            else:
                torch.testing.assert_close(got, want[rows], rtol=RTOL[dtype], atol=0, equal_nan=True, msg=name)
        assert some.status[-2] == (torchvor.CellStatus.SUCCESS if use_batch else torchvor.CellStatus.DUPLICATE)


def test_rows_none_or_empty(device, dtype, gen):
    """No row asked: no output row; every row: the full call."""
    points = rand(200, gen, dtype, device)
    points[150] = points[10]
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    op = torch.ops.torchvor.voronoi_cells.default
    none = op(points, box, None, None, 1 << 30, torch.zeros(0, dtype=torch.int64, device=device))
    assert all(t.shape[0] == 0 for t in none)
    assert none[1].shape == (0, 3) and none[0].dtype == dtype
    every = op(points, box, None, None, 1 << 30, torch.arange(200, device=device))
    full = op(points, box, None, None, 1 << 30)
    for got, want in zip(every, full):
        if dtype == torch.float64:
            assert torch.equal(got, want)


def test_rows_invalid(device, gen):
    points = rand(50, gen, torch.float64, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64, device=device)
    op = torch.ops.torchvor.voronoi_cells.default
    with pytest.raises(ValueError, match=r"rows must be indices of points, in \[0, 50\)"):
        op(points, box, None, None, 1 << 30, torch.tensor([3, 50], device=device))
    with pytest.raises(ValueError, match=r"rows must be indices of points"):
        op(points, box, None, None, 1 << 30, torch.tensor([-1], device=device))
    with pytest.raises(TypeError, match="rows must be int64"):
        op(points, box, None, None, 1 << 30, torch.tensor([3], dtype=torch.int32, device=device))
    with pytest.raises(ValueError, match=r"rows must have shape \(M,\)"):
        op(points, box, None, None, 1 << 30, torch.tensor([[3]], device=device))
    if torch.device(device).type == "cuda":
        with pytest.raises(ValueError, match="rows is on cpu"):
            op(points, box, None, None, 1 << 30, torch.tensor([3]))


def test_opcheck_voronoi_rows(device, dtype, gen):
    points = rand(30, gen, dtype, device)
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=dtype, device=device)
    op = torch.ops.torchvor.voronoi_cells.default
    torch.library.opcheck(op, (points, box, None, 40, 1 << 20, torch.arange(30, device=device).flip(0)))
    torch.library.opcheck(op, (points, box, None, 40, 1 << 20, torch.tensor([0, 7, 29], device=device)))


def test_rows_gradients(device, gen):
    """The asked cells' gradients are the full call's (the others give none)."""
    from torchvor.ops import _voronoi_rows
    points = rand(60, gen, torch.float64, device).requires_grad_()
    box = torch.tensor([[[0.0, 0, 0], [1, 1, 1]]], dtype=torch.float64, device=device)
    rows = torch.tensor([3, 17, 40, 59, 17], device=device)  # 17 twice: its gradients add
    weights = torch.rand(5, 3, dtype=torch.float64, generator=gen).to(device)
    some = _voronoi_rows(points, box, rows)
    (some.volume.sum() + (some.centroid * weights).sum() + some.second_moment.sum()).backward()
    got = points.grad.clone()
    points.grad = None
    full = torchvor.voronoi(points, box)
    (full.volume[rows].sum() + (full.centroid[rows] * weights).sum() + full.second_moment[rows].sum()).backward()
    torch.testing.assert_close(got, points.grad, rtol=1e-9, atol=1e-12)
