"""Voronoi cells and k nearest neighbours of one cloud spread over the ranks of a
``torch.distributed`` process group.

Each rank passes its own points (any partition of the cloud, not necessarily
spatial) and gets the results for its own points, in its own order; indices
are global: rank r's point i is ``offset_r + i``, offsets in rank order (the
cloud is the ranks' points concatenated). The results are those of the
single-process call on that whole cloud: in float64 bit for bit for the cells
that both compute in the same pass (every cell whose neighbours the first
pass's k covers), otherwise to rounding: a retried cell's tier and precision
depend on the other cells its pass retries, and they round in another order
(as the same cell does between two single-process calls with different k).

How: the cloud is cut into slabs along the longest axis of its box, one a
rank, balanced by count; every point goes to its slab's rank, with a halo of
the points of the other slabs within a width of its slab. A rank computes its
slab's points among those (the plain op, its points ordered by global index,
so ties break as on the whole cloud) and keeps the results that the halo
certifies: a cell whose twice radius stays inside the halo (no absent point
can cut it: the radius of security), a neighbour row whose k-th distance
does. The rest run again with the halo their reach asks for, up to the whole
cloud. The results then go back to the ranks that own the points.

Periodic boxes (voronoi, lloyd): torchvor.periodic's cells with every decision
reduced over the ranks (_RankAgreement): each rank pads its own points with
their images, and the plain cells run as above over every rank's padded
points, the images' cells not computed.

Collectives are ``all_to_all_single`` and ``all_reduce`` of the points'
device: gloo for CPU tensors, NCCL for CUDA ones. Every rank of the group must
call, with points of one dtype and device kind.
"""
from __future__ import annotations

import math
import sys
import time
import warnings
from typing import List, Optional, Sequence

import torch
import torch.distributed as dist

from .graph import VoronoiGraph, voronoi_graph as _plain_graph
from . import periodic as _periodic
from .ops import DEFAULT_MEMORY_BUDGET, KNN, CellStatus, VoronoiCells, _check_on_failure, as_box
from .ops import _voronoi_rows, knn as _plain_knn
from .radius import radius as _plain_radius

__all__ = ["knn", "lloyd", "voronoi", "voronoi_graph"]

# The first halo: this many mean spacings (the cube root of the volume a point
# of the box) on each side of a slab; then what the uncertified cells ask for.
FIRST_HALO_SPACINGS = 3.0
# A cell is certified when 2 radius (1 + CERTIFY_SLACK) stays inside the halo
# (the radius of the computed vertices: see torchvor.periodic).
CERTIFY_SLACK = 1e-2
# Histogram bins along the cut axis that place the slab boundaries.
BALANCE_BINS = 1 << 16


class _Group:
    """The process group, the ranks' point counts and offsets."""

    def __init__(self, group, count: int, device: torch.device):
        if not dist.is_available() or not dist.is_initialized():
            raise RuntimeError("torchvor.distributed: torch.distributed is not initialized "
                               "(call torch.distributed.init_process_group first)")
        self.group = group
        self.rank = dist.get_rank(group)
        self.size = dist.get_world_size(group)
        self.device = device
        counts = self.all_gather_int(count)
        self.counts = counts
        self.offset = sum(counts[: self.rank])
        self.total = sum(counts)

    def recounted(self, count: int) -> "_Group":
        """The same group, each rank holding `count` rows now (offsets follow)."""
        other = object.__new__(_Group)
        other.group, other.rank, other.size, other.device = self.group, self.rank, self.size, self.device
        other.counts = self.all_gather_int(count)
        other.offset = sum(other.counts[: self.rank])
        other.total = sum(other.counts)
        return other

    def all_gather_int(self, value: int) -> List[int]:
        """Every rank's `value`, in rank order (one all_reduce)."""
        row = torch.zeros(self.size, dtype=torch.int64, device=self.device)
        row[self.rank] = value
        dist.all_reduce(row, group=self.group)
        return row.tolist()

    def reduce(self, tensor: torch.Tensor, op) -> torch.Tensor:
        """`tensor` reduced over the ranks (a copy)."""
        out = tensor.clone()
        dist.all_reduce(out, op=op, group=self.group)
        return out

    def exchange(self, dest: torch.Tensor, tensors: Sequence[torch.Tensor]) -> List[torch.Tensor]:
        """Each row of `tensors` sent to rank `dest` of that row; returns the rows
        this rank receives, by source rank, each source's rows in their order."""
        order = torch.sort(dest, stable=True).indices
        send = torch.bincount(dest, minlength=self.size)
        recv = torch.empty_like(send)
        dist.all_to_all_single(recv, send, group=self.group)
        send_splits, recv_splits = send.tolist(), recv.tolist()
        out = []
        for tensor in tensors:
            rows = tensor[order].contiguous()
            received = rows.new_empty((sum(recv_splits), *rows.shape[1:]))
            dist.all_to_all_single(received, rows, recv_splits, send_splits, group=self.group)
            out.append(received)
        return out


def _check_input(points: torch.Tensor, batch: Optional[torch.Tensor], caller: str) -> Optional[str]:
    """What is wrong with this rank's points (None: nothing)."""
    if not isinstance(points, torch.Tensor) or points.dim() != 2 or points.shape[1] != 3:
        return f"points must be a tensor of shape (N, 3), got {getattr(points, 'shape', type(points))}"
    if points.dtype not in (torch.float32, torch.float64):
        return f"points must be float32 or float64, got {points.dtype}"
    if not bool(torch.isfinite(points).all()):
        return "points contain NaN or Inf"
    if batch is not None:
        if not isinstance(batch, torch.Tensor) or batch.shape != (points.shape[0],) or batch.dtype != torch.int64:
            return "batch must be an int64 tensor of shape (N,)"
        if batch.numel() and (bool((batch < 0).any()) or bool((batch[1:] < batch[:-1]).any())):
            return "batch must be sorted and non-negative"
    return None


def _agree(points: torch.Tensor, batch, caller: str, group) -> _Group:
    """The group, once every rank's input is valid and all share one dtype:
    otherwise every rank raises (none is left waiting in a collective)."""
    device = points.device if isinstance(points, torch.Tensor) else torch.device("cpu")
    problem = _check_input(points, batch, caller)
    count = points.shape[0] if problem is None else 0
    g = _Group(group, count, device)
    dtype_code = {torch.float32: 1, torch.float64: 2}.get(getattr(points, "dtype", None), 3)
    flags = torch.tensor([int(problem is not None), dtype_code, -dtype_code], dtype=torch.int64, device=device)
    flags = g.reduce(flags, dist.ReduceOp.MAX)
    if problem is not None:
        raise ValueError(f"torchvor.distributed.{caller}: {problem}")
    if int(flags[0]):
        raise ValueError(f"torchvor.distributed.{caller}: another rank's input is invalid (it raised the reason)")
    if int(flags[1]) != -int(flags[2]):
        raise TypeError(f"torchvor.distributed.{caller}: every rank must pass points of one dtype")
    return g


def _global_batch(g: _Group, batch: Optional[torch.Tensor], n: int,
                  counts: Optional[List[int]] = None) -> Optional[torch.Tensor]:
    """The batch vector, after checking that the ranks' vectors concatenate
    in order (the whole cloud's must be sorted, as the plain ops ask);
    `counts`: the ranks' row counts (default: their points')."""
    counts = g.counts if counts is None else counts
    has = int(batch is not None)
    uses = g.reduce(torch.tensor([has, -has], device=g.device), dist.ReduceOp.MAX).tolist()
    if not uses[0]:
        return None
    if uses[1] == 0:  # some rank passed none
        raise ValueError("torchvor.distributed: every rank must pass a batch vector, or none")
    ends = torch.full((2 * g.size,), -(1 << 62), dtype=torch.int64, device=g.device)  # below any entry
    if n:
        ends[2 * g.rank], ends[2 * g.rank + 1] = -batch[0], batch[-1]  # first negated: one MAX reduces both
    ends = g.reduce(ends, dist.ReduceOp.MAX).tolist()
    last = -1
    for r in range(g.size):
        if counts[r]:
            if -ends[2 * r] < last:
                raise ValueError("torchvor.distributed: the ranks' batch vectors, concatenated in rank order, "
                                 "must be sorted")
            last = ends[2 * r + 1]
    return batch


def _global_box(g: _Group, points: torch.Tensor, box, batch: Optional[torch.Tensor]) -> torch.Tensor:
    """(B, 2, 3) float64: the box of each cloud, the given one or the whole
    cloud's bounding box (reduced over the ranks)."""
    clouds = int(g.reduce(torch.tensor([int(batch.max()) + 1 if batch is not None and batch.numel() else 1],
                                       device=g.device), dist.ReduceOp.MAX)[0])
    if box is not None:
        given = as_box(points, box, batch).double()
        if given.shape[0] == 1 and clouds > 1:
            given = given.expand(clouds, 2, 3)
        return given.contiguous()
    lo = torch.full((clouds, 3), math.inf, dtype=torch.float64, device=g.device)
    hi = torch.full((clouds, 3), -math.inf, dtype=torch.float64, device=g.device)
    if points.shape[0]:
        index = (batch if batch is not None else torch.zeros(points.shape[0], dtype=torch.int64,
                                                             device=g.device)).unsqueeze(1).expand(-1, 3)
        lo = lo.scatter_reduce(0, index, points.double(), "amin")
        hi = hi.scatter_reduce(0, index, points.double(), "amax")
    lo = g.reduce(lo, dist.ReduceOp.MIN)
    hi = g.reduce(hi, dist.ReduceOp.MAX)
    empty = ~torch.isfinite(lo).all(1)
    lo[empty], hi[empty] = 0.0, 0.0
    return torch.stack([lo, hi], 1)


class _Slabs:
    """The cut: slab s holds the points whose coordinate along `axis` lies in
    [bounds[s], bounds[s + 1]) (the outer bounds infinite), balanced by count."""

    def __init__(self, g: _Group, points: torch.Tensor, box: torch.Tensor):
        lo, hi = box[:, 0].amin(0), box[:, 1].amax(0)
        self.axis = int(torch.argmax(hi - lo))
        a, b = float(lo[self.axis]), float(hi[self.axis])
        x = points[:, self.axis].double()
        if b > a:
            counts = torch.histc(x, bins=BALANCE_BINS, min=a, max=b) if x.numel() else \
                torch.zeros(BALANCE_BINS, dtype=torch.float64, device=g.device)
            counts = g.reduce(counts.double(), dist.ReduceOp.SUM)
            cumulative = torch.cumsum(counts, 0)
            targets = torch.arange(1, g.size, dtype=torch.float64, device=g.device) * (g.total / g.size)
            edge = torch.searchsorted(cumulative, targets, right=True).clamp_max(BALANCE_BINS - 1)
            inner = (a + (edge.double() + 1) * ((b - a) / BALANCE_BINS)).tolist()
        else:
            inner = [a] * (g.size - 1)
        self.bounds = [-math.inf, *inner, math.inf]
        self.size = g.size
        # the mean spacing of the densest cloud's box: the first halo's unit
        volume = (box[:, 1] - box[:, 0]).clamp_min(0).prod(1).max()
        self.spacing = float((volume / max(g.total, 1)) ** (1.0 / 3.0)) if float(volume) > 0 else \
            float((hi - lo).max()) / max(g.total, 1)

    def owner(self, coordinate: torch.Tensor) -> torch.Tensor:
        """(N,) int64: the slab of each coordinate along the axis."""
        inner = torch.tensor(self.bounds[1:-1], dtype=torch.float64, device=coordinate.device)
        return torch.searchsorted(inner, coordinate.double().contiguous(), right=True)

    def halo_dest(self, coordinate: torch.Tensor, home: int, widths: List[float]):
        """(rows, dest): the rows (of points in slab `home`) within widths[s] of
        another slab s, one entry a (row, s) pair."""
        rows, dests = [], []
        x = coordinate.double()
        for s in range(self.size):
            if s == home:
                continue
            near = (x >= self.bounds[s] - widths[s]) & (x < self.bounds[s + 1] + widths[s])
            idx = near.nonzero().squeeze(1)
            rows.append(idx)
            dests.append(torch.full_like(idx, s))
        if not rows:
            empty = torch.zeros(0, dtype=torch.int64, device=coordinate.device)
            return empty, empty
        return torch.cat(rows), torch.cat(dests)

    def clearance(self, coordinate: torch.Tensor, slab: int, width: float) -> torch.Tensor:
        """(N,) float64: the distance of each coordinate (in `slab`) to the
        edge of its slab widened by `width` (inf on an outer side)."""
        x = coordinate.double()
        below = x - (self.bounds[slab] - width)
        above = (self.bounds[slab + 1] + width) - x
        return torch.minimum(below, above)


class _Local:
    """This rank's slab: its points (with global index, batch and the rank
    that owns each) and the halo, ordered by global index. `wanted` (N,) bool:
    the points whose results are asked for (default: all); the others only
    bound cells (a periodic call's images)."""

    def __init__(self, g: _Group, slabs: _Slabs, points: torch.Tensor, batch: Optional[torch.Tensor],
                 wanted: Optional[torch.Tensor] = None):
        self.g, self.slabs = g, slabs
        n = points.shape[0]
        index = torch.arange(g.offset, g.offset + n, dtype=torch.int64, device=g.device)
        b = batch if batch is not None else torch.zeros(n, dtype=torch.int64, device=g.device)
        dest = slabs.owner(points[:, slabs.axis])
        if wanted is None:
            self.points, self.index, self.batch = g.exchange(dest, [points, index, b])
            self.wanted = torch.ones(self.index.numel(), dtype=torch.bool, device=g.device)
        else:
            self.points, self.index, self.batch, wanted = g.exchange(dest, [points, index, b, wanted.to(torch.int64)])
            self.wanted = wanted.bool()

    def cloud(self, width: float):
        """(points, global index, batch, own): the slab's points and every point
        of the other slabs within `width` of it (every rank passes the same
        width), sorted by global index; `own`: the slab's wanted points."""
        g = self.g
        rows, dest = self.slabs.halo_dest(self.points[:, self.slabs.axis], g.rank, [width] * g.size)
        halo = g.exchange(dest, [self.points[rows], self.index[rows], self.batch[rows]])
        points = torch.cat([self.points, halo[0]])
        index = torch.cat([self.index, halo[1]])
        batch = torch.cat([self.batch, halo[2]])
        own = torch.zeros(index.numel(), dtype=torch.bool, device=g.device)
        own[: self.index.numel()] = self.wanted
        order = torch.sort(index).indices
        return points[order], index[order], batch[order], own[order]

    def move(self, points: torch.Tensor) -> None:
        """The slab's points moved to `points` (rows of `self.points`); those
        now in another slab go to its rank (rows stay sorted by global index).
        Every point is wanted (Lloyd's)."""
        dest = self.slabs.owner(points[:, self.slabs.axis])
        if bool(self.g.reduce(torch.tensor([int(bool((dest != self.g.rank).any()))], device=self.g.device),
                              dist.ReduceOp.MAX)[0]):
            points, index, batch = self.g.exchange(dest, [points, self.index, self.batch])
            order = torch.sort(index).indices
            self.points, self.index, self.batch = points[order], index[order], batch[order]
            self.wanted = torch.ones(self.index.numel(), dtype=torch.bool, device=self.g.device)
        else:
            self.points = points

    def send_edges(self, edges: torch.Tensor, values: torch.Tensor):
        """Edges (E, 2) of global (neighbour, cell) and their `values` sent to
        the rank that owns each cell."""
        return tuple(self.g.exchange(_owner_rank(self.g, self.g.counts, edges[:, 1]), [edges, values]))

    def wrap(self, points: torch.Tensor) -> torch.Tensor:
        """Moved points as they stay (no periodic axis)."""
        return points

    @property
    def wanted_index(self) -> torch.Tensor:
        """The global index of the slab's wanted points, in their order."""
        return self.index[self.wanted]

    def send_back(self, index: torch.Tensor, *values: torch.Tensor) -> List[torch.Tensor]:
        """Each of `values`, rows of this slab's points (global `index`), sent to
        the ranks that own them: this rank's rows, in its input order."""
        return _send_back(self.g, self.g.counts, index, values)


def _owner_rank(g: _Group, counts: List[int], index: torch.Tensor) -> torch.Tensor:
    """(N,) int64: the rank that owns each global index, the ranks owning
    `counts` rows in rank order."""
    starts = torch.tensor([sum(counts[:r]) for r in range(1, g.size)], dtype=torch.int64, device=g.device)
    return torch.searchsorted(starts, index.contiguous(), right=True)


def _send_back(g: _Group, counts: List[int], index: torch.Tensor, values) -> List[torch.Tensor]:
    """Each of `values`, rows of global `index` (rows owned by the ranks as
    `counts` says), sent to their owners: this rank's rows, in its order."""
    got_index, *got = g.exchange(_owner_rank(g, counts, index), [index, *values])
    rows = got_index - sum(counts[: g.rank])
    out = []
    for value, received in zip(values, got):
        mine = value.new_empty((counts[g.rank], *value.shape[1:]))
        mine[rows] = received
        out.append(mine)
    return out


def _together(g: _Group, fn, *args):
    """fn(*args) on every rank; if it raises on any, every rank raises (that
    rank its own error), so that none is left waiting in a collective."""
    error = None
    try:
        result = fn(*args)
    except Exception as caught:  # noqa: BLE001 - re-raised below, on every rank
        error, result = caught, None
    failed = g.reduce(torch.tensor([int(error is not None)], device=g.device), dist.ReduceOp.MAX)
    if error is not None:
        raise error
    if int(failed[0]):
        raise RuntimeError("torchvor.distributed: the call raised on another rank (that rank names the cause)")
    return result


def _check_inside(points: torch.Tensor, batch: Optional[torch.Tensor], box: torch.Tensor,
                  periodic: Optional[torch.Tensor] = None) -> None:
    """This rank's points inside their clouds' boxes (as the plain op asks),
    checked where they are, before they move; along the `periodic` axes
    ((3,) bool) anywhere."""
    if points.shape[0] == 0:
        return
    if box.shape[0] > 1 and batch is None:
        raise ValueError("torchvor.distributed.voronoi: a box per cloud needs batch")
    rows = box[batch] if batch is not None else box[0].expand(points.shape[0], 2, 3)
    outside = (points < rows[:, 0]) | (points > rows[:, 1])
    if periodic is not None:
        outside &= ~periodic
    if bool(outside.any()):
        raise ValueError("torchvor.distributed.voronoi: points must lie inside box (lo <= p <= hi)"
                         + (" along the axes that are not periodic" if periodic is not None else ""))


def _halo_rounds(g: _Group, local: _Local, compute, shortfall, max_rounds: int = 8):
    """Runs `compute(points, batch)` on the slab and a growing halo until
    `shortfall(result, clearance, rows, width)` is 0 for every row, the last
    round with the whole cloud; returns (the global index of each point
    computed, the rows of the slab's own points, the result). `clearance`:
    each computed point's distance to the halo's edge; the shortfall: how
    much wider the halo must be for each row that counts (the slab's points
    `rows`, or the queries), inf: as wide as the cloud."""
    width = FIRST_HALO_SPACINGS * local.slabs.spacing
    for round_ in range(max_rounds + 1):
        if round_ == max_rounds:
            width = math.inf
        points, index, batch, own = local.cloud(width)
        rows = own.nonzero().squeeze(1)
        clearance = local.slabs.clearance(points[:, local.slabs.axis], g.rank, width)

        def work():
            result = compute(points, batch)
            return result, torch.nan_to_num(shortfall(result, clearance, rows, width), nan=math.inf)

        result, short = _together(g, work)
        if width == math.inf or g.size == 1:
            short = torch.zeros_like(short)  # the whole cloud is there
        need = float(short.max()) if short.numel() else 0.0
        wanted = float(g.reduce(torch.tensor([need], dtype=torch.float64, device=g.device), dist.ReduceOp.MAX)[0])
        if wanted == 0.0 or width == math.inf:
            return index, rows, result
        width = max(2 * width, width + 1.25 * wanted)  # inf (or NaN: then the whole cloud) when a reach is
        if not width < math.inf:
            width = math.inf
    raise AssertionError("unreachable: the last round holds the whole cloud")


def _certify_rows(g: _Group, local: _Local, compute, shortfall, extract, max_rounds: int = 8) -> List[torch.Tensor]:
    """_halo_rounds for results a row of the slab's points each: the first
    round computes the slab with the first halo, each later one only the rows
    not yet certified, among the points of a wider halo within 1.25 times the
    reach they asked for (_near_seeds). `compute(points, batch, rows)` may
    compute the rows' results alone; `extract(result, index, rows)`
    gives the rows' outputs (tensors, row by row; `index` the global index of
    each point computed); returns them for every slab point, in
    `local.points`' order."""
    width = FIRST_HALO_SPACINGS * local.slabs.spacing
    outputs: Optional[List[torch.Tensor]] = None
    pending = reach = None  # the rows still to certify (None: all), and the reach each asks for
    axis = local.slabs.axis
    for round_ in range(max_rounds + 1):
        if round_ == max_rounds:
            width = math.inf
        points, index, batch, own = local.cloud(width)
        rows = own.nonzero().squeeze(1)
        clearance = local.slabs.clearance(points[:, axis], g.rank, width)

        def work(points=points, index=index, batch=batch, clearance=clearance):
            if pending is None:
                seeds = rows
            else:  # the points within reach of a pending seed, the seeds among them
                sub, bound = _near_seeds(points, batch, rows[pending], reach, axis)
                seeds = torch.searchsorted(sub, rows[pending])
                points, index, batch, clearance = points[sub], index[sub], batch[sub], clearance[sub].clone()
                clearance[seeds] = torch.minimum(clearance[seeds], bound)  # a point left out lies farther
            result = compute(points, batch, seeds)
            short = torch.nan_to_num(shortfall(result, clearance, seeds, width), nan=math.inf)
            if width == math.inf or g.size == 1:
                short = torch.zeros_like(short)  # the whole cloud is there
            return short, extract(result, index, seeds), clearance[seeds]

        short, values, seed_clearance = _together(g, work)
        done = short == 0
        if outputs is None:
            outputs = [v.new_empty((rows.numel(), *v.shape[1:])) for v in values]
        at = torch.arange(rows.numel(), device=g.device) if pending is None else pending
        for out, v in zip(outputs, values):
            out[at[done]] = v[done]
        pending, reach = at[~done], 1.25 * (short[~done] + seed_clearance[~done])
        need = float(short.max()) if short.numel() else 0.0
        wanted = float(g.reduce(torch.tensor([need], dtype=torch.float64, device=g.device), dist.ReduceOp.MAX)[0])
        if wanted == 0.0:
            return outputs
        width = max(2 * width, width + 1.25 * wanted)  # inf (or NaN: then the whole cloud) when a reach is
        if not width < math.inf:
            width = math.inf
    raise AssertionError("unreachable: the last round holds the whole cloud")


# _near_seeds lists at most this many (seed, point) pairs by a radius search;
# beyond, it takes the points near the seeds along the cut axis alone.
NEAR_PAIRS = 1 << 23


def _near_seeds(points: torch.Tensor, batch: torch.Tensor, seeds: torch.Tensor, reach: torch.Tensor, axis: int):
    """(rows, bound): the sorted rows of `points` within `reach` of one of the
    rows `seeds` (seeds included), and for each seed how far a point left out
    lies at least: every point within the largest reach, by a radius search,
    where that lists few enough pairs (estimated at the mean density of the
    points' extent); else the points within each seed's reach along `axis`."""
    r = float(reach.max()) if reach.numel() else 0.0
    extent = (points.amax(0) - points.amin(0)).double().clamp_min(1e-300) if points.shape[0] else None
    if 0.0 < r < math.inf and points.shape[0]:
        volume = float(extent.prod())
        density = points.shape[0] / volume if volume > 0.0 else math.inf  # flat: the axis alone
        if seeds.numel() * density * (4.0 / 3.0) * math.pi * min(r, float(extent.max())) ** 3 <= NEAR_PAIRS:
            found = _plain_radius(points.detach(), r, points[seeds].detach(), batch=batch, query_batch=batch[seeds])
            rows = torch.unique(torch.cat([found.edge_index[0], seeds]))
            return rows, torch.full_like(reach, r)
    x = points[:, axis].double()
    return _within_any(x, x[seeds], reach).nonzero().squeeze(1), reach


def _within_any(x: torch.Tensor, centres: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the coordinates `x` within `reach` of one of `centres` (the
    union of the intervals centre +- reach)."""
    if centres.numel() == 0:
        return torch.zeros_like(x, dtype=torch.bool)
    starts, order = torch.sort(centres - reach)
    ends = torch.cummax((centres + reach)[order], 0).values
    at = torch.searchsorted(starts, x.contiguous(), right=True) - 1
    return (at >= 0) & (x <= ends[at.clamp_min(0)])


def _cell_shortfall(cells: VoronoiCells, clearance: torch.Tensor) -> torch.Tensor:
    """(N,) float64 of every computed cell: how far twice its radius (with
    CERTIFY_SLACK) passes its clearance; inf where the cell failed."""
    computed = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
    reach = 2 * cells.radius.double() * (1 + CERTIFY_SLACK)
    excess = (reach - clearance).clamp_min(0)
    return torch.where(computed, torch.nan_to_num(excess, nan=math.inf), torch.full_like(excess, math.inf))


def _pack_cells(cells: VoronoiCells, rows: torch.Tensor, *more: torch.Tensor):
    """The fields of cells `rows` as two tensors (and `more` floating columns
    appended to the first): (R, 6 + ...) of the floating fields, (R, 2) int32
    of status and neighbors_needed."""
    floats = torch.cat([cells.volume[rows].unsqueeze(1), cells.centroid[rows], cells.second_moment[rows].unsqueeze(1),
                        cells.radius[rows].to(cells.volume.dtype).unsqueeze(1), *more], 1)
    ints = torch.stack([cells.status[rows].to(torch.int32), cells.neighbors_needed[rows]], 1)
    return floats, ints


def _unpack_cells(floats: torch.Tensor, ints: torch.Tensor) -> VoronoiCells:
    return VoronoiCells(floats[:, 0], floats[:, 1:4], floats[:, 4], ints[:, 0].to(torch.int8),
                        ints[:, 1].contiguous(), floats[:, 5])


def _setup(points, box, batch, group, caller: str):
    """The group, points (detached), batch, boxes (B, 2, 3) in the points'
    dtype, and the slabs, after the checks every rank agrees on."""
    g = _agree(points, batch, caller, group)
    points = points.detach()
    batch = _global_batch(g, batch, points.shape[0])
    full_box = _global_box(g, points, box, batch)
    box_arg = full_box.to(points.dtype)
    _together(g, _check_inside, points, batch, box_arg)
    return g, points, batch, box_arg, _Slabs(g, points, full_box)


def _no_weights(caller: str, kwargs) -> None:
    """Power diagrams are computed in one process only, so far."""
    if kwargs.get("weights") is not None:
        raise NotImplementedError(f"torchvor.distributed.{caller}: weights (power diagrams) are not distributed "
                                  f"yet; call torchvor.{caller} in one process")
    kwargs.pop("weights", None)


def _start(caller: str, points, box, batch, group, kwargs):
    """A cell call's first steps: (on_failure, group, points, batch, boxes,
    this rank's slab), `kwargs` left with what the plain op takes."""
    _no_weights(caller, kwargs)
    if _periodic.periodic_axes(kwargs.pop("periodic", False), f"distributed.{caller}") is not None:
        raise NotImplementedError(f"torchvor.distributed.{caller}: periodic boxes are supported by "
                                  f"torchvor.distributed.voronoi and lloyd only, so far")
    on_failure = kwargs.pop("on_failure", "warn")
    _check_on_failure(f"distributed.{caller}", on_failure)
    g, points, batch, box_arg, slabs = _setup(points, box, batch, group, caller)
    return on_failure, g, points, batch, box_arg, _Local(g, slabs, points, batch)


def _slab_cells(g: _Group, local: "_Local", box_arg, batched: bool, kwargs) -> VoronoiCells:
    """The cells of this rank's wanted slab points (the plain voronoi's,
    on_failure "flag"), in the order of `local.points`. The halo's cells are
    not computed: its points only bound the slab's."""

    def compute(p, b, rows):
        return _voronoi_rows(p, box_arg, rows, b if batched else None, **kwargs)

    def shortfall(cells, clearance, rows, width):  # cells: the rows' own
        return _cell_shortfall(cells, clearance[rows])

    def extract(cells, index, rows):
        return _pack_cells(cells, slice(None))

    return _unpack_cells(*_certify_rows(g, local, compute, shortfall, extract))


def voronoi(points: torch.Tensor, box=None, *, group=None, batch: Optional[torch.Tensor] = None,
            **kwargs) -> VoronoiCells:
    """:func:`torchvor.voronoi` of the cloud that the ranks' points make
    together (rank order), each rank getting its own points' cells.

    Args:
        points: (N_r, 3) float32 or float64, this rank's points (any N_r, 0 too).
        box: as :func:`torchvor.voronoi`; None: the whole cloud's bounding box.
        group: the process group (default: the world).
        batch: (N_r,) int64 batch vector of this rank's points; the ranks'
            vectors concatenated in rank order must be sorted.
        **kwargs: ``k``, ``on_failure``, ``memory_budget`` and ``periodic``
            as :func:`torchvor.voronoi` (periodic: the box is required).

    Returns:
        :class:`torchvor.VoronoiCells` of this rank's points, in their order:
        the single-process call's results on the whole cloud. The outputs carry
        no gradient (no distributed backward yet).
    """
    _no_weights("voronoi", kwargs)
    axes = _periodic.periodic_axes(kwargs.pop("periodic", False), "distributed.voronoi")
    if axes is not None:
        return _periodic_voronoi(points, box, batch, group, axes, kwargs)
    on_failure, g, points, batch, box_arg, local = _start("voronoi", points, box, batch, group, kwargs)
    cells = _slab_cells(g, local, box_arg, batch is not None, kwargs)
    out = _unpack_cells(*local.send_back(local.index, *_pack_cells(cells, slice(None))))
    _report_failures(out, on_failure, "voronoi")
    return out


class _RankAgreement(_periodic.Agreement):
    """periodic.cells over the ranks of `g`: each rank pads its own points,
    every decision is reduced over the ranks, and the plain cells are computed
    over every rank's padded points (the images' cells not computed)."""

    alone = False  # a cell that reaches past the margin asks for a wider one, the whole cloud again

    def __init__(self, g: _Group):
        self.g = g

    def counts(self, pbox, batch, n):
        return self.g.reduce(_periodic.cloud_counts(pbox, batch, n), dist.ReduceOp.SUM)

    def all(self, flag: bool) -> bool:
        return bool(self.g.reduce(torch.tensor([int(flag)], device=self.g.device), dist.ReduceOp.MIN)[0])

    def any(self, flags: torch.Tensor) -> bool:
        return bool(self.g.reduce(torch.tensor([int(bool(flags.any()))], device=self.g.device),
                                  dist.ReduceOp.MAX)[0])

    def max(self, values: torch.Tensor) -> torch.Tensor:
        return self.g.reduce(values, dist.ReduceOp.MAX)

    def rows(self, points, box, rows, batch, k, memory_budget, weights=None) -> VoronoiCells:
        assert weights is None, "power cells are not distributed (voronoi raises before)"
        g = self.g.recounted(points.shape[0])
        points = points.detach()
        wanted = torch.zeros(points.shape[0], dtype=torch.bool, device=g.device)
        wanted[rows] = True
        local = _Local(g, _Slabs(g, points, box.double()), points, batch, wanted)
        cells = _slab_cells(g, local, box, batch is not None, {"k": k, "memory_budget": memory_budget})
        every = _unpack_cells(*local.send_back(local.wanted_index, *_pack_cells(cells, slice(None))))
        return VoronoiCells(*(t[rows] for t in every))


def _periodic_setup(points, box, batch, group, axes, caller: str):
    """(group, points (detached), batch, periodic box) of a periodic call
    along `axes` (periodic_axes'), after the checks every rank agrees on."""
    g = _agree(points, batch, caller, group)
    points = points.detach()
    batch = _global_batch(g, batch, points.shape[0])
    if box is None:
        raise ValueError(f"torchvor.distributed.{caller}: periodic needs a box (its edges are the periods)")
    full_box = _global_box(g, points, box, batch).to(points.dtype)
    pbox = _together(g, _periodic.periodic_box, points, full_box, batch, axes, f"distributed.{caller}")
    _together(g, _check_inside, points, batch, full_box, pbox.mask)
    return g, points, batch, pbox


class _Owned:
    """A rank's own points in a periodic call (as _Local for lloyd, but they
    stay on their rank: each periodic call pads and cuts them anew)."""

    def __init__(self, g: _Group, points: torch.Tensor, batch: Optional[torch.Tensor], pbox):
        self.g, self.points, self.pbox, self.given_batch = g, points, pbox, batch
        self.batch = batch if batch is not None else torch.zeros(points.shape[0], dtype=torch.int64, device=g.device)
        self.index = torch.arange(g.offset, g.offset + points.shape[0], dtype=torch.int64, device=g.device)

    def cells(self, k: Optional[int], memory_budget: int = DEFAULT_MEMORY_BUDGET) -> VoronoiCells:
        found = _periodic.cells(self.points, self.pbox, self.given_batch, k, memory_budget, graph=False,
                                agreement=_RankAgreement(self.g))
        return _periodic._caller_cells(found, self.points.dtype)

    def wrap(self, points: torch.Tensor) -> torch.Tensor:
        return _periodic.wrap(points, self.pbox, self.given_batch)

    def move(self, points: torch.Tensor) -> None:
        self.points = points

    def send_back(self, index: torch.Tensor, *values: torch.Tensor) -> List[torch.Tensor]:
        return list(values)  # the rows are this rank's own, in its order


def _periodic_voronoi(points, box, batch, group, axes, kwargs) -> VoronoiCells:
    """voronoi with periodic: torchvor.periodic's cells (images, certificate,
    wider margins) with _RankAgreement."""
    on_failure = kwargs.pop("on_failure", "warn")
    _check_on_failure("distributed.voronoi", on_failure)
    unknown = set(kwargs) - {"k", "memory_budget"}
    if unknown:
        raise TypeError(f"torchvor.distributed.voronoi: unexpected keyword(s) {sorted(unknown)}")
    g, points, batch, pbox = _periodic_setup(points, box, batch, group, axes, "voronoi")
    out = _Owned(g, points, batch, pbox).cells(kwargs.get("k"), kwargs.get("memory_budget", DEFAULT_MEMORY_BUDGET))
    _report_failures(out, on_failure, "voronoi")
    return out


def voronoi_graph(points: torch.Tensor, box=None, *, group=None, batch: Optional[torch.Tensor] = None,
                  **kwargs) -> VoronoiGraph:
    """:func:`torchvor.voronoi_graph` of the cloud that the ranks' points make
    together (rank order), each rank getting its own cells and their faces.

    Args:
        points, box, group, batch: as :func:`voronoi`.
        **kwargs: ``k``, ``on_failure``, ``memory_budget`` as :func:`torchvor.voronoi_graph`.

    Returns:
        :class:`torchvor.VoronoiGraph` of this rank's cells: ``edge_index``
        (2, E_r) holds global indices (row 1 this rank's points, sorted by it
        then row 0), ``wall_area`` and ``cells`` this rank's rows in its
        order: the single-process call's on the whole cloud (each face is the
        mean of what its two cells computed, so a cell counts as computed when
        its neighbours are too). No gradient.
    """
    on_failure, g, points, batch, box_arg, local = _start("voronoi_graph", points, box, batch, group, kwargs)

    def compute(p, b):
        return _plain_graph(p, box_arg, batch=b if batch is not None else None, on_failure="flag", **kwargs)

    def shortfall(graph, clearance, rows, width):
        own_cell = _cell_shortfall(graph.cells, clearance)
        source, target = graph.edge_index
        worst = own_cell.scatter_reduce(0, target, own_cell[source], "amax")  # and every neighbour's
        return worst[rows]

    index, rows, graph = _halo_rounds(g, local, compute, shortfall)
    own = torch.zeros(index.numel(), dtype=torch.bool, device=g.device)
    own[rows] = True
    source, target = graph.edge_index
    mine = own[target]
    edges = torch.stack([index[source[mine]], index[target[mine]]], 1)
    faces = torch.cat([graph.area[mine].unsqueeze(1), graph.centroid[mine]], 1)
    edges, faces = local.send_edges(edges, faces)
    key = edges[:, 1] * max(g.total, 1) + edges[:, 0]  # by cell, then neighbour
    order = torch.sort(key).indices
    edges, faces = edges[order], faces[order]
    floats, ints = local.send_back(index[rows], *_pack_cells(graph.cells, rows, graph.wall_area[rows]))
    cells = _unpack_cells(floats, ints)
    _report_failures(cells, on_failure, "voronoi_graph")
    return VoronoiGraph(edges.t().contiguous(), faces[:, 0].contiguous(), faces[:, 1:4].contiguous(),
                        floats[:, 6:12].contiguous(), cells)


def lloyd(points: torch.Tensor, box=None, iters: int = 10, *, group=None, tol: Optional[float] = None,
          k: Optional[int] = None, batch: Optional[torch.Tensor] = None, progress: bool = False, callback=None,
          return_history: bool = False, periodic=False):
    """:func:`torchvor.lloyd` of the cloud that the ranks' points make together
    (rank order), each rank getting its own points relaxed, in its order.

    Each iteration computes the cells over the ranks (:func:`voronoi`; the
    slabs are cut once) and moves every point to its cell's centroid (a point
    whose cell failed stays, with a RuntimeWarning on its rank), as the
    single-process relaxation does: the same points, bit for bit in float64.

    Args:
        points, box, group, batch: as :func:`voronoi` (box None: the first
            points' bounding box, kept for every iteration).
        iters, tol, k, progress, return_history: as :func:`torchvor.lloyd`;
            ``tol`` and the history's measures are over the whole cloud
            (``neighbors_needed``: the largest of the ranks' percentiles;
            ``k``: the given k, or 0 where each call's pilot picks it);
            ``progress`` prints on rank 0.
        callback: ``callback(iteration, points, cells)`` on every rank with its
            own moved points and cells; True on any rank stops every rank.
        periodic: as :func:`torchvor.lloyd` (the box required): each
            iteration is a periodic :func:`voronoi`, the points wrapped into the
            box, and they stay on their owners' ranks.

    Returns:
        This rank's relaxed points (a new tensor), or ``(points, history)``.
    """
    from .lloyd import LloydStep, _progress_line, neighbors_quantile

    if not isinstance(iters, int) or isinstance(iters, bool) or iters < 0:
        raise ValueError(f"torchvor.distributed.lloyd: iters must be a non-negative int, got {iters!r}")
    if tol is not None and not tol >= 0:
        raise ValueError(f"torchvor.distributed.lloyd: tol must be None or >= 0, got {tol!r}")
    if k is not None and (not isinstance(k, int) or isinstance(k, bool) or k < 1):
        raise ValueError(f"torchvor.distributed.lloyd: k must be None or a positive int, got {k!r}")
    axes = _periodic.periodic_axes(periodic, "distributed.lloyd")
    if axes is not None:
        g, current, batch, pbox = _periodic_setup(points, box, batch, group, axes, "lloyd")
        box_arg = pbox.box
        local = _Owned(g, current, batch, pbox)
    else:
        g, current, batch, box_arg, slabs = _setup(points, box, batch, group, "lloyd")
        # the points stay on their slabs' ranks between iterations; those that cross a boundary move
        local = _Local(g, slabs, current, batch)
    edges = (box_arg[:, 1] - box_arg[:, 0]).double().norm(dim=1)
    history = []
    for iteration in range(iters):
        start = time.perf_counter()
        if axes is not None:
            cells = local.cells(k)
        else:
            cells = _slab_cells(g, local, box_arg, batch is not None, {"k": k})
        computed = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
        target = torch.where(computed.unsqueeze(1), cells.centroid, local.points)
        needed = neighbors_quantile(cells.neighbors_needed[computed])
        diagonal = edges[local.batch] if batch is not None else edges[0].expand(target.shape[0])
        moves = ((target - local.points).double().norm(dim=1) / diagonal).max() if target.shape[0] else \
            torch.zeros((), dtype=torch.float64, device=g.device)
        moved = local.wrap(target)
        sums = g.reduce(torch.stack([cells.second_moment.double().sum(), (~computed).sum().double()]),
                        dist.ReduceOp.SUM)
        maxima = g.reduce(torch.stack([moves.double(), torch.tensor(float(needed), dtype=torch.float64,
                                                                    device=g.device)]), dist.ReduceOp.MAX)
        energy, failed = float(sums[0]), int(sums[1])
        mine_failed = int((~computed).sum())
        if mine_failed:
            warnings.warn(f"torchvor.distributed.lloyd: {mine_failed} cell(s) could not be computed in iteration "
                          f"{iteration}; their points stay in place", RuntimeWarning, stacklevel=2)
        step = LloydStep(iteration=iteration, energy=energy, max_displacement=float(maxima[0]),
                         seconds=time.perf_counter() - start, k=k or 0, neighbors_needed=int(maxima[1]),
                         failed=failed)
        history.append(step)
        stop = False
        if callback is not None:  # the caller's rows and order
            mine, *floats_ints = local.send_back(local.index, moved, *_pack_cells(cells, slice(None)))
            stop = callback(iteration, mine, _unpack_cells(*floats_ints)) is True
        local.move(moved)
        if progress and g.rank == 0:
            print(_progress_line(step, iters), file=sys.stderr, flush=True)
        stop = bool(g.reduce(torch.tensor([int(stop)], device=g.device), dist.ReduceOp.MAX)[0])
        if stop or (tol is not None and step.max_displacement < tol):
            break
    (current,) = local.send_back(local.index, local.points)
    return (current, history) if return_history else current


def _report_failures(cells: VoronoiCells, on_failure: str, caller: str) -> None:
    """on_failure of voronoi and voronoi_graph for this rank's cells."""
    ok = (cells.status == CellStatus.SUCCESS) | (cells.status == CellStatus.DUPLICATE)
    failed = int((~ok).sum())
    if failed and on_failure != "flag":
        message = f"torchvor.distributed.{caller}: {failed} cell(s) could not be computed (NaN outputs)"
        if on_failure == "raise":
            raise RuntimeError(message)
        warnings.warn(message, RuntimeWarning, stacklevel=3)


def knn(points: torch.Tensor, k: int, queries: Optional[torch.Tensor] = None, *, group=None,
        batch: Optional[torch.Tensor] = None, query_batch: Optional[torch.Tensor] = None,
        exclude_self: Optional[bool] = None) -> KNN:
    """:func:`torchvor.knn` in the cloud that the ranks' points make together
    (rank order), for this rank's queries.

    Args:
        points: (N_r, 3) float32 or float64, this rank's points.
        k: neighbours a row, ``k >= 1``.
        queries: (M_r, 3) this rank's queries (the points' dtype); None: its points.
        group: the process group (default: the world).
        batch, query_batch: (N_r,) and (M_r,) int64 batch vectors; the ranks'
            vectors concatenated in rank order must be sorted; a query sees only
            points of its batch element (query_batch is required with batch
            where queries are given, as in :func:`torchvor.knn`).
        exclude_self: with queries None, whether a point skips itself (default True).

    Returns:
        :class:`torchvor.KNN` (dist2, idx), (M_r, k): idx are global indices
        into the whole cloud (rank r's point i is ``offset_r + i``), as the
        single-process call gives them; missing neighbours are inf / -1.
    """
    if not isinstance(k, int) or isinstance(k, bool) or k < 1:
        raise ValueError(f"torchvor.distributed.knn: k must be an int >= 1, got {k!r}")
    if queries is not None and exclude_self:
        raise ValueError("torchvor.distributed.knn: exclude_self applies only when queries is None")
    g = _agree(points, batch, "knn", group)
    points = points.detach()
    batch = _global_batch(g, batch, points.shape[0])
    slabs = _Slabs(g, points, _global_box(g, points, None, batch))
    local = _Local(g, slabs, points, batch)
    skip = queries is None and (exclude_self is None or bool(exclude_self))
    asked = None if queries is None else _Queries(g, slabs, points, batch, queries.detach(), query_batch)

    def compute(p, b, rows=None):  # every row's neighbours (they are cheap beside the exchanges)
        if asked is None:
            return _plain_knn(p, k, batch=b if batch is not None else None, exclude_self=skip)
        return _plain_knn(p, k, asked.points, batch=b if batch is not None else None,
                          query_batch=asked.batch if batch is not None else None)

    def shortfall(result, clearance, rows, width):
        if asked is None:
            rows_clearance = clearance[rows]
        else:
            rows_clearance = slabs.clearance(asked.points[:, slabs.axis], g.rank, width)
            rows = slice(None)
        last = torch.sqrt(result.dist2[rows, -1].double())  # inf where a row is short of k: the whole cloud decides
        return (last - rows_clearance).clamp_min(0)

    def extract(result, index, rows):
        idx = result.idx[rows]
        return [result.dist2[rows], torch.where(idx >= 0, index[idx.clamp_min(0)], idx)]  # global indices

    if asked is None:
        return KNN(*local.send_back(local.index, *_certify_rows(g, local, compute, shortfall, extract)))
    index, _, result = _halo_rounds(g, local, compute, shortfall)
    return KNN(*asked.send_back(*extract(result, index, slice(None))))


class _Queries:
    """This rank's slab's queries (sorted by global query index), routed by
    coordinate as the points are, and how their rows go back."""

    def __init__(self, g: _Group, slabs: _Slabs, points, batch, queries: torch.Tensor, query_batch):
        problem = None
        if not isinstance(queries, torch.Tensor) or queries.dim() != 2 or queries.shape[1] != 3:
            problem = "queries must have shape (M, 3)"
        elif queries.dtype != points.dtype or not bool(torch.isfinite(queries).all()):
            problem = "queries must have the points' dtype and be finite"
        elif batch is not None and (query_batch is None or query_batch.shape != (queries.shape[0],)):
            problem = "query_batch (M,) is required with batch when queries are given"
        _together(g, _raise_if, problem)
        self.g = g
        m = queries.shape[0]
        self.counts = g.all_gather_int(m)
        self.offset = sum(self.counts[: g.rank])
        if batch is not None:
            _global_batch(g, query_batch, m, self.counts)
        qindex = torch.arange(self.offset, self.offset + m, dtype=torch.int64, device=g.device)
        qbatch = query_batch if batch is not None else torch.zeros(m, dtype=torch.int64, device=g.device)
        got = g.exchange(slabs.owner(queries[:, slabs.axis]), [queries, qindex, qbatch])
        order = torch.sort(got[1]).indices
        self.points, self.index, self.batch = (t[order] for t in got)

    def send_back(self, *values: torch.Tensor) -> List[torch.Tensor]:
        """Each of `values`, rows of the slab's queries, sent to the ranks that asked them."""
        return _send_back(self.g, self.counts, self.index, values)


def _raise_if(problem: Optional[str]) -> None:
    if problem is not None:
        raise ValueError(f"torchvor.distributed.knn: {problem}")
