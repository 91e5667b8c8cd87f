"""How torchvor.distributed spreads one cloud over the ranks of a process
group: the group and its collectives (Group), the checks every rank agrees on,
the cut into slabs along the box's longest axis (Slabs), each rank's slab with
a halo of the other slabs' points (Local), the rounds that widen the halo
until every cell or row is certified (halo_rounds, certify_rows), and the
results sent back to the ranks that own the points."""
from __future__ import annotations

import math
from typing import List, Optional, Sequence

import torch
import torch.distributed as dist

from .ops import CellStatus, VoronoiCells, as_box
from .periodic import CERTIFY_SLACK  # a cell is certified when 2 radius (1 + CERTIFY_SLACK) stays inside the halo
from .radius import radius as _plain_radius

# The first halo: this many mean spacings (the cube root of the volume a point
# of the box) on each side of a slab; then what the uncertified cells ask for.
FIRST_HALO_SPACINGS = 3.0
# Histogram bins along the cut axis that place the slab boundaries.
BALANCE_BINS = 1 << 16


def _ceiling(value: float, dtype: torch.dtype) -> float:
    """The smallest value of `dtype` at or above `value` (a float64): for x
    of that dtype, x >= value exactly when x >= _ceiling(value, dtype)."""
    if dtype == torch.float64 or not math.isfinite(value):
        return value
    rounded = torch.tensor(value, dtype=dtype)
    if float(rounded) < value:
        rounded = torch.nextafter(rounded, torch.tensor(math.inf, dtype=dtype))
    return float(rounded)


class Group:
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

    def recounted(self, count: int) -> "Group":
        """The same group, each rank holding `count` rows now (offsets follow)."""
        other = object.__new__(Group)
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

    def grouping(self, dest: torch.Tensor) -> torch.Tensor:
        """The stable order that groups rows by `dest`, sorted by a key as
        narrow as the rank count allows (a radix sort's passes go by its bytes)."""
        return torch.sort(dest.to(torch.int16 if self.size <= 1 << 15 else torch.int32), stable=True).indices

    def splits(self, dest: torch.Tensor):
        """(send, receive): how many rows this rank sends to each rank, by
        `dest`, and receives from each."""
        send = torch.bincount(dest, minlength=self.size).tolist()
        return send, self.received(send)[0]

    def received(self, *sends: List[int]) -> List[List[int]]:
        """For each of `sends` (how many rows this rank sends to each rank),
        how many it receives from each rank (one collective for all)."""
        if not sends:
            return []
        sent = torch.tensor(sends, dtype=torch.int64, device=self.device).t().contiguous()  # (ranks, len(sends))
        got = torch.empty_like(sent)
        dist.all_to_all_single(got, sent, group=self.group)
        return got.t().tolist()

    def exchange(self, dest: torch.Tensor, tensors: Sequence[torch.Tensor],
                 grouped: bool = False) -> List[torch.Tensor]:
        """Each row of `tensors` sent to rank `dest` of that row; returns the rows
        this rank receives, by source rank, each source's rows in their order.
        `grouped`: `dest` is already non-decreasing (the rows go as they are)."""
        order = None if grouped else self.grouping(dest)
        send, recv = self.splits(dest)
        return [self.all_to_all(t if order is None else t[order], send, recv) for t in tensors]

    def all_to_all(self, rows: torch.Tensor, send: List[int], recv: List[int]) -> torch.Tensor:
        """`rows`, grouped by destination, send[r] of them to rank r; returns
        the recv[r] rows from each rank r, in rank order."""
        rows = rows.contiguous()
        received = rows.new_empty((sum(recv), *rows.shape[1:]))
        dist.all_to_all_single(received, rows, recv, send, group=self.group)
        return received


def check_input(points: torch.Tensor, batch: Optional[torch.Tensor], caller: str) -> Optional[str]:
    """What is wrong with this rank's points (None: nothing)."""
    if not isinstance(points, torch.Tensor) or points.dim() != 2 or points.shape[1] != 3:
        return f"points must be a tensor of shape (N, 3), got {getattr(points, 'shape', type(points))}"
    if points.dtype not in (torch.float32, torch.float64):
        return f"points must be float32 or float64, got {points.dtype}"
    if points.numel() and not bool(torch.isfinite(torch.stack(torch.aminmax(points, dim=0))).all()):
        return "points contain NaN or Inf"  # min and max are NaN or infinite where a coordinate is
    if batch is not None:
        if not isinstance(batch, torch.Tensor) or batch.shape != (points.shape[0],) or batch.dtype != torch.int64:
            return "batch must be an int64 tensor of shape (N,)"
        if batch.numel() and (bool((batch < 0).any()) or bool((batch[1:] < batch[:-1]).any())):
            return "batch must be sorted and non-negative"
    return None


def agree(points: torch.Tensor, batch, caller: str, group) -> Group:
    """The group, once every rank's input is valid and all share one dtype:
    otherwise every rank raises (none is left waiting in a collective)."""
    device = points.device if isinstance(points, torch.Tensor) else torch.device("cpu")
    problem = check_input(points, batch, caller)
    count = points.shape[0] if problem is None else 0
    g = Group(group, count, device)
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


def global_batch(g: Group, batch: Optional[torch.Tensor], n: int,
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


def global_box(g: Group, points: torch.Tensor, box, batch: Optional[torch.Tensor]) -> torch.Tensor:
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


class Slabs:
    """The cut: slab s holds the points whose coordinate along `axis` lies in
    [bounds[s], bounds[s + 1]) (the outer bounds infinite), balanced by count."""

    def __init__(self, g: Group, points: torch.Tensor, box: torch.Tensor):
        lo, hi = box[:, 0].amin(0), box[:, 1].amax(0)
        self.axis = int(torch.argmax(hi - lo))
        a, b = float(lo[self.axis]), float(hi[self.axis])
        x = points[:, self.axis]  # its dtype: the balance needs no exact edges
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

    def near(self, coordinate: torch.Tensor, slab: int, width: float) -> torch.Tensor:
        """(N,) bool: the coordinates in `slab` widened by `width` on each side,
        [bounds[slab] - width, bounds[slab + 1] + width) in float64, compared
        in the coordinates' own dtype (each edge rounded up to it: exactly
        the same test, no float64 copy)."""
        lo = _ceiling(self.bounds[slab] - width, coordinate.dtype)
        hi = _ceiling(self.bounds[slab + 1] + width, coordinate.dtype)
        return (coordinate >= lo) & (coordinate < hi)

    def halo_dest(self, coordinate: torch.Tensor, home: int, widths: List[float]):
        """(rows, dest): the rows (of points in slab `home`) within widths[s] of
        another slab s, one entry a (row, s) pair."""
        rows, dests = [], []
        for s in range(self.size):
            if s == home:
                continue
            idx = self.near(coordinate, s, widths[s]).nonzero().squeeze(1)
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


class Local:
    """This rank's slab: its points (with global index, batch and the rank
    that owns each) and the halo, ordered by global index. `wanted` (N,) bool:
    the points whose results are asked for (default: all); the others only
    bound cells (a periodic call's images).

    The first exchange sends each point to its slab's rank and, within the
    first halo's width of another slab, to that slab's rank too, each
    rank's rows in their order: every rank receives its first cloud (slab
    and halo) sorted by global index, with no sort and no second exchange.
    The slab alone (`points`, `index`, `batch`, `wanted`) is taken from it
    when first asked for (a wider halo, Lloyd). Later, the few rows that
    arrive (a wider halo, the points a Lloyd step moves across a boundary)
    are sorted and merged in. `batch` is None without a batch vector."""

    def __init__(self, g: Group, slabs: Slabs, points: torch.Tensor, batch: Optional[torch.Tensor],
                 wanted: Optional[torch.Tensor] = None):
        self.g, self.slabs = g, slabs
        self.batched = batch is not None
        self.all_wanted = wanted is None
        self.first_width = FIRST_HALO_SPACINGS * slabs.spacing
        axis = slabs.axis
        # the rows each rank gets (its slab and first halo; a pass over the points a rank), in this
        # rank's order; `owned`: those of its slab proper, whose results send_home brings back
        sent_rows = [slabs.near(points[:, axis], s, self.first_width).nonzero().squeeze(1) for s in range(g.size)]
        send = [rows.numel() for rows in sent_rows]
        order = torch.cat(sent_rows)
        sent_points = points[order]
        owned = [slabs.near(part[:, axis], s, 0.0) for s, part in enumerate(sent_points.split(send))]
        self._home = order[torch.cat(owned)]
        home_send = torch.stack([own.sum() for own in owned]).tolist()
        recv, home_recv = g.received(send, home_send)
        self._home_splits = (home_send, home_recv)
        narrow = torch.int32 if g.total < 1 << 31 else torch.int64  # the index travels as narrow as it fits
        sent = [sent_points, (order + g.offset).to(narrow)]
        sent += [batch[order]] if self.batched else []
        sent += [wanted[order].to(torch.uint8)] if wanted is not None else []
        got = [g.all_to_all(t, send, recv) for t in sent]
        own = slabs.near(got[0][:, axis], g.rank, 0.0)
        # the first cloud: points, index (narrow), batch, wanted (uint8 or None), own (bool): the slab's rows
        self._first = (got[0], got[1], got[2] if self.batched else None, got[-1] if wanted is not None else None, own)
        self._slab: Optional[List[Optional[torch.Tensor]]] = None  # points, index, batch, wanted

    def _slab_columns(self) -> List[Optional[torch.Tensor]]:
        """The slab's points, global index, batch and wanted (taken from the first cloud once)."""
        if self._slab is None:
            points, index, batch, wanted, own = self._first
            rows = own.nonzero().squeeze(1)
            self._slab = [points[rows], index[rows].long(), batch[rows] if batch is not None else None,
                          wanted[rows].bool() if wanted is not None else
                          torch.ones(rows.numel(), dtype=torch.bool, device=self.g.device)]
        return self._slab

    @property
    def points(self) -> torch.Tensor:
        return self._slab_columns()[0]

    @property
    def index(self) -> torch.Tensor:
        return self._slab_columns()[1]

    @property
    def batch(self) -> Optional[torch.Tensor]:
        return self._slab_columns()[2]

    @property
    def wanted(self) -> torch.Tensor:
        return self._slab_columns()[3]

    def cloud(self, width: float):
        """(points, global index, batch, rows): the slab's points and every
        point of the other slabs within `width` of it (every rank passes the
        same width), sorted by global index (batch None without a batch
        vector); `rows` (sorted): where the slab's wanted points are."""
        if self._first is not None and width == self.first_width:
            points, index, batch, wanted, own = self._first
            rows = (own if wanted is None else own & wanted.bool()).nonzero().squeeze(1)
            return points, index.long(), batch, rows
        g = self.g
        rows, dest = self.slabs.halo_dest(self.points[:, self.slabs.axis], g.rank, [width] * g.size)
        halo = g.exchange(dest, [self.points[rows], self.index[rows]] + ([self.batch[rows]] if self.batched else []))
        order = index_order(g, halo[1])
        halo = [t[order] for t in halo]
        at = merged_positions(self.index, halo[1])
        points, index = merged(*at, self.points, halo[0]), merged(*at, self.index, halo[1])
        rows = at[0] if self.all_wanted else at[0][self.wanted]
        return points, index, merged(*at, self.batch, halo[2]) if self.batched else None, rows

    def move(self, points: torch.Tensor) -> None:
        """The slab's points moved to `points` (rows of `self.points`); those
        now in another slab go to its rank (rows stay sorted by global index).
        Every point is wanted (Lloyd's)."""
        g = self.g
        index, batch = self.index, self.batch
        self._first = None  # the first cloud's points are no longer where they were
        dest = self.slabs.owner(points[:, self.slabs.axis])
        leave = dest != g.rank
        if bool(g.reduce(torch.tensor([int(bool(leave.any()))], device=g.device), dist.ReduceOp.MAX)[0]):
            stay = ~leave
            columns = [points, index] + ([batch] if self.batched else [])
            got = g.exchange(dest[leave], [t[leave] for t in columns])
            order = index_order(g, got[1])
            kept = [t[stay] for t in columns]
            at = merged_positions(kept[1], got[1][order])
            columns = [merged(*at, t, u[order]) for t, u in zip(kept, got)]
            index, batch = columns[1], columns[2] if self.batched else None
            self._home = None  # the rows are no longer those that came
        else:
            columns = [points]
        self._slab = [columns[0], index, batch, torch.ones(index.numel(), dtype=torch.bool, device=g.device)]
        self.all_wanted = True

    def send_edges(self, edges: torch.Tensor, values: torch.Tensor):
        """Edges (E, 2) of global (neighbour, cell) and their `values` sent to
        the rank that owns each cell."""
        return tuple(self.g.exchange(owner_rank(self.g, self.g.counts, edges[:, 1]), [edges, values]))

    def wrap(self, points: torch.Tensor) -> torch.Tensor:
        """Moved points as they stay (no periodic axis)."""
        return points

    @property
    def wanted_index(self) -> torch.Tensor:
        """The global index of the slab's wanted points, in their order."""
        return self.index[self.wanted]

    def send_back(self, index: torch.Tensor, *values: torch.Tensor) -> List[torch.Tensor]:
        """Each of `values`, rows of this slab's points (global `index`, sorted),
        sent to the ranks that own them: this rank's rows, in its input order."""
        return send_to_owners(self.g, self.g.counts, index, values)

    def send_home(self, *values: torch.Tensor) -> List[torch.Tensor]:
        """send_back of a row for every point of the slab (in its order), by
        the way the points came: no index travels. Not after a move."""
        assert self._home is not None, "send_home: the slab's points moved; use send_back"
        send, recv = self._home_splits
        out = []
        for value in values:
            received = self.g.all_to_all(value, recv, send)
            out.append(received.new_empty((self._home.numel(), *value.shape[1:])).index_copy_(0, self._home, received))
        return out


def index_order(g: Group, index: torch.Tensor) -> torch.Tensor:
    """The order that sorts distinct global indices, by a 32-bit key where
    they fit (half the radix passes of the 64-bit one)."""
    return torch.sort(index.to(torch.int32) if g.total < 1 << 31 else index).indices


def merged_positions(first: torch.Tensor, second: torch.Tensor):
    """(at_first, at_second): where the rows of two sorted lists of distinct
    indices (none in both) go in their merged, sorted list."""
    at_first = torch.searchsorted(second, first) + torch.arange(first.numel(), device=first.device)
    at_second = torch.searchsorted(first, second) + torch.arange(second.numel(), device=second.device)
    return at_first, at_second


def merged(at_first: torch.Tensor, at_second: torch.Tensor, first: torch.Tensor, second: torch.Tensor):
    """The rows of `first` and `second` placed at `at_first` and `at_second`
    (merged_positions') in one tensor."""
    out = first.new_empty((at_first.numel() + at_second.numel(), *first.shape[1:]))
    return out.index_copy_(0, at_first, first).index_copy_(0, at_second, second)


def owner_rank(g: Group, counts: List[int], index: torch.Tensor) -> torch.Tensor:
    """(N,) int64: the rank that owns each global index, the ranks owning
    `counts` rows in rank order."""
    starts = torch.tensor([sum(counts[:r]) for r in range(1, g.size)], dtype=torch.int64, device=g.device)
    return torch.searchsorted(starts, index.contiguous(), right=True)


def send_to_owners(g: Group, counts: List[int], index: torch.Tensor, values) -> List[torch.Tensor]:
    """Each of `values`, rows of global `index` (sorted, rows owned by the
    ranks as `counts` says), sent to their owners: this rank's rows, in its
    order."""
    got_index, *got = g.exchange(owner_rank(g, counts, index), [index, *values], grouped=True)
    rows = got_index - sum(counts[: g.rank])
    out = []
    for value, received in zip(values, got):
        mine = value.new_empty((counts[g.rank], *value.shape[1:]))
        mine[rows] = received
        out.append(mine)
    return out


def together(g: Group, fn, *args):
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


def check_inside(points: torch.Tensor, batch: Optional[torch.Tensor], box: torch.Tensor,
                  periodic: Optional[torch.Tensor] = None) -> None:
    """This rank's points inside their clouds' boxes (as the plain op asks),
    checked where they are, before they move; along the `periodic` axes
    ((3,) bool) anywhere."""
    if points.shape[0] == 0:
        return
    if box.shape[0] > 1 and batch is None:
        raise ValueError("torchvor.distributed.voronoi: a box per cloud needs batch")
    if batch is not None:
        rows = box[batch]
        outside = (points < rows[:, 0]) | (points > rows[:, 1])
    else:  # one box: the extremes decide
        low, high = torch.aminmax(points, dim=0)
        outside = (low < box[0, 0]) | (high > box[0, 1])
    if periodic is not None:
        outside &= ~periodic
    if bool(outside.any()):
        raise ValueError("torchvor.distributed.voronoi: points must lie inside box (lo <= p <= hi)"
                         + (" along the axes that are not periodic" if periodic is not None else ""))


def halo_rounds(g: Group, local: Local, compute, shortfall, max_rounds: int = 8):
    """Runs `compute(points, batch)` on the slab and a growing halo until
    `shortfall(result, clearance, rows, width)` is 0 for every row, the last
    round with the whole cloud; returns (the global index of each point
    computed, the rows of the slab's wanted points, the result). `clearance`:
    each computed point's distance to the halo's edge; the shortfall: how
    much wider the halo must be for each row that counts (the slab's points
    `rows`, or the queries), inf: as wide as the cloud."""
    width = local.first_width
    for round_ in range(max_rounds + 1):
        if round_ == max_rounds:
            width = math.inf
        points, index, batch, rows = local.cloud(width)
        clearance = local.slabs.clearance(points[:, local.slabs.axis], g.rank, width)

        def work():
            result = compute(points, batch)
            return result, torch.nan_to_num(shortfall(result, clearance, rows, width), nan=math.inf)

        result, short = together(g, work)
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


def certify_rows(g: Group, local: Local, compute, shortfall, extract, max_rounds: int = 8) -> List[torch.Tensor]:
    """halo_rounds for results a row of the slab's points each: the first
    round computes the slab with the first halo, each later one only the rows
    not yet certified, among the points of a wider halo within 1.25 times the
    reach they asked for (near_seeds). `compute(points, batch, rows)` may
    compute the rows' results alone; `shortfall(result, clearance, rows,
    width)` as halo_rounds', but `clearance` holds the rows' alone;
    `extract(result, index, rows)` gives the rows' outputs (tensors, row by
    row; `index` the global index of each point computed); returns them for
    every slab point, in `local.points`' order."""
    width = local.first_width
    outputs: Optional[List[torch.Tensor]] = None
    pending = reach = None  # the rows still to certify (None: all), and the reach each asks for
    slabs, axis = local.slabs, local.slabs.axis
    for round_ in range(max_rounds + 1):
        if round_ == max_rounds:
            width = math.inf
        points, index, batch, rows = local.cloud(width)

        def work(points=points, index=index, batch=batch):
            if pending is None:
                seeds = rows
                clearance = slabs.clearance(points[seeds, axis], g.rank, width)
            else:  # the points within reach of a pending seed, the seeds among them
                sub, bound = near_seeds(points, batch, rows[pending], reach, axis)
                seeds = torch.searchsorted(sub, rows[pending])
                points, index = points[sub], index[sub]
                batch = batch[sub] if batch is not None else None
                # a point left out lies farther than bound
                clearance = torch.minimum(slabs.clearance(points[seeds, axis], g.rank, width), bound)
            result = compute(points, batch, seeds)
            short = torch.nan_to_num(shortfall(result, clearance, seeds, width), nan=math.inf)
            if width == math.inf or g.size == 1:
                short = torch.zeros_like(short)  # the whole cloud is there
            return short, extract(result, index, seeds), clearance

        short, values, clearance = together(g, work)
        done = short == 0
        if outputs is None:  # every row: the values stand, the pending rows' replaced in later rounds
            outputs = list(values)
        else:
            for out, v in zip(outputs, values):
                out[pending[done]] = v[done]
        need = float(short.max()) if short.numel() else 0.0
        wanted = float(g.reduce(torch.tensor([need], dtype=torch.float64, device=g.device), dist.ReduceOp.MAX)[0])
        if wanted == 0.0:
            return outputs
        left = (~done).nonzero().squeeze(1)
        pending, reach = (left if pending is None else pending[left]), 1.25 * (short[left] + clearance[left])
        width = max(2 * width, width + 1.25 * wanted)  # inf (or NaN: then the whole cloud) when a reach is
        if not width < math.inf:
            width = math.inf
    raise AssertionError("unreachable: the last round holds the whole cloud")


# near_seeds lists at most this many (seed, point) pairs by a radius search;
# beyond, it takes the points near the seeds along the cut axis alone.
NEAR_PAIRS = 1 << 23


def near_seeds(points: torch.Tensor, batch: Optional[torch.Tensor], seeds: torch.Tensor, reach: torch.Tensor,
               axis: int):
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
            found = _plain_radius(points.detach(), r, points[seeds].detach(), batch=batch,
                                  query_batch=batch[seeds] if batch is not None else None)
            rows = torch.unique(torch.cat([found.edge_index[0], seeds]))
            return rows, torch.full_like(reach, r)
    x = points[:, axis].double()
    return within_any(x, x[seeds], reach).nonzero().squeeze(1), reach


def within_any(x: torch.Tensor, centres: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
    """(N,) bool: the coordinates `x` within `reach` of one of `centres` (the
    union of the intervals centre +- reach)."""
    if centres.numel() == 0:
        return torch.zeros_like(x, dtype=torch.bool)
    starts, order = torch.sort(centres - reach)
    ends = torch.cummax((centres + reach)[order], 0).values
    at = torch.searchsorted(starts, x.contiguous(), right=True) - 1
    return (at >= 0) & (x <= ends[at.clamp_min(0)])


def cell_shortfall(cells: VoronoiCells, clearance: torch.Tensor) -> torch.Tensor:
    """(N,) float64 of every computed cell: how far twice its radius (with
    CERTIFY_SLACK) passes its clearance; inf where the cell failed."""
    failed = (cells.status != CellStatus.SUCCESS) & (cells.status != CellStatus.DUPLICATE)
    excess = cells.radius.to(torch.float64, copy=True).mul_(2 * (1 + CERTIFY_SLACK)).sub_(clearance).clamp_min_(0)
    return excess.nan_to_num_(nan=math.inf).masked_fill_(failed, math.inf)


def cell_columns(cells: VoronoiCells, rows=slice(None)) -> List[torch.Tensor]:
    """The fields of cells `rows` as they travel, a collective each (rows a
    slice: no copy); VoronoiCells(*columns) makes the cells again."""
    return [t[rows] for t in cells]
