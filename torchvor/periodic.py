"""Periodic boxes: the neighbour searches and the Voronoi cells of points on a torus.

A periodic axis of the box [lo, hi] repeats the cloud every ``hi - lo`` along
it. The ops here add the images of the points that lie within a margin of the
box's periodic faces, run the plain ops on the padded cloud, and keep what
belongs to the original points, mapped back to them:

- a neighbour search is exact for a query whose k-th distance (or radius)
  stays inside the margin; each point counts once, at its nearest image
  (the minimum-image convention);
- a Voronoi cell is exact when twice its radius (``VoronoiCells.radius``, the
  farthest vertex) stays inside the margin: no absent image can then cut it,
  nor can the padded box's walls. Cells that reach past the margin are
  computed again with a wider one, up to the images of every point.

Points are first wrapped into [lo, hi) along the periodic axes (a point
outside the box along one is its image inside). The cells' images lie below
lo alone (pad's one_sided), where they are exact for a box [0, L]: float32
cells are computed in float32 where every image is exact, else in float64
with the outputs rounded to float32 (a rounded image would move by a
rounding of the box's coordinates, which is large beside the cells of tight
clusters); the searches compute float32 in float64. Gradients flow through
the images to the points.
"""
from __future__ import annotations

import itertools
import math
from typing import NamedTuple, Optional, Tuple

import torch

from .ops import KNN, PeriodicLike, VoronoiCells, as_box, knn as _plain_knn


# A cell is certified when 2 radius (1 + CERTIFY_SLACK) is within the margin:
# the radius is that of the computed vertices, which an ill-conditioned vertex
# (nearly parallel planes) holds to less than the cell's volume.
CERTIFY_SLACK = 1e-2
# A first margin of this many mean spacings (the cube root of the volume a
# point) holds the cells of blue noise and nearly all of white noise's next to
# the faces; cells that reach further are computed again with the margin they
# need.
FIRST_MARGIN_SPACINGS = 3.0
# Rounds of a wider margin before the images of every point within the
# cells' reach (the last round certifies every cell: see _voronoi_images).
MARGIN_ROUNDS = 4


def periodic_axes(periodic: PeriodicLike, caller: str) -> Optional[Tuple[bool, bool, bool]]:
    """The periodic axes that `periodic` names (True: all three; a 3-sequence of
    bools: those), or None where none is periodic."""
    if periodic is None or periodic is False:
        return None
    if periodic is True:
        return (True, True, True)
    if isinstance(periodic, torch.Tensor):
        periodic = periodic.tolist()
    if isinstance(periodic, (tuple, list)) and len(periodic) == 3 and all(isinstance(p, bool) for p in periodic):
        return tuple(periodic) if any(periodic) else None
    raise ValueError(f"torchvor.{caller}: periodic must be True, False or three bools (x, y, z), got {periodic!r}")


class PeriodicBox(NamedTuple):
    """The box (B, 2, 3) of a periodic call, its periods and axes."""

    box: torch.Tensor      # (B, 2, 3)
    period: torch.Tensor   # (B, 3): hi - lo on periodic axes, 0 on the others
    axes: Tuple[bool, bool, bool]

    @property
    def mask(self) -> torch.Tensor:
        return torch.tensor(self.axes, device=self.box.device)

    def to(self, dtype: torch.dtype) -> "PeriodicBox":
        """The same box in `dtype`, its periods the differences of its corners
        there (a float32 period rounded, then widened, shifts float64 images by
        that rounding: 2e-3 of a sliver cell beside a face of a thin slab)."""
        box = self.box.to(dtype)
        edges = box[:, 1] - box[:, 0]
        return PeriodicBox(box, torch.where(self.mask, edges, torch.zeros_like(edges)), self.axes)


def periodic_box(points: torch.Tensor, box, batch: Optional[torch.Tensor], axes, caller: str) -> PeriodicBox:
    """The box of a periodic call, required, with positive periods."""
    if box is None:
        raise ValueError(f"torchvor.{caller}: periodic needs a box (its edges are the periods)")
    box_tensor = as_box(points, box, batch).to(points.dtype)
    clouds = _check_batch(batch, points, caller)
    if box_tensor.shape[0] == 1 and clouds > 1:
        box_tensor = box_tensor.expand(clouds, 2, 3)
    elif box_tensor.shape[0] < clouds:
        raise ValueError(f"torchvor.{caller}: batch refers to {clouds} point clouds but box holds "
                         f"{box_tensor.shape[0]}")
    mask = torch.tensor(axes, device=box_tensor.device)
    edges = box_tensor[:, 1] - box_tensor[:, 0]
    finite, positive = torch.stack([torch.isfinite(box_tensor).all(), (edges[:, mask] > 0).all()]).tolist()
    if not finite:
        raise ValueError(f"torchvor.{caller}: box contains NaN or Inf")
    if not positive:
        raise ValueError(f"torchvor.{caller}: the box is flat along a periodic axis (hi <= lo): "
                         f"a period must be positive, got box {box_tensor.tolist()}")
    period = torch.where(mask, edges, torch.zeros_like(edges))
    return PeriodicBox(box_tensor, period, axes)


def _check_batch(batch: Optional[torch.Tensor], points: torch.Tensor, caller: str) -> int:
    """The number of clouds of a batch vector (1 without), after the checks
    the ops make (the periodic calls index with it before they run)."""
    if batch is None:
        return 1
    if not isinstance(batch, torch.Tensor) or batch.dtype != torch.int64:
        raise TypeError(f"torchvor.{caller}: batch must be an int64 tensor")
    if batch.shape != (points.shape[0],):
        raise ValueError(f"torchvor.{caller}: batch must have shape ({points.shape[0]},), got {tuple(batch.shape)}")
    if batch.device != points.device:
        raise ValueError(f"torchvor.{caller}: batch is on {batch.device}, points on {points.device}")
    if batch.numel() == 0:
        return 1
    if bool((batch < 0).any()) or bool((batch[1:] < batch[:-1]).any()):
        raise ValueError(f"torchvor.{caller}: batch must be non-negative and sorted")
    return int(batch[-1]) + 1


def _per_point(values: torch.Tensor, batch: Optional[torch.Tensor], n: int) -> torch.Tensor:
    """Rows of a (B, ...) tensor for each of n points of batch vector `batch`."""
    if batch is None:
        return values[0].expand(n, *values.shape[1:])
    return values[batch]


def wrap(points: torch.Tensor, pbox: PeriodicBox, batch: Optional[torch.Tensor]) -> torch.Tensor:
    """The points moved into [lo, hi) along the periodic axes by whole periods
    (the others as given); a point on hi goes to lo exactly (the same point of
    the torus: lo + (hi - lo) can round away from hi). The shift is a
    constant: gradients pass unchanged."""
    n = points.shape[0]
    lo = _per_point(pbox.box[:, 0], batch, n)
    period = _per_point(pbox.period, batch, n)
    with torch.no_grad():
        periodic = period > 0
        below = _per_point(torch.where(pbox.period > 0, pbox.box[:, 0], -math.inf), batch, n)
        above = _per_point(torch.where(pbox.period > 0, pbox.box[:, 1], math.inf), batch, n)
        if bool(((points >= below) & (points < above)).all()):
            return points  # inside already (the usual case): the same tensor
        on_hi = periodic & (points == above)
        safe = torch.where(periodic, period, torch.ones_like(period))
        turns = torch.where(periodic, torch.floor((points - lo) / safe), torch.zeros_like(points))
        moved = points - turns * period
        # rounding can land a point on hi (or a hair below lo): take its image
        hi = lo + period
        turns = turns + torch.where(periodic & (moved >= hi), torch.ones_like(turns), torch.zeros_like(turns))
        turns = turns - torch.where(periodic & (moved < lo), torch.ones_like(turns), torch.zeros_like(turns))
        offset = turns * period
    inside = points - offset
    with torch.no_grad():  # a last rounding at hi: the point at lo is the same point
        at_hi = on_hi | (periodic & (inside >= hi))
    return torch.where(at_hi, lo + (points - points.detach()), inside)


class Padded(NamedTuple):
    """A cloud and the images of its points near the periodic faces."""

    points: torch.Tensor             # (P, 3): the points and their images, by batch element
    source: torch.Tensor             # (P,) int64: the point each row is an image of
    shift: torch.Tensor              # (P, 3) int8: the image's shift in periods
    batch: Optional[torch.Tensor]    # (P,) sorted, or None
    position: torch.Tensor           # (N,) int64: the row of each point itself
    box: torch.Tensor                # (B, 2, 3): the box widened by the margin on the periodic axes
    moved: torch.Tensor              # (M,) int64: the points whose own row is an image (one_sided)
    exact: torch.Tensor              # () bool: every image is its point plus shift * period without rounding


def pad(points: torch.Tensor, pbox: PeriodicBox, batch: Optional[torch.Tensor], margin: torch.Tensor,
        one_sided: bool = False) -> Padded:
    """`points` (wrapped) and every image of them within `margin` (B,) of the
    box along the periodic axes (on all of them at once), the margin capped
    at a period along each axis (axis_margins); `position` the points' own rows.

    one_sided: every image below lo instead, to a depth of twice the margin,
    and a point within the margin of hi has its own cell at its image below
    lo (`position`, `moved`). Every cell then keeps the same clearance as with
    images on both sides, and an image is ``x - k (hi - lo)`` for x near hi:
    exact in floating point where x and the period share their binade's
    spacing (a box [0, L], say), where ``x + (hi - lo)`` for x near lo rounds
    away the fine digits of points near 0."""
    n, device = points.shape[0], points.device
    margins = axis_margins(pbox, margin)
    depth = 2 * margins if one_sided else margins
    periodic = pbox.mask
    with torch.no_grad():
        lo = _per_point(pbox.box[:, 0], batch, n)
        hi = _per_point(pbox.box[:, 1], batch, n)
        d = _per_point(depth, batch, n)
        if one_sided:
            # below lo, down to lo - d: images of the points within d of hi, two periods deep at most
            near = ((hi - points) <= d) & periodic
            deep = bool((depth > pbox.period).any())
            steps = [range(-2 if deep else -1, 1) if a else range(1) for a in pbox.axes]
        else:
            # points with an image within the margin: near a periodic face (all of them where it is a period)
            m = _per_point(margins, batch, n)
            near = (((points - lo) < m) | ((hi - points) < m) | (m >= _per_point(pbox.period, batch, n))) & periodic
            steps = [range(-1, 2) if a else range(1) for a in pbox.axes]
        candidates = near.any(1).nonzero().squeeze(1)
        shifts = torch.tensor([s for s in itertools.product(*steps) if any(s)], dtype=torch.int64,
                              device=device).reshape(-1, 3)
        sub_batch = batch[candidates] if batch is not None else None
        c = candidates.numel()
        p = points.detach()[candidates].unsqueeze(1)                       # (C, 1, 3)
        per = _per_point(pbox.period, sub_batch, c).unsqueeze(1)           # (C, 1, 3)
        low = _per_point(pbox.box[:, 0], sub_batch, c).unsqueeze(1)
        high = _per_point(pbox.box[:, 1], sub_batch, c).unsqueeze(1)
        dd = _per_point(depth, sub_batch, c).unsqueeze(1)
        step = shifts.to(points.dtype) * per                               # (C, S, 3)
        image = p + step
        keep = (image >= low - dd) & (image <= high + (0 if one_sided else dd))
        if one_sided:
            keep &= image < high
        keep = (keep | ~periodic).all(2)
        # shift-major, as the images are laid out: every image of one shift, then the next
        which, row = keep.t().nonzero().unbind(1)
        source = torch.cat([torch.arange(n, device=device), candidates[row]])
        shift = torch.zeros(n + row.numel(), 3, dtype=torch.int8, device=device)
        shift[n:] = shifts[which].to(torch.int8)
        exact = (_rounding_error(p.squeeze(1)[row], step[row, which]) == 0).all()
        position = torch.arange(n, device=device)
        moved = position[:0]
        if one_sided:  # the points within the margin of hi: their own cell is their image at shift -1 there
            m = _per_point(margins, sub_batch, c)
            own_shift = torch.where(periodic & ((high.squeeze(1) - p.squeeze(1)) <= m), -1, 0)
            mine = (shifts[which] == own_shift[row]).all(1).nonzero().squeeze(1)
            moved = candidates[row[mine]]
            position[moved] = n + mine
    images = points[source[n:]] + step[row, which]  # the images above, now with the points' gradient
    padded = torch.cat([points, images])
    padded_batch = None
    if batch is not None:
        with torch.no_grad():
            padded_batch = torch.cat([batch, batch[source[n:]]])
            order = torch.sort(padded_batch, stable=True).indices
            padded_batch = padded_batch[order]
            source, shift = source[order], shift[order]
            row_of = torch.empty_like(order)
            row_of[order] = torch.arange(order.numel(), device=device)
            position = row_of[position]
        padded = padded[order]
    widened = pbox.box.clone()
    grow = depth.to(widened.dtype)
    widened[:, 0] -= grow
    if not one_sided:
        widened[:, 1] += grow
    return Padded(padded, source, shift, padded_batch, position, widened, moved, exact)


def _rounding_error(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """What a + b loses to rounding in their dtype (Knuth's TwoSum: exact,
    whatever their magnitudes, short of overflow)."""
    total = a + b
    b_part = total - a
    return (a - (total - b_part)) + (b - b_part)


def images_exact(given: torch.Tensor, x: torch.Tensor, padded: Padded, pbox: PeriodicBox,
                 batch: Optional[torch.Tensor]) -> bool:
    """Whether the wrapped points `x` (and `padded`'s images of them, each
    ``x + shift * period`` in x's dtype) are the `given` points moved by
    exactly whole periods, and the periods (in x's dtype) exactly the box's
    corners' differences."""
    with torch.no_grad():
        n = x.shape[0]
        box = pbox.box.to(x.dtype)
        exact = padded.exact & (_rounding_error(box[:, 1], -box[:, 0])[:, pbox.mask] == 0).all()
        if given is not x:  # wrap returns the points themselves where they lie inside
            # x = given - turns * period where given lay outside: each subtraction exact
            period = _per_point(torch.where(pbox.mask, box[:, 1] - box[:, 0], torch.zeros_like(box[:, 0])), batch, n)
            given = given.detach().to(x.dtype)
            safe = torch.where(period > 0, period, torch.ones_like(period))
            moved = torch.round((given - x.detach()) / safe) * period
            exact &= ((given - moved) == x.detach()).all() & (_rounding_error(given, -moved) == 0).all()
        return bool(exact)


def axis_margins(pbox: PeriodicBox, margin: torch.Tensor) -> torch.Tensor:
    """(B, 3): `margin` along each periodic axis, capped at its period (0 on
    the others). A point within a period of the box along an axis holds the
    nearest image, along it, of every point to anything within half a period
    of the box; and a cell lies within half a period of its point (its own
    images bound it). So images past a period never cut a cell, and an axis
    padded by a whole period leaves no image out that could."""
    return torch.where(pbox.mask, torch.minimum(margin.unsqueeze(1).to(pbox.period.dtype), pbox.period),
                       torch.zeros_like(pbox.period))


def face_distance(points: torch.Tensor, pbox: PeriodicBox, batch: Optional[torch.Tensor],
                  margin: torch.Tensor) -> torch.Tensor:
    """(N,) float64: each (wrapped) point's distance to the nearest face of its
    box along a periodic axis that `margin` pads by less than a period (inf
    where there is none: no image that could cut a cell is left out)."""
    n = points.shape[0]
    lo = _per_point(pbox.box[:, 0], batch, n).double()
    hi = _per_point(pbox.box[:, 1], batch, n).double()
    short = _per_point(pbox.mask & (axis_margins(pbox, margin) < pbox.period), batch, n)
    p = points.detach().double()
    gap = torch.minimum(p - lo, hi - p).clamp_min(0)
    gap = torch.where(short, gap, torch.full_like(gap, math.inf))
    return gap.amin(1)


def first_margin(pbox: PeriodicBox, batch: Optional[torch.Tensor], n: int, per_point: float,
                 counts: Optional[torch.Tensor] = None) -> torch.Tensor:
    """(B,) a margin of `per_point` times the mean spacing of each batch
    element (`counts`: the points of each, if not those of `batch`)."""
    if counts is None:
        counts = cloud_counts(pbox, batch, n)
    counts = counts.to(torch.float64)
    volume = (pbox.box[:, 1] - pbox.box[:, 0]).double().prod(1)
    spacing = (volume / counts.clamp_min(1)) ** (1.0 / 3.0)
    return (per_point * spacing).to(pbox.box.dtype)


def cloud_counts(pbox: PeriodicBox, batch: Optional[torch.Tensor], n: int) -> torch.Tensor:
    """(B,) int64: the points of each batch element."""
    if batch is None:
        return torch.tensor([n], device=pbox.box.device)
    return torch.bincount(batch, minlength=pbox.box.shape[0])


def work_dtype(points: torch.Tensor) -> torch.dtype:
    """The dtype periodic calls compute in (module docstring)."""
    return torch.float64 if points.dtype == torch.float32 else points.dtype


def image_shift(offset_j: torch.Tensor, offset_i: torch.Tensor, shift: torch.Tensor,
                period: torch.Tensor) -> torch.Tensor:
    """The shift (in periods) of the image of j that i sees, in the caller's
    coordinates (wrap moved each point by an offset of whole periods)."""
    safe = torch.where(period > 0, period, torch.ones_like(period))
    moved = torch.round((offset_i - offset_j) / safe).to(torch.int64)
    return shift + torch.where(period > 0, moved, torch.zeros_like(moved))


# ---- neighbour searches ----------------------------------------------------

def _search_inputs(points, queries, batch, query_batch, pbox: PeriodicBox, caller: str):
    """(box in the work dtype, points, queries) of a search, wrapped into the
    box; `queries` None: the points themselves."""
    dtype = work_dtype(points)
    pbox = pbox.to(dtype)
    x = wrap(points.to(dtype), pbox, batch)
    if queries is None:
        return pbox, x, x
    _check_batch(query_batch, queries, caller)
    return pbox, x, wrap(queries.to(dtype), pbox, query_batch)


def _sort_rows(dist2: torch.Tensor, source: torch.Tensor, shift: Optional[torch.Tensor] = None):
    """Each row by (distance, index) as the plain searches order it (missing last)."""
    key = torch.where(source >= 0, source, torch.full_like(source, torch.iinfo(torch.int64).max))
    order = torch.sort(key, dim=1, stable=True).indices
    dist2, source = dist2.gather(1, order), source.gather(1, order)
    again = torch.sort(dist2.detach(), dim=1, stable=True).indices
    return dist2.gather(1, again), source.gather(1, again)


def knn(points, k, queries, batch, query_batch, exclude_self, pbox: PeriodicBox) -> KNN:
    """torchvor.knn on the torus (see the module docstring): each point at
    most once a row, at its nearest image. `queries` None: the points."""
    out_dtype, dtype = points.dtype, work_dtype(points)
    pbox, x, q = _search_inputs(points, queries, batch, query_batch, pbox, "knn")
    m, n = q.shape[0], x.shape[0]
    dist2 = torch.full((m, k), math.inf, dtype=dtype, device=x.device)
    index = torch.full((m, k), -1, dtype=torch.int64, device=x.device)
    if m == 0 or n == 0:
        return KNN(dist2.to(out_dtype), index)
    margin = first_margin(pbox, batch, n, FIRST_MARGIN_SPACINGS) * max(1.0, (k / 20) ** (1 / 3))
    # clouds with no more points than a row holds: every pair at once
    counts = torch.bincount(batch, minlength=pbox.box.shape[0]) if batch is not None else torch.tensor([n], device=x.device)
    small = _per_point(counts, query_batch, m) <= k + int(bool(exclude_self))
    brute = [torch.arange(m, device=x.device)[small]]
    rows = torch.arange(m, device=x.device)[~small]
    shortest_period = float(pbox.period[:, pbox.mask].double().min())
    done_dist2, done_index, done_rows = [], [], []
    for _ in range(MARGIN_ROUNDS):
        if rows.numel() == 0:
            break
        padded = pad(x, pbox, batch, margin)
        gap = face_distance(q, pbox, query_batch, margin)
        extra = 1 if exclude_self else 0
        sub_batch = None if query_batch is None else query_batch[rows]
        found = _plain_knn(padded.points, k + extra, q[rows], batch=padded.batch, query_batch=sub_batch)
        d2, idx = found.dist2, found.idx
        if exclude_self:  # drop the query's own row of the padded cloud, wherever it sorts among ties
            itself = idx == padded.position[rows].unsqueeze(1)
            at = torch.where(itself.any(1), itself.to(torch.int8).argmax(1), k)
            step = torch.arange(k, device=x.device)
            keep = step + (step >= at.unsqueeze(1)).to(step.dtype)
            d2, idx = d2.gather(1, keep), idx.gather(1, keep)
        source = torch.where(idx >= 0, padded.source[idx.clamp_min(0)], idx)
        # rows come sorted by distance; ties by padded row, which an image breaks: those rows again by index
        tied = ((d2[:, 1:] == d2[:, :-1]) & (source[:, 1:] >= 0)).any(1)
        if bool(tied.any()):
            which = tied.nonzero().squeeze(1)
            tied_d2, tied_source = _sort_rows(d2[which], source[which])
            d2, source = d2.index_put((which,), tied_d2), source.index_put((which,), tied_source)
        # exact: the k-th distance within the margin, and no point twice
        reach = (margin[sub_batch] if sub_batch is not None else margin[0].expand(rows.numel())).double()
        last = d2[:, -1].detach().double()
        inside = torch.sqrt(last) <= reach + gap[rows]
        # two images of a point in one row lie a period apart: only where the k-th distance reaches half a period
        if bool((4 * last[torch.isfinite(last)] >= shortest_period ** 2).any()):
            unique = torch.sort(source, dim=1).values
            twice = ((unique[:, 1:] == unique[:, :-1]) & (unique[:, 1:] >= 0)).any(1)
        else:
            twice = torch.zeros_like(inside)
        ok = inside & ~twice
        done_dist2.append(d2[ok]), done_index.append(source[ok]), done_rows.append(rows[ok])
        brute.append(rows[twice])
        retry = ~ok & ~twice
        need = torch.sqrt(last[retry]) - gap[rows[retry]]
        rows = rows[retry]
        if rows.numel():
            wanted = torch.zeros_like(margin).scatter_reduce(
                0, query_batch[rows] if query_batch is not None else torch.zeros_like(rows),
                (1.25 * need).to(margin.dtype), "amax")
            margin = torch.maximum(2 * margin, wanted)
    brute = torch.cat([*brute, rows])
    if brute.numel():
        d2, source = _brute_force_knn(x, q, k, brute, batch, query_batch, exclude_self, pbox)
        done_dist2.append(d2), done_index.append(source), done_rows.append(brute)
    all_rows = torch.cat(done_rows)
    dist2 = dist2.index_put((all_rows,), torch.cat(done_dist2))
    index = index.index_put((all_rows,), torch.cat(done_index))
    return KNN(dist2.to(out_dtype), index)


def minimum_image(difference: torch.Tensor, period: torch.Tensor) -> torch.Tensor:
    """The difference of two positions moved by whole periods to its shortest form."""
    safe = torch.where(period > 0, period, torch.ones_like(period))
    turns = torch.where(period > 0, torch.round(difference.detach() / safe), torch.zeros_like(difference))
    return difference - turns * period


def _brute_force_knn(x, q, k, rows, batch, query_batch, exclude_self, pbox, chunk_pairs=1 << 24):
    """The k nearest points at their nearest images for queries `rows`, every
    pair at once (clouds small beside k)."""
    n = x.shape[0]
    out_d2, out_index = [], []
    step = max(1, chunk_pairs // max(1, n))
    for start in range(0, rows.numel(), step):
        part = rows[start:start + step]
        period = _per_point(pbox.period, query_batch, q.shape[0])[part]
        difference = minimum_image(x.unsqueeze(0) - q[part].unsqueeze(1), period.unsqueeze(1))
        d2 = (difference * difference).sum(2)
        if batch is not None:
            d2 = torch.where(batch.unsqueeze(0) == query_batch[part].unsqueeze(1), d2, torch.full_like(d2, math.inf))
        if exclude_self:
            d2 = d2.index_put((torch.arange(part.numel(), device=x.device), part),
                          torch.tensor(math.inf, dtype=d2.dtype, device=d2.device))
        index = torch.arange(n, device=x.device).expand(part.numel(), n)
        d2s, idx = _sort_rows(d2, index)
        d2s, idx = d2s[:, :k], idx[:, :k]
        if idx.shape[1] < k:
            fill = k - idx.shape[1]
            d2s = torch.cat([d2s, torch.full((part.numel(), fill), math.inf, dtype=d2s.dtype, device=x.device)], 1)
            idx = torch.cat([idx, torch.full((part.numel(), fill), -1, dtype=idx.dtype, device=x.device)], 1)
        idx = torch.where(torch.isinf(d2s), torch.full_like(idx, -1), idx)
        out_d2.append(d2s), out_index.append(idx)
    return torch.cat(out_d2), torch.cat(out_index)


def radius(points, r, queries, batch, query_batch, max_num_neighbors, exclude_self, pbox: PeriodicBox):
    """torchvor.radius on the torus: (idx, row, dist2) of every point within r
    of each query at its nearest image, sorted by query, distance, index."""
    from .radius import radius as _plain_radius

    out_dtype, dtype = points.dtype, work_dtype(points)
    pbox, x, q = _search_inputs(points, queries, batch, query_batch, pbox, "radius")
    margin = torch.full((pbox.box.shape[0],), float(r), dtype=dtype, device=x.device)
    padded = pad(x, pbox, batch, margin)
    found = _plain_radius(padded.points, r, q, batch=padded.batch, query_batch=query_batch)
    idx, row = found.edge_index
    dist2 = found.dist2
    if exclude_self:
        keep = idx != padded.position[row]
        idx, row, dist2 = idx[keep], row[keep], dist2[keep]
    source = padded.source[idx]
    # two images of a point within r of a query only where 2 r reaches a period
    periods = pbox.period[:, list(i for i, a in enumerate(pbox.axes) if a)]
    if idx.numel() and 2 * r >= float(periods.min()):
        order = _lexsort([row, source, dist2.detach()])
        row, source, dist2 = row[order], source[order], dist2[order]
        first = torch.ones_like(row, dtype=torch.bool)
        first[1:] = (row[1:] != row[:-1]) | (source[1:] != source[:-1])
        row, source, dist2 = row[first], source[first], dist2[first]
    order = _lexsort([row, dist2.detach(), source])
    row, source, dist2 = row[order], source[order], dist2[order]
    if max_num_neighbors is not None and row.numel():
        start = torch.searchsorted(row, row, side="left")
        keep = (torch.arange(row.numel(), device=row.device) - start) < max_num_neighbors
        row, source, dist2 = row[keep], source[keep], dist2[keep]
    return source, row, dist2.to(out_dtype)


def _lexsort(keys):
    """The order that sorts by keys[0], then keys[1], ... (stable sorts, last key first)."""
    order = torch.sort(keys[-1], stable=True).indices
    for key in reversed(keys[:-1]):
        order = order[torch.sort(key[order], stable=True).indices]
    return order


# ---- Voronoi cells -----------------------------------------------------------

class PeriodicCells(NamedTuple):
    cells: VoronoiCells        # in the work dtype
    given: torch.Tensor        # (N, 3): the points in the work dtype
    x: torch.Tensor            # (N, 3): wrapped (`given` itself where every point lies inside)
    seed: torch.Tensor         # (N, 3): where each point's cell was computed (x, or an image of it)
    moved: Optional[torch.Tensor]  # (M,) int64 sorted: the points whose seed is not the point (None: any)
    padded: Padded
    graph: Optional[object]    # the padded cloud's VoronoiGraph, where asked

    def offset(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 3) float64: each point of `rows` minus the seed of its cell."""
        return self.given.detach()[rows].double() - self.seed[rows].double()

    def wrap_offset(self, rows: torch.Tensor) -> torch.Tensor:
        """(R, 3) float64: each point of `rows` minus its wrapped position."""
        return self.given.detach()[rows].double() - self.x.detach()[rows].double()


def _full_reach(pbox: PeriodicBox) -> torch.Tensor:
    """(B,) a margin that certifies every cell: a period along every periodic
    axis (axis_margins)."""
    longest = torch.where(pbox.mask, pbox.period, torch.zeros_like(pbox.period)).amax(1)
    return longest * (1 + 1e-3)


class _InexactImages(Exception):
    """A float32 call's images would round: it runs again in float64."""


class Agreement:
    """How cells() decides and computes: in one process (this class), or over
    the ranks of a process group (torchvor.distributed), where each rank pads
    its own points, every decision is taken together and the plain cells are
    computed over every rank's padded points."""

    alone = True  # cells that reach past the margin may be computed again alone (_recompute)

    def counts(self, pbox: PeriodicBox, batch: Optional[torch.Tensor], n: int) -> torch.Tensor:
        """(B,) the points of each batch element."""
        return cloud_counts(pbox, batch, n)

    def all(self, flag: bool) -> bool:
        return flag

    def any(self, flags: torch.Tensor) -> bool:
        return bool(flags.any())

    def max(self, values: torch.Tensor) -> torch.Tensor:
        """`values`, each the largest any caller holds."""
        return values

    def rows(self, points, box, rows, batch, k, memory_budget, weights=None) -> VoronoiCells:
        """The cells of `points[rows]` among `points` (ops._voronoi_rows; the
        power cells with `weights`, differentiable in them)."""
        return _rows(points, box, rows, batch, k, memory_budget, weights)


def _rows(points, box, rows, batch, k, memory_budget, weights=None) -> VoronoiCells:
    """Agreement.rows in one process."""
    from .ops import _voronoi_rows
    from .power import voronoi as _power_rows

    if weights is None:
        return _voronoi_rows(points, box, rows, batch, k, memory_budget)
    return _power_rows(points, weights, box, batch, k, memory_budget, rows=rows)


ONE_PROCESS = Agreement()


def cells(points, pbox: PeriodicBox, batch, k, memory_budget, graph: bool,
          agreement: Agreement = ONE_PROCESS, weights: Optional[torch.Tensor] = None) -> PeriodicCells:
    """The periodic cells of `points` (and the padded cloud's graph with
    `graph`): padded below lo with images (pad's one_sided) until every
    computed cell is certified (module docstring). Without `graph`, the cells
    that reach past the margin are computed again alone, among the points
    within their reach of a wider padding; with it, everything is (the edges
    of a cell come with their neighbours'). float32 points are computed in
    float32 where every image is exact (images_exact), else in float64.
    `agreement`: where the decisions are taken and the plain cells computed
    (Agreement; the graph in one process only). `weights` (N,): the power
    cells (checked weights), whose images carry their point's weight and
    whose reach is that of the power radius of security (_reach)."""
    if points.dtype == torch.float32:
        try:
            return _cells(points, pbox, batch, k, memory_budget, graph, torch.float32, agreement, weights)
        except _InexactImages:
            pass
    return _cells(points, pbox, batch, k, memory_budget, graph, work_dtype(points), agreement, weights)


def _cells(points, pbox: PeriodicBox, batch, k, memory_budget, graph: bool, dtype: torch.dtype,
           agree: Agreement, weights: Optional[torch.Tensor]) -> PeriodicCells:

    exact_only = dtype == torch.float32
    given_box = pbox
    pbox = pbox.to(dtype)
    given = points.to(dtype)
    x = wrap(given, pbox, batch)
    n = x.shape[0]
    w = None if weights is None else weights.to(dtype)
    full = _full_reach(pbox)
    margin = torch.minimum(first_margin(pbox, batch, n, FIRST_MARGIN_SPACINGS, agree.counts(pbox, batch, n)), full)
    power = None if w is None else _PowerReach(w, x, pbox, batch, k, memory_budget)
    one_sided = True  # until an image would round: then both sides, the points' cells in place
    for round_ in range(MARGIN_ROUNDS + 1):
        padded = pad(x, pbox, batch, margin, one_sided=one_sided)
        if one_sided and not agree.all(images_exact(points, x, padded, given_box, batch)):
            if exact_only:
                raise _InexactImages()
            one_sided = False
            padded = pad(x, pbox, batch, margin)
        padded_weights = None if w is None else w[padded.source]
        if graph:
            result = _padded_graph(padded, padded_weights, k, memory_budget)
            own = VoronoiCells(*(t.index_select(0, padded.position) for t in result.cells))
        else:  # the images only bound the points' cells: theirs are not computed
            result = None
            own = agree.rows(padded.points, padded.box, padded.position, padded.batch, k, memory_budget,
                             padded_weights)
        seed = padded.points.detach().index_select(0, padded.position)  # where each point's cell was computed
        moved = [padded.moved]
        within = clearance(padded, pbox, batch, margin, _reach(own, power))
        short = _reaching_past(own, within, power)
        if not graph and agree.alone:  # the few cells that reach past the margin, alone
            for again in range(MARGIN_ROUNDS):
                if not bool(short.any()) or not _few_pairs(x, own, short, pbox, batch, power):
                    break  # none left, or so many that the whole cloud runs again (below)
                margin = _wider(margin, own, short, x, pbox, batch, full, one_sided, power,
                                last=again == MARGIN_ROUNDS - 1)
                own, within, seed, one_sided = _recompute(points if exact_only else None, given_box, x, pbox, batch,
                                                          own, within, seed, short, margin, k, memory_budget,
                                                          one_sided, w, power)
                moved.append(short.nonzero().squeeze(1))
                short = _reaching_past(own, within, power)
        if not agree.any(short):
            break
        if bool((margin >= full).all()):
            raise RuntimeError("torchvor: internal error: a periodic cell reaches past every image of the cloud")
        margin = agree.max(_wider(margin, own, short, x, pbox, batch, full, one_sided, power,
                                  last=round_ == MARGIN_ROUNDS - 1))
    moved = torch.unique(torch.cat(moved)) if x is given else None
    return PeriodicCells(own, given, x, seed, moved, padded, result)


def clearance(padded: Padded, pbox: PeriodicBox, batch: Optional[torch.Tensor], margin: torch.Tensor,
              reach: Optional[torch.Tensor] = None, rows: Optional[torch.Tensor] = None) -> torch.Tensor:
    """The distance from each point's own cell seed (its row `position`) to
    the nearest face of the padded box along a periodic axis that `margin`
    pads by less than a period (inf where there is none: no image that could
    cut a cell is left out), float64: (R,) at the points `rows`, or (N,) at
    every point given each one's `reach`. Every seed clears the margin (pad),
    so the distance is computed only where the reach passes that, and is the
    margin elsewhere."""
    n = padded.position.numel()
    margins = axis_margins(pbox, margin).double()
    short_axes = pbox.mask & (margins < pbox.period.double())
    if rows is not None:
        within = torch.empty(rows.numel(), dtype=torch.float64, device=margin.device)
        at = torch.arange(rows.numel(), device=margin.device)
    else:
        least = torch.where(short_axes, margins, torch.full_like(margins, math.inf)).amin(1)
        within = _per_point(least, batch, n).clone()
        rows = at = (~(reach <= within)).nonzero().squeeze(1)
    sub_batch = batch[rows] if batch is not None else None
    box = padded.box.double()
    lo, hi = _per_point(box[:, 0], sub_batch, rows.numel()), _per_point(box[:, 1], sub_batch, rows.numel())
    p = padded.points.detach()[padded.position[rows]].double()
    gap = torch.minimum(p - lo, hi - p).clamp_min(0)
    gap = torch.where(_per_point(short_axes, sub_batch, rows.numel()), gap, torch.full_like(gap, math.inf))
    return within.index_put((at,), gap.amin(1))


def _padded_graph(padded: Padded, weights: Optional[torch.Tensor], k, memory_budget):
    """The VoronoiGraph of the padded cloud (the power diagram's with `weights`)."""
    from .graph import VoronoiGraph, voronoi_graph as _plain_graph
    from .power import voronoi_graph as _power_graph

    if weights is None:
        return _plain_graph(padded.points, padded.box, batch=padded.batch, k=k, on_failure="flag",
                            memory_budget=memory_budget)
    cells, edge_index, area, centroid, wall_area = _power_graph(padded.points, weights, padded.box, padded.batch, k,
                                                                memory_budget)
    return VoronoiGraph(edge_index, area, centroid, wall_area, cells)


class _PowerReach:
    """How far the images must reach for the power cells of weights `w` (N,)
    in the work dtype (see _reach)."""

    def __init__(self, w: torch.Tensor, x: torch.Tensor, pbox: PeriodicBox, batch: Optional[torch.Tensor], k,
                 memory_budget):
        from .power import _weight_max

        self.w = w.detach().double()
        self.x, self.pbox, self.batch, self.k, self.memory_budget = x, pbox, batch, k, memory_budget
        clouds, n = pbox.box.shape[0], self.w.shape[0]
        self.spread = (_per_point(_weight_max(self.w, batch, clouds), batch, n) - self.w).clamp_min(0)
        self._lowest = -_per_point(_weight_max(-self.w, batch, clouds), batch, n)
        self._covering = None

    def empty_reach(self) -> torch.Tensor:
        """(N,) float64: ``sqrt(rho^2 + w_i - min w)``, rho the farthest any
        point of the box lies from its nearest point (the largest radius of
        the plain periodic cells, computed once): the true cell of i lies
        within it of x_i (its points are no farther, in power, than from
        their nearest point). An empty cell computed in a box this wide
        around its point is empty."""
        if self._covering is None:
            plain = cells(self.x.detach(), self.pbox, self.batch, self.k, self.memory_budget, graph=False).cells
            radius = plain.radius.double()
            rho = torch.zeros(self.pbox.box.shape[0], dtype=torch.float64, device=radius.device)
            rho = rho.scatter_reduce(0, self.batch if self.batch is not None else torch.zeros_like(plain.status,
                                     dtype=torch.int64), radius, "amax")
            self._covering = _per_point(rho, self.batch, radius.shape[0])
        return torch.sqrt(self._covering.square() + (self.w - self._lowest).clamp_min(0))


def _reach(own: VoronoiCells, power: Optional[_PowerReach] = None) -> torch.Tensor:
    """(N,) float64: how far each cell's images must be for none to cut it,
    with CERTIFY_SLACK (NaN where not computed): twice its radius R; for a
    power cell, ``R + sqrt(R^2 + max w - w_i)`` (a point j can cut it only
    within ``R + sqrt(R^2 + w_j - w_i)``), and for an empty one
    _PowerReach.empty_reach."""
    from .ops import CellStatus
    from .power import _power_reach

    r = own.radius.detach().double()
    if power is None:
        return 2 * r * (1 + CERTIFY_SLACK)
    reach = _power_reach(r, power.spread)
    empty = own.status == CellStatus.EMPTY
    if bool(empty.any()):
        reach = torch.where(empty, power.empty_reach(), reach)
    return reach * (1 + CERTIFY_SLACK)


def _reaching_past(own: VoronoiCells, within: torch.Tensor, power: Optional[_PowerReach] = None) -> torch.Tensor:
    """(N,) bool: computed cells whose reach (_reach) passes `within` (the
    distance to the nearest image or wall left out)."""
    from .ops import CellStatus

    computed = (own.status == CellStatus.SUCCESS) | (own.status == CellStatus.DUPLICATE) | \
        (own.status == CellStatus.EMPTY)
    return computed & ~(_reach(own, power) <= within)


# _recompute's radius search lists this many (cell, point) pairs at most; past
# it the whole padded cloud runs again.
RECOMPUTE_PAIRS = 1 << 23


def _few_pairs(x, own, short, pbox: PeriodicBox, batch, power=None) -> bool:
    """Whether _recompute's search for the cells `short` lists at most
    RECOMPUTE_PAIRS pairs, estimated at each cloud's mean density."""
    counts = (torch.bincount(batch, minlength=pbox.box.shape[0]) if batch is not None
              else torch.tensor([x.shape[0]], device=x.device)).double()
    density = float((counts / (pbox.box[:, 1] - pbox.box[:, 0]).double().prod(1)).max())
    r = float(1.25 * _reach(own, power)[short].max())
    return int(short.sum()) * density * 27 * min(r, float(pbox.period.max())) ** 3 <= RECOMPUTE_PAIRS


def _wider(margin, own, short, x, pbox: PeriodicBox, batch, full, one_sided: bool, power, last: bool):
    """The margin the cells `short` ask for (a quarter more), at least a
    quarter more than before, at most `full` (the last round: `full`). For a
    reach c, a point at distances b above lo and a below hi along an axis
    asks for c - min(a, b) with images on both sides; with one-sided
    padding, for (c - b) / 2 (its cell in place, where a >= c), or for
    (c + a) / 2 and at least a (its cell at its image below lo)."""
    if last:
        return full
    u = short.nonzero().squeeze(1)
    sub_batch = batch[u] if batch is not None else None
    lo = _per_point(pbox.box[:, 0], sub_batch, u.numel()).double()
    hi = _per_point(pbox.box[:, 1], sub_batch, u.numel()).double()
    p = x[u].detach().double()
    below, above = p - lo, hi - p
    c = _reach(own, power)[u].unsqueeze(1)
    if one_sided:
        in_place = torch.where(above >= c, ((c - below) / 2).clamp_min(0), torch.full_like(above, math.inf))
        at_image = torch.maximum((c + above) / 2, above)
        ask = torch.minimum(in_place, at_image)
    else:
        ask = (c - torch.minimum(below, above)).clamp_min(0)
    need = torch.where(pbox.mask, ask, torch.zeros_like(above)).amax(1) * 1.25
    wanted = torch.zeros_like(margin).scatter_reduce(
        0, sub_batch if sub_batch is not None else torch.zeros_like(u), need.to(margin.dtype), "amax")
    return torch.minimum(torch.maximum(1.25 * margin, wanted), full)


def _recompute(points, given_box, x, pbox, batch, own, within, seed, short, margin, k, memory_budget, one_sided,
               weights=None, power=None):
    """The cells `short` computed again among the points of the cloud padded
    by `margin` that lie within a quarter more than their reach: their rows
    of `own` replaced, `within` with the distance to the nearest point left
    out (the padding's edge, or that reach), and `seed` with where they were
    computed; and whether the padding stayed one-sided (it turns two-sided
    where an image would round). `points`: the given float32 points whose
    images must be exact (images_exact), or None; `weights` (N,), `power`:
    the power cells' weights and _PowerReach."""
    from .radius import radius as _plain_radius

    u = short.nonzero().squeeze(1)
    wider = pad(x, pbox, batch, margin, one_sided=one_sided)
    if one_sided and not images_exact(points if points is not None else x, x, wider, given_box, batch):
        if points is not None:
            raise _InexactImages()
        one_sided = False
        wider = pad(x, pbox, batch, margin)
    r = float(1.25 * _reach(own, power)[u].max())
    seeds = wider.position[u]
    found = _plain_radius(wider.points.detach(), r, wider.points[seeds].detach(), batch=wider.batch,
                          query_batch=batch[u] if batch is not None else None)
    keep = torch.unique(torch.cat([found.edge_index[0], seeds]))  # sorted: batch order kept
    rows = torch.searchsorted(keep, seeds)
    sub = _rows(wider.points[keep], wider.box, rows, wider.batch[keep] if batch is not None else None, k,
                memory_budget, None if weights is None else weights[wider.source[keep]])
    own = VoronoiCells(*(t.index_copy(0, u, s) for t, s in zip(own, sub)))
    reach = torch.minimum(clearance(wider, pbox, batch, margin, rows=u), torch.full_like(within[u], r))
    return own, within.index_copy(0, u, reach), seed.index_copy(0, u, wider.points.detach()[seeds]), one_sided


def voronoi(points, pbox, batch, k, memory_budget, weights=None) -> VoronoiCells:
    """torchvor.voronoi on the torus: centroids near their points (each
    point plus the centroid's offset from it within the cell); the power
    cells with `weights`."""
    found = cells(points, pbox, batch, k, memory_budget, graph=False, weights=weights)
    return _caller_cells(found, points.dtype)


def _caller_cells(found: PeriodicCells, dtype: torch.dtype) -> VoronoiCells:
    """The cells in the caller's dtype, centroids moved to the given points
    (by the offset of their seeds, where that is not 0)."""
    c = found.cells
    if found.moved is None:
        centroid = (c.centroid.double() + found.offset(slice(None))).to(dtype)
    else:
        rows = found.moved
        centroid = c.centroid.to(dtype).index_put((rows,), (c.centroid[rows].double() + found.offset(rows)).to(dtype))
    return VoronoiCells(c.volume.to(dtype), centroid, c.second_moment.to(dtype), c.status, c.neighbors_needed,
                        c.radius.to(dtype))


def voronoi_graph(points, pbox, batch, k, memory_budget, weights=None):
    """torchvor.voronoi_graph on the torus: (cells, edge_index, area, centroid,
    wall_area, shift), edges sorted by cell, neighbour, then shift; the power
    diagram's with `weights`."""
    found = cells(points, pbox, batch, k, memory_budget, graph=True, weights=weights)
    padded, graph = found.padded, found.graph
    dtype = points.dtype
    n = points.shape[0]
    own_row = torch.zeros(padded.points.shape[0], dtype=torch.bool, device=points.device)
    own_row[padded.position] = True
    j_row, i_row = graph.edge_index
    keep = own_row[i_row]
    j_row, i_row = j_row[keep], i_row[keep]
    i, j = padded.source[i_row], padded.source[j_row]
    period = _per_point(pbox.period.double(), batch, n)
    shift = image_shift(found.wrap_offset(j), found.wrap_offset(i),
                        padded.shift[j_row].long() - padded.shift[i_row].long(), period[i])
    if shift.numel() and int(shift.abs().max()) > 127:
        raise ValueError("torchvor.voronoi_graph: points lie more than 127 periods from the box; "
                         "wrap them into it first (shift is int8)")
    code = ((shift + 128) * torch.tensor([65536, 256, 1], device=shift.device)).sum(1)
    order = _lexsort([i, j, code])
    i, j, shift, i_row = i[order], j[order], shift[order], i_row[order]
    area = graph.area[keep][order]
    centroid = graph.centroid[keep][order].double() + found.offset(i)
    cells_out = _caller_cells(found, dtype)
    wall_area = graph.wall_area[padded.position].to(dtype)
    return cells_out, torch.stack([j, i]), area.to(dtype), centroid.to(dtype), wall_area, shift.to(torch.int8)
