"""Power (Laguerre) diagrams, and the weights that give every cell a prescribed volume.

The power cell of point i with weight w_i is the set of points y of its box
with ``|y - x_i|^2 - w_i <= |y - x_j|^2 - w_j`` for every j. Equal weights
give the Voronoi diagram. A cell may lie away from its point, or be empty.

The cells come from ``torch.ops.torchvor.power_cells`` (csrc/ops/power.h):
each cell walks a grid of the points outwards from its own, clipped by the
points that can reach it until the power radius of security proves it exact,
in float64 (float32 points' cells first in float32). This
module bounds the weights that can reach each cell (_WeightBounds), retries
the cells whose arrays overflowed (the next tier; the largest run on the CPU)
or whose arithmetic did not resolve them (float32 to float64, float64 to
double-double on the CPU), and gathers the faces. :func:`power_weights` solves for the weights by damped Newton
(Kitagawa, Merigot and Thibert 2019), with the power diagram's Laplacian
as the Jacobian and conjugate gradients in torch.
"""
from __future__ import annotations

import math
import warnings
from typing import NamedTuple, Optional, Tuple

import torch

from .ops import DEFAULT_MEMORY_BUDGET, CellStatus, VoronoiCells

# The power_cells tiers (csrc/ops/power.h, kPowerTierPlanes): float32 cells of up
# to 32 planes (float32 points), float64 cells of up to 64, 160, 1024,
# 4096 and 16384 planes, then double-double ones of 4096 and 16384 (for cells
# from tier 5).
FLOAT32_TIER = 0
FIRST_FLOAT64_TIER = 1
LAST_FLOAT64_TIER = 5
DOUBLE_DOUBLE_TIER = 6
_RETRY_TIER = (int(CellStatus.TOO_MANY_PLANES), int(CellStatus.TOO_MANY_VERTICES))
_RETRY_WIDER = (int(CellStatus.ILL_CONDITIONED), int(CellStatus.BOUNDARY_ERROR))
_EMPTY = int(CellStatus.EMPTY)


class PowerFaces(NamedTuple):
    """The faces of power cells, each cell's own (not symmetrised).

    cell: (F,) int64 the cell's row; target: (F,) int64 the point across the
    face, or -1 - wall (walls -x, +x, -y, +y, -z, +z); area: (F,); centroid:
    (F, 3) absolute coordinates; inertia: (F,) the integral over the face of
    ``|y - centroid|^2``.
    """

    cell: torch.Tensor
    target: torch.Tensor
    area: torch.Tensor
    centroid: torch.Tensor
    inertia: torch.Tensor


def check_weights(points: torch.Tensor, weights, caller: str) -> torch.Tensor:
    """``weights`` as a (N,) tensor of the points' dtype and device, finite."""
    if not isinstance(weights, torch.Tensor):
        raise TypeError(f"torchvor.{caller}: weights must be a torch.Tensor, got {type(weights).__name__}")
    if weights.dtype != points.dtype:
        raise TypeError(f"torchvor.{caller}: weights must have the points' dtype {points.dtype}, got {weights.dtype}")
    if weights.device != points.device:
        raise ValueError(f"torchvor.{caller}: weights must be on the points' device {points.device}, "
                         f"got {weights.device}")
    if weights.shape != (points.shape[0],):
        raise ValueError(f"torchvor.{caller}: weights must have shape ({points.shape[0]},), one per point, "
                         f"got {tuple(weights.shape)}")
    if not bool(torch.isfinite(weights).all()):
        raise ValueError(f"torchvor.{caller}: weights contain NaN or Inf")
    return weights.contiguous()


def checked_call(points: torch.Tensor, box, batch: Optional[torch.Tensor], weights, caller: str):
    """(box (B, 2, 3), weights) of a call with weights, checked (check_inputs,
    check_weights)."""
    from .ops import _box_for_call

    box_tensor = _box_for_call(points, box, batch)
    check_inputs(points, box_tensor, batch)
    return box_tensor, check_weights(points, weights, caller)


def check_inputs(points: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor]) -> None:
    """The checks of torchvor.voronoi (shapes, dtypes, finite points inside a
    box of positive extent, the batch vector), by its op on no rows."""
    no_rows = torch.empty(0, dtype=torch.int64, device=points.device)
    torch.ops.torchvor.voronoi_cells.default(points, box, batch, None, DEFAULT_MEMORY_BUDGET, no_rows)


def _clouds(points: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor]):
    """(box (B, 2, 3) with a box per cloud, counts (B,) int64)."""
    n = points.shape[0]
    if batch is None:
        return box.contiguous(), torch.tensor([n], device=points.device)
    clouds = max(int(batch.max()) + 1 if n else 1, box.shape[0])
    if box.shape[0] == 1 and clouds > 1:
        box = box.expand(clouds, 2, 3)
    return box.contiguous(), torch.bincount(batch, minlength=clouds)


def _weight_max(weights: torch.Tensor, batch: Optional[torch.Tensor], clouds: int) -> torch.Tensor:
    """(B,) float64: the largest weight of each cloud (0 for an empty one)."""
    w = weights.double()
    if batch is None:
        return (w.max() if w.numel() else w.new_zeros(())).reshape(1)
    top = torch.full((clouds,), -math.inf, dtype=torch.float64, device=w.device)
    top = top.scatter_reduce(0, batch, w, "amax")
    return torch.where(torch.isfinite(top), top, torch.zeros_like(top))


# The weight bounds' first reach is that of a cell of this many mean spacings
# (about a white-noise cell's radius) where no radius is hinted; a cell that
# reaches farther runs again with its own reach.
GUESS = 2.0


class _WeightBounds:
    """Per-row bounds on the weights that can cut a power cell, tighter than its
    cloud's largest weight: a cell within R of its point is cut only by points
    within its reach ``R + sqrt(R^2 + max w - w_i)``, so the largest weight
    within a distance D >= that reach bounds them. The largest weights are
    kept on a grid of cubes (about GRID_POINTS points each) and dilated a cube
    at a time; a row of D gets the largest weight within ceil(D / side) cubes.
    One cloud only (the others keep their cloud's largest weight)."""

    GRID_POINTS = 2
    MAX_CUBES = 1 << 24  # a coarser grid past it
    MAX_DILATION = 24  # cubes; past it, the cloud's largest weight

    def __init__(self, points: torch.Tensor, weights: torch.Tensor, box: torch.Tensor, batch):
        self.top = _weight_max(weights, batch, box.shape[0])  # (B,)
        self.batch = batch
        self.local = box.shape[0] == 1 and points.shape[0] > 0
        if not self.local:
            return
        lo, hi = box[0, 0].double(), box[0, 1].double()
        extent = (hi - lo).clamp_min(0)
        n = points.shape[0]
        volume = float(extent.prod())
        side = (volume * self.GRID_POINTS / n) ** (1.0 / 3.0) if volume > 0 else 0.0
        side = max(side, float(extent.max()) / 1024, (volume / self.MAX_CUBES) ** (1.0 / 3.0))
        if not side > 0:
            self.local = False
            return
        self.side, self.lo = side, lo
        self.shape = [max(1, min(1024, math.ceil(float(e) / side))) for e in extent]
        self.cube = self._cube_of(points)
        flat = (self.cube[:, 0] * self.shape[1] + self.cube[:, 1]) * self.shape[2] + self.cube[:, 2]
        grid = torch.full((math.prod(self.shape),), -math.inf, dtype=torch.float64, device=points.device)
        self.grid = grid.scatter_reduce(0, flat, weights.double(), "amax").reshape(1, 1, *self.shape)

    def _cube_of(self, points: torch.Tensor) -> torch.Tensor:
        index = torch.floor((points.double() - self.lo) / self.side).long()
        return torch.minimum(index.clamp_min(0), torch.tensor(self.shape, device=points.device) - 1)

    def cloud_max(self, rows: torch.Tensor) -> torch.Tensor:
        """(M,) float64: the rows' clouds' largest weights."""
        return self.top[self.batch[rows]] if self.batch is not None else self.top[0].expand(rows.numel())

    def bound(self, rows: torch.Tensor, reach: torch.Tensor) -> torch.Tensor:
        """(M,) float64: the largest weight within `reach` (M,) of each row's point."""
        out = self.cloud_max(rows).clone()
        if not self.local or rows.numel() == 0:
            return out
        steps = torch.ceil(reach / self.side + 1e-6)
        steps = torch.where(torch.isfinite(steps), steps, torch.full_like(steps, math.inf))
        near = steps <= self.MAX_DILATION
        if not bool(near.any()):
            return out
        steps = steps.clamp(0, self.MAX_DILATION).long()
        cube = self.cube[rows]
        grid = self.grid
        for level in range(int(steps[near].max()) + 1):
            if level:
                grid = torch.nn.functional.max_pool3d(grid, 3, stride=1, padding=1)
            at = near & (steps == level)
            if bool(at.any()):
                c = cube[at]
                out[at] = grid[0, 0, c[:, 0], c[:, 1], c[:, 2]]
        return out


def _power_reach(radius: torch.Tensor, spread: torch.Tensor) -> torch.Tensor:
    """``R + sqrt(R^2 + spread)``: no point farther can cut a power cell within
    R of its point whose weight is `spread` below the largest that can."""
    r = radius.double()
    return r + torch.sqrt(r * r + spread.clamp_min(0))


def power_cells(points: torch.Tensor, weights: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor] = None,
                memory_budget: int = DEFAULT_MEMORY_BUDGET, faces=False, rows: Optional[torch.Tensor] = None,
                radius_hint: Optional[torch.Tensor] = None,
                float32_faces: bool = False) -> Tuple[VoronoiCells, Optional[PowerFaces]]:
    """The power cells of every point (checked inputs; ``box`` (B, 2, 3)).
    ``rows``: (M,) int64, the points whose cells to compute (default all);
    the others come back NOT_COMPUTED (NaN outputs, no faces).
    ``radius_hint``: (N,) the radii the cells likely have (the last ones of
    points whose weights moved a little), for the first reach of their weight
    bounds (_WeightBounds). ``memory_budget`` bounds the faces of one op call.
    ``float32_faces``: float32 points' cells with faces computed in float32
    too where its checks pass (float64 otherwise): faces good for a Jacobian,
    not split as exactly as voronoi_graph's.

    Returns :class:`VoronoiCells` (N,) (status EMPTY for an empty cell) and,
    with ``faces``, every computed cell's :class:`PowerFaces` (the cells' own
    pass writes them; a second pass only where its room ran out); with
    ``faces = "later"``, a function that gathers them, skipped where they turn
    out not to be needed. Not differentiable.
    """
    with torch.no_grad():
        return _power_cells(points, weights, box, batch, memory_budget, faces, rows, radius_hint, float32_faces)


def _spatial_order(points: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor]) -> torch.Tensor:
    """The rows sorted by cloud, then by the cell of a grid of about 4 points a
    cell over their box: nearby cells run side by side and read nearby
    neighbours (the device's caches), and their walks are alike in length."""
    n = points.shape[0]
    g = max(1, round((n / 4) ** (1.0 / 3.0)))
    corners = box[batch] if batch is not None else box[:1].expand(n, 2, 3)
    lo, extent = corners[:, 0], (corners[:, 1] - corners[:, 0]).clamp_min(torch.finfo(points.dtype).tiny)
    cell = ((points - lo) / extent * g).long().clamp(0, g - 1)
    key = (cell[:, 0] * g + cell[:, 1]) * g + cell[:, 2]
    if batch is not None:
        key = key + batch * g ** 3
    return torch.argsort(key)


def _power_cells(points, weights, box, batch, memory_budget, faces, rows=None, radius_hint=None, float32_faces=False):
    n = points.shape[0]
    device = points.device
    box, counts = _clouds(points, box, batch)
    bounds = _WeightBounds(points, weights, box, batch)
    w64 = weights.double()
    volume = points.new_full((n,), math.nan)
    centroid = points.new_full((n, 3), math.nan)
    second = points.new_full((n,), math.nan)
    status = torch.full((n,), int(CellStatus.NOT_COMPUTED), dtype=torch.int8, device=device)
    needed = torch.zeros(n, dtype=torch.int32, device=device)
    radius = torch.full((n,), math.nan, dtype=torch.float32, device=device)
    face_count = torch.zeros(n, dtype=torch.int32, device=device)
    # float32 points' cells start in float32 (tier 0) unless their faces must be float64's
    single = points.dtype == torch.float32 and (not faces or float32_faces)
    first_tier = FLOAT32_TIER if single else FIRST_FLOAT64_TIER
    row_tier = torch.full((n,), first_tier, dtype=torch.int64, device=device)
    row_reach = torch.zeros(n, dtype=torch.float64, device=device)  # the reach each row's bound holds for
    row_bound = torch.zeros(n, dtype=torch.float64, device=device)  # weight_max: the bound within it
    # With faces, each op call's cells claim their faces' rows (face_room a cell): the
    # calls' face arrays (`claims`), and for each row its last call and first face there.
    face_room = FACE_ROOM if faces else 0
    rows_a_call = max(1, memory_budget // (FACE_ROOM * FACE_BYTES)) if faces else None
    claims = []
    row_call = torch.full((n,), -1, dtype=torch.int64, device=device)
    row_first = torch.full((n,), -1, dtype=torch.int64, device=device)

    def aim(pending, r):
        """The rows `pending` bounded for cells of radius `r` (M,) (a tenth more)."""
        row_reach[pending] = 1.1 * _power_reach(r, bounds.cloud_max(pending) - w64[pending])
        row_bound[pending] = bounds.bound(pending, row_reach[pending])

    def run(pending):
        """Computes the cells of `pending` (at their row_tier and row_bound)
        until none asks for a retry; a cell that stopped on a bound whose
        reach falls short of its own runs again with its reach."""
        while pending.numel():
            retry = []
            for tier in torch.unique(row_tier[pending]).tolist():
                group = pending[row_tier[pending] == tier]
                for part in (torch.split(group, rows_a_call) if faces else (group,)):
                    out = torch.ops.torchvor.power_cells.default(points, weights, box, batch, part, row_bound[part],
                                                                 tier, face_room)
                    for target, value in zip((volume, centroid, second, status, needed, radius, face_count), out):
                        target[part] = value
                    if faces:
                        row_call[part] = len(claims)
                        row_first[part] = out[7]
                        claims.append(out[8:])
                code = status[group].long()
                overflow = (code == _RETRY_TIER[0]) | (code == _RETRY_TIER[1])
                larger = overflow & ((tier < LAST_FLOAT64_TIER) | (tier == DOUBLE_DOUBLE_TIER))
                wider = ((code == _RETRY_WIDER[0]) | (code == _RETRY_WIDER[1])) & (tier < DOUBLE_DOUBLE_TIER)
                row_tier[group[larger]] = tier + 1
                # float32 cells go to float64, float64 ones to double-double
                row_tier[group[wider]] = (FIRST_FLOAT64_TIER if tier == FLOAT32_TIER else
                                          DOUBLE_DOUBLE_TIER + (tier == LAST_FLOAT64_TIER))
                # the bound held where nothing past its reach could cut: the cell's own reach within it
                # (an empty cell stays empty)
                stopped = code == int(CellStatus.SUCCESS)
                own = _power_reach(radius[group], bounds.cloud_max(group) - w64[group])
                short = stopped & (own > row_reach[group]) & (row_bound[group] < bounds.cloud_max(group))
                if bool(short.any()):
                    aim(group[short], radius[group[short]])
                retry.append(group[larger | wider | short])
            pending = torch.cat(retry) if retry else pending[:0]

    order = _spatial_order(points, box, batch) if n else torch.arange(0, device=device)
    if rows is not None:
        asked = torch.zeros(n, dtype=torch.bool, device=device)
        asked[rows] = True
        order = order[asked[order]]
    # the bounds' first reach: the hinted radii, or GUESS spacings
    spacing = ((box[:, 1] - box[:, 0]).double().clamp_min(0).prod(1) / counts.clamp_min(1)) ** (1.0 / 3.0)
    guess = GUESS * (spacing[batch] if batch is not None else spacing[0].expand(n))
    aim(order, guess[order] if radius_hint is None else radius_hint.double()[order].nan_to_num(0).maximum(
        0.5 * guess[order]))
    run(order)
    cells = VoronoiCells(volume, centroid, second, status, needed, radius)
    if not faces:
        return cells, None

    def faces_of_the_cells() -> PowerFaces:
        with torch.no_grad():
            return _claimed_faces(points, weights, box, batch, row_bound, row_tier, face_count, memory_budget,
                                  claims, row_call, row_first)

    return cells, faces_of_the_cells if faces == "later" else faces_of_the_cells()


# Bytes a face takes in power_faces' outputs (target, area, centroid, inertia;
# float64) and the gathers after it: the faces of one op call fit the budget.
FACE_BYTES = 96
# The faces' rows a cell's power_cells call keeps room for (a cell claims as many
# as it has, so the room is the mean it allows: Voronoi cells of white noise have
# 15.5 on average); a call whose cells run out of room leaves the rest to a second
# pass (power_faces).
FACE_ROOM = 20


def _claimed_faces(points, weights, box, batch, row_bound, row_tier, face_count, memory_budget, claims, row_call,
                   row_first) -> PowerFaces:
    """The faces the cells claimed in their last power_cells call (call by call,
    rows in order), and those of the cells whose call ran out of room (_faces, a
    second pass)."""
    with_faces = face_count > 0
    claimed = with_faces & (row_first >= 0)
    parts = []
    for call, arrays in enumerate(claims):
        rows = torch.nonzero(claimed & (row_call == call)).flatten()
        if rows.numel() == 0:
            continue
        counts = face_count[rows].long()
        starts = counts.cumsum(0) - counts
        index = (row_first[rows] - starts).repeat_interleave(counts) + torch.arange(int(counts.sum()),
                                                                                   device=points.device)
        parts.append(PowerFaces(rows.repeat_interleave(counts), *(column.index_select(0, index) for column in arrays)))
    rest = with_faces & ~claimed
    if bool(rest.any()) or not parts:
        parts.append(_faces(points, weights, box, batch, row_bound, row_tier, torch.where(rest, face_count, 0),
                            memory_budget))
    return parts[0] if len(parts) == 1 else PowerFaces(*(torch.cat(column) for column in zip(*parts)))


def _faces(points, weights, box, batch, row_bound, row_tier, face_count, memory_budget) -> PowerFaces:
    """The faces of the cells with faces, computed again at their last pass's tier and bound."""
    device = points.device
    with_faces = torch.nonzero(face_count > 0).flatten()
    parts = []
    tiers = row_tier[with_faces]
    for tier in torch.unique(tiers).tolist():
        group = with_faces[tiers == tier]
        pieces = max(1, math.ceil(int(face_count[group].sum()) * FACE_BYTES / memory_budget))
        for rows in torch.tensor_split(group, pieces):
            counts = face_count[rows].long()
            offsets = torch.cat([counts.new_zeros(1), counts.cumsum(0)])
            target, area, centroid, inertia = torch.ops.torchvor.power_faces.default(
                points, weights, box, batch, rows, row_bound[rows], tier, offsets)
            parts.append((rows.repeat_interleave(counts), target, area, centroid, inertia))
    if not parts:
        empty = torch.empty(0, dtype=torch.int64, device=device)
        return PowerFaces(empty, empty, points.new_empty(0), points.new_empty(0, 3), points.new_empty(0))
    return PowerFaces(*(torch.cat(column) for column in zip(*parts)))


def graph_of_faces(n: int, faces: PowerFaces, dtype) -> Tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """(edge_index (2, E), area (E,), centroid (E, 3), wall_area (N, 6)) as
    voronoi_graph gives them: each face both ways with the mean of the two
    cells' areas (centroids weighted by area), sorted by cell then neighbour."""
    wall = faces.target < 0
    wall_area = torch.zeros(n, 6, dtype=dtype, device=faces.area.device)
    wall_area.index_put_((faces.cell[wall], -1 - faces.target[wall]), faces.area[wall], accumulate=True)
    i, j = faces.cell[~wall], faces.target[~wall]
    area, centroid = faces.area[~wall], faces.centroid[~wall]
    low, high = torch.minimum(i, j), torch.maximum(i, j)
    keys, inverse = torch.unique(low * n + high, return_inverse=True)
    total = area.new_zeros(keys.numel()).index_add(0, inverse, area)
    sides = area.new_zeros(keys.numel()).index_add(0, inverse, torch.ones_like(area))
    moment = centroid.new_zeros(keys.numel(), 3).index_add(0, inverse, area.unsqueeze(1) * centroid)
    mean_area = total / sides
    mean_centroid = moment / total.clamp_min(torch.finfo(dtype).tiny).unsqueeze(1)
    a, b = keys // n, keys % n
    cell = torch.cat([a, b])
    neighbor = torch.cat([b, a])
    order = torch.argsort(cell * n + neighbor)
    edge_index = torch.stack([neighbor[order], cell[order]])
    return edge_index, mean_area.repeat(2)[order], mean_centroid.repeat(2, 1)[order], wall_area


# ---- the cells as torchvor.voronoi returns them, differentiable in the weights ---------


def _gradient_terms(points, faces: PowerFaces):
    """Per neighbour face of a computed cell i with point j across: (i, j,
    dV_i/dw_j, dM_i/dw_j (first moment), dS_i/dw_j (second moment)); the
    derivatives in w_i are their negatives (a face moves along x_j - x_i by
    (dw_i - dw_j) / (2 |x_j - x_i|))."""
    keep = faces.target >= 0
    i, j = faces.cell[keep], faces.target[keep]
    area, centroid, inertia = faces.area[keep], faces.centroid[keep], faces.inertia[keep]
    speed = 0.5 / (points[j] - points[i]).norm(dim=1)
    d_volume = -speed * area
    d_moment = d_volume.unsqueeze(1) * centroid
    d_second = -speed * (area * (centroid - points[i]).square().sum(1) + inertia)
    return i, j, d_volume, d_moment, d_second


class _PowerCells(torch.autograd.Function):
    """volume, centroid and second moment of the power cells of `rows` (all
    points where None), with their gradients in the weights (not in the
    points: that backward raises)."""

    @staticmethod
    def forward(ctx, points, weights, box, batch, k, memory_budget, rows):
        cells, faces = power_cells(points, weights, box, batch, memory_budget, faces=weights.requires_grad,
                                   rows=rows)
        ctx.faces = faces
        ctx.rows = rows
        ctx.save_for_backward(points, cells.volume, cells.centroid)
        out = tuple(cells) if rows is None else tuple(t.index_select(0, rows) for t in cells)
        ctx.mark_non_differentiable(*out[3:])
        return out

    @staticmethod
    def backward(ctx, grad_volume, grad_centroid, grad_second, *_):
        if ctx.needs_input_grad[0]:
            raise RuntimeError("torchvor.voronoi: power cells (weights=...) are differentiable in the weights, "
                               "not yet in the points; detach the points")
        points, volume, centroid = ctx.saved_tensors
        if not ctx.needs_input_grad[1]:
            return (None,) * 7
        if ctx.rows is not None:  # the gradients of the rows' cells, at their points
            grad_volume, grad_centroid, grad_second = (
                None if g is None else torch.zeros((points.shape[0],) + g.shape[1:], dtype=g.dtype,
                                                   device=g.device).index_copy(0, ctx.rows, g)
                for g in (grad_volume, grad_centroid, grad_second))
        i, j, d_volume, d_moment, d_second = _gradient_terms(points, ctx.faces)
        term = points.new_zeros(i.shape[0])
        if grad_volume is not None:
            term = term + grad_volume[i] * d_volume
        if grad_centroid is not None:
            # centroid = M / V: d centroid = (dM - centroid dV) / V
            d_centroid = (d_moment - centroid[i] * d_volume.unsqueeze(1)) / volume[i].unsqueeze(1)
            term = term + (grad_centroid[i] * d_centroid).sum(1)
        if grad_second is not None:
            term = term + grad_second[i] * d_second
        term = torch.nan_to_num(term)  # a failed cell (NaN outputs) has no faces anyway
        grad_weights = torch.zeros_like(volume).index_add(0, j, term).index_add(0, i, -term)
        return None, grad_weights, None, None, None, None, None


def voronoi(points, weights, box, batch, k, memory_budget, rows: Optional[torch.Tensor] = None) -> VoronoiCells:
    """torchvor.voronoi with weights (checked): the power cells (of `rows`
    only, in their order, where given), differentiable in the weights. `k`
    is unused (no neighbour lists: the cells walk a grid)."""
    return VoronoiCells(*_PowerCells.apply(points, weights, box, batch, k, memory_budget, rows))


def voronoi_graph(points, weights, box, batch, k, memory_budget):
    """torchvor.voronoi_graph with weights (checked): (cells, edge_index, area, centroid, wall_area);
    `k` unused."""
    with torch.no_grad():
        cells, faces = power_cells(points, weights, box, batch, memory_budget, faces=True)
    edge_index, area, centroid, wall_area = graph_of_faces(points.shape[0], faces, points.dtype)
    return cells, edge_index, area, centroid, wall_area


# ---- op registrations: fake kernels; the ops' own outputs are not differentiable --------


@torch.library.register_fake("torchvor::power_cells")
def _power_cells_fake(points, weights, box, batch, rows, weight_max, tier, face_room=0):
    m = rows.shape[0]
    f = m * face_room
    return (points.new_empty((m,)), points.new_empty((m, 3)), points.new_empty((m,)),
            points.new_empty((m,), dtype=torch.int8), points.new_empty((m,), dtype=torch.int32),
            points.new_empty((m,), dtype=torch.float32), points.new_empty((m,), dtype=torch.int32),
            points.new_empty((m if face_room > 0 else 0,), dtype=torch.int64),
            points.new_empty((f,), dtype=torch.int64), points.new_empty((f,)), points.new_empty((f, 3)),
            points.new_empty((f,)))


@torch.library.register_fake("torchvor::power_faces")
def _power_faces_fake(points, weights, box, batch, rows, weight_max, tier, face_offsets):
    f = torch.library.get_ctx().new_dynamic_size()
    return (points.new_empty((f,), dtype=torch.int64), points.new_empty((f,)), points.new_empty((f, 3)),
            points.new_empty((f,)))


def _register_non_differentiable():
    from .ops import _no_backward, _non_differentiable
    for op in ("power_cells", "power_faces"):
        torch.library.register_autograd(f"torchvor::{op}", _no_backward, setup_context=_non_differentiable)


_register_non_differentiable()


# ---- semi-discrete optimal transport: the weights of prescribed volumes -----------------


class PowerWeights(NamedTuple):
    """Result of :func:`power_weights`.

    weights: (N,) the points' dtype: the power diagram with these weights
        gives every cell its target volume (up to ``error``); their mean is 0
        (adding a constant changes no cell; float32 weights: up to a few ulps
        of the largest, the shift whose rounding errs least).
    iterations: Newton iterations taken.
    error: the largest relative volume error, ``max |V_i - target_i| / target_i``.
    cells: the :class:`VoronoiCells` (power cells) of the returned weights.
    """

    weights: torch.Tensor
    iterations: int
    error: float
    cells: VoronoiCells


class _Jacobian(NamedTuple):
    """The volumes' Jacobian in the weights (d V_i / d w_j = -c_ij, c_ij =
    a_ij / (2 |x_i - x_j|), for each face (j, i); rows summing to zero):
    ``matrix`` the (N, N) CSR matrix, the row sums on its diagonal, so that a
    conjugate-gradient iteration is one sparse product; ``diagonal`` (N,)."""
    matrix: torch.Tensor
    diagonal: torch.Tensor

    @staticmethod
    def of(n: int, edge_index: torch.Tensor, coefficient: torch.Tensor) -> "_Jacobian":
        """From each face (j, i)'s c_ij (repeated pairs add up)."""
        j, i = edge_index
        key, order = torch.sort(i * n + j)
        return _Jacobian._assembled(n, key // n, key % n, coefficient[order])

    @staticmethod
    def of_faces(n: int, faces: PowerFaces, work: torch.Tensor) -> "_Jacobian":
        """From the cells' own faces: c_ij from the mean of the two cells'
        areas, as graph_of_faces gives them, by one sort of the faces and one
        of their reverses (graph_of_faces where a face is listed twice or by
        one side only)."""
        key = torch.where(faces.target >= 0, faces.cell * n + faces.target, -1)
        key, order = torch.sort(key)
        first = int(torch.searchsorted(key, 0))  # the walls' faces sort first
        key, order = key[first:], order[first:]
        i, j, area = key // n, key % n, faces.area[order]
        # every face listed once by each side: the reversed keys sort to the same
        # keys, and the one that lands at m is face m's reverse
        reverse_key, landing = torch.sort(j * n + i)
        if key.numel() == 0 or not (torch.equal(reverse_key, key) and bool((key[1:] != key[:-1]).all())):
            edge_index, mean_area, _centroid, _walls = graph_of_faces(n, faces, torch.float64)
            j, i = edge_index
            return _Jacobian.of(n, edge_index, mean_area / (2 * (work[i] - work[j]).norm(dim=1)))
        reverse = torch.empty_like(landing).index_copy_(0, landing, torch.arange(key.numel(), device=key.device))
        return _Jacobian._assembled(n, i, j, 0.5 * (area + area[reverse]) / (2 * (work[i] - work[j]).norm(dim=1)))

    @staticmethod
    def _assembled(n: int, rows: torch.Tensor, columns: torch.Tensor, c: torch.Tensor) -> "_Jacobian":
        """The CSR matrix of entries -c at (rows, columns), sorted by row then
        column, and each row's sum of c on its diagonal, in its column's place
        (after any entry of the row's own column, whose terms cancel)."""
        device = c.device
        diagonal = torch.zeros(n, dtype=c.dtype, device=device).index_add(0, rows, c)
        counts = torch.bincount(rows, minlength=n)
        row_start = torch.zeros(n + 1, dtype=torch.int64, device=device)
        row_start[1:] = (counts + 1).cumsum(0)
        # an entry's place: its row's start, its rank in the row, one more past the diagonal
        rank = torch.arange(rows.numel(), device=device) - (counts.cumsum(0) - counts)[rows]
        place = row_start[rows] + rank + (columns >= rows)
        before = torch.zeros(n, dtype=torch.int64, device=device).index_add(0, rows, (columns < rows).long())
        on_diagonal = row_start[:-1] + before
        values = torch.empty(rows.numel() + n, dtype=c.dtype, device=device)
        values[place] = -c
        values[on_diagonal] = diagonal
        column = torch.empty(rows.numel() + n, dtype=torch.int64, device=device)
        column[place] = columns
        column[on_diagonal] = torch.arange(n, device=device)
        with warnings.catch_warnings():  # torch's notices that sparse CSR is in beta, unchecked
            warnings.filterwarnings("ignore", message="Sparse (CSR tensor support|invariant checks)")
            matrix = torch.sparse_csr_tensor(row_start, column, values, (n, n))
        return _Jacobian(matrix, diagonal)

    def apply(self, x: torch.Tensor) -> torch.Tensor:
        return self.matrix @ x


# The conjugate gradients test their residual every CG_CHECK iterations (one
# wait for the device each time).
CG_CHECK = 4


def _conjugate_gradient(jacobian: _Jacobian, rhs, rtol: float, max_iters: int):
    """J x = rhs (sum of rhs 0, J a graph Laplacian: x of mean 0) by CG with
    the Jacobi preconditioner, to |r| <= rtol |rhs| (tested every CG_CHECK
    iterations), or until a direction finds no curvature (J's null space,
    by rounding)."""
    diagonal = jacobian.diagonal
    inverse = torch.where(diagonal > 0, 1.0 / diagonal, torch.zeros_like(diagonal))
    x = torch.zeros_like(rhs)
    r = rhs - rhs.mean()
    z = inverse * r
    p = z.clone()
    rz = torch.dot(r, z)
    stop = rtol * float(r.norm())
    stalled = torch.zeros((), dtype=torch.bool, device=rhs.device)
    for iteration in range(max_iters):
        if iteration % CG_CHECK == 0 and bool((r.norm() <= stop) | stalled):
            break
        q = jacobian.apply(p)
        curvature = torch.dot(p, q)
        stalled |= ~(curvature > 0)  # no step once a direction found no curvature
        alpha = torch.where(stalled, 0.0, rz / curvature)
        x.addcmul_(alpha, p)
        r.addcmul_(alpha, q, value=-1)
        torch.mul(inverse, r, out=z)
        rz_next = torch.dot(r, z)
        p = torch.addcmul(z, torch.where(rz > 0, rz_next / rz, 0.0), p)
        rz = rz_next
    return x - x.mean()


def _jacobian(n: int, found, work: torch.Tensor) -> _Jacobian:
    """The volumes' Jacobian in the weights from evaluate's faces: PowerFaces,
    or a periodic call's (edge_index, c)."""
    if not isinstance(found, PowerFaces):
        return _Jacobian.of(n, *found)
    return _Jacobian.of_faces(n, found, work)


def _periodic_faces(graph, work: torch.Tensor, period: torch.Tensor):
    """(edge_index, c) of a periodic voronoi_graph (cells, edge_index, area,
    centroid, wall_area, shift): c = area / (2 |x_i - image of x_j|); a
    cell's faces with its own images do not move with its weight."""
    _cells, edge_index, area, _centroid, _walls, shift = graph
    j, i = edge_index
    keep = i != j
    j, i = j[keep], i[keep]
    across = work[j] + shift[keep].double() * period - work[i]
    return torch.stack([j, i]), area[keep] / (2 * across.norm(dim=1))


# power_weights' trial steps at a largest relative error over SAMPLE_ERROR are
# first computed on every SAMPLE_STRIDE-th cell (clouds of SAMPLE_MIN_POINTS
# and more): a step refused there costs the sample's cells, not all of them.
SAMPLE_ERROR = 0.1
SAMPLE_STRIDE = 16
SAMPLE_MIN_POINTS = 20_000
# Float32 points' cells and faces are computed in float32 from zero weights and
# for the trial steps from a largest relative error over SINGLE_ERROR: there
# their rounding is noise far below the error, and the steps after them land
# far above it.
SINGLE_ERROR = 0.2
# Float32 points' Newton stops once its float64 error is below ROUNDING_SHARE
# of what rounding the weights to float32 adds (the Jacobian times the
# rounding): further steps cannot lower the error of the weights returned.
# The rounding is the best of ROUNDING_SHIFTS (_float32_weights).
ROUNDING_SHARE = 0.25
ROUNDING_SHIFTS = 8


def _faces_in_float64(gather):
    """The faces' gather (power_cells' faces="later"), their floating columns in float64."""
    def gathered() -> PowerFaces:
        found = gather()
        return PowerFaces(found.cell, found.target, found.area.double(), found.centroid.double(),
                          found.inertia.double())
    return gathered


def _float32_weights(jacobian: _Jacobian, weights: torch.Tensor, target: torch.Tensor) -> Tuple[torch.Tensor, float]:
    """(float32 weights, the largest relative volume error their rounding adds,
    to first order: the Jacobian times the rounding) of float64 `weights` of
    mean 0: of the weights plus each of ROUNDING_SHIFTS constants (steps of
    0.382 of the largest weight's ulp: each rounds the weights apart), the
    one that adds the least."""
    ulp = float(torch.finfo(torch.float32).eps) * float(weights.abs().max())
    candidates = [(weights + k * 0.3819660112501051 * ulp).float() for k in range(ROUNDING_SHIFTS)]
    errors = torch.stack([(jacobian.apply(c.double() - weights).abs() / target).max() for c in candidates])
    best = int(torch.argmin(errors))
    return candidates[best], float(errors[best])


def power_weights(points: torch.Tensor, box=None, *, volumes: Optional[torch.Tensor] = None, tol: float = 1e-6,
                  max_iters: int = 100, k: Optional[int] = None, progress: bool = False,
                  memory_budget: int = DEFAULT_MEMORY_BUDGET, weights: Optional[torch.Tensor] = None,
                  periodic=False) -> PowerWeights:
    """Weights whose power diagram gives every cell a prescribed volume
    (semi-discrete optimal transport of the uniform measure on the box to the
    points).

    Damped Newton (Kitagawa, Merigot and Thibert 2019): from zero weights
    (the Voronoi diagram), each step solves ``J dw = target - V`` by
    conjugate gradients, J the power diagram's Laplacian (``d V_i / d w_j =
    -a_ij / (2 |x_i - x_j|)``, a_ij the face area), and halves the step until
    no cell shrinks below half the smallest initial or target volume and the
    largest volume error falls by at least a factor ``1 - step / 2`` (far
    from the solution, a trial step is first computed on every 16th cell,
    which can refuse it). The cells are computed in float64, but far from the
    solution (a largest error over 0.2, and from zero weights) float32
    points' cells and faces are computed in float32.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``,
            distinct (a copy of a point can get no volume of its own).
        box: as :func:`torchvor.voronoi`.
        volumes: (N,) positive target volumes in proportion (scaled to sum
            to the box's volume), the points' dtype and device; default: all
            equal.
        tol: the largest relative volume error to reach, ``> 0``.
        max_iters: Newton iterations at most; not converged then: a
            RuntimeWarning, and the weights reached. Float32 weights are
            the float64 solution rounded: their cells and ``error`` are those
            of the rounded weights (the rounding leaves errors that grow with
            the weights' spread and N: about 1e-5 at 100K white-noise points,
            3e-5 at 1M, whatever ``tol``), and Newton stops once its float64
            error is under a quarter of what the rounding adds.
        k: with ``periodic``, as :func:`torchvor.voronoi` (the plain cells
            that size the padding); unused otherwise (power cells walk a
            grid of the points, no neighbour lists).
        progress: print each iteration's error and step.
        memory_budget: bytes of the faces that one pass computes at a time.
        weights: (N,) the weights to start from (default zeros: the Voronoi
            diagram), e.g. the previous solution of points that moved a little;
            halved towards zero while it empties a cell.
        periodic: as :func:`torchvor.voronoi` (the box required): the power
            diagram on the torus, whose cells share the box's volume.

    Returns:
        :class:`PowerWeights` ``(weights, iterations, error, cells)``.

    Raises:
        ValueError: bad shapes or values (as :func:`torchvor.voronoi`),
            non-positive volumes or tol, duplicate points.
        TypeError: mismatched dtypes.
        RuntimeError: a cell that could not be computed.
    """
    from . import periodic as _periodic
    from .ops import _box_for_call, _check_points, _check_tensor

    _check_tensor(points, "points")
    axes = _periodic.periodic_axes(periodic, "power_weights")
    if axes is None:
        box_tensor = _box_for_call(points, box, None)
        check_inputs(points, box_tensor, None)
    else:
        _check_points(points, "power_weights")
        box_tensor = _periodic.periodic_box(points, box, None, axes, "power_weights").box
    if not (isinstance(tol, (int, float)) and tol > 0):
        raise ValueError(f"torchvor.power_weights: tol must be a positive number, got {tol!r}")
    if not (isinstance(max_iters, int) and max_iters >= 0):
        raise ValueError(f"torchvor.power_weights: max_iters must be a non-negative int, got {max_iters!r}")
    n = points.shape[0]
    if box_tensor.shape[0] != 1:
        raise ValueError("torchvor.power_weights: one box, (lo, hi) or (2, 3)")
    lo, hi = box_tensor[0, 0].double(), box_tensor[0, 1].double()
    box_volume = float((hi - lo).prod())
    if volumes is None:
        target = torch.full((n,), box_volume / max(n, 1), dtype=torch.float64, device=points.device)
    else:
        target = check_weights(points, volumes, "power_weights").double()
        if n and not bool((target > 0).all()):
            raise ValueError("torchvor.power_weights: volumes must be positive")
        target = target * (box_volume / float(target.sum())) if n else target
    work = points.double().contiguous()
    box64 = box_tensor.double()
    pbox = None if axes is None else _periodic.periodic_box(work, box64, None, axes, "power_weights")
    rounds = points.dtype == torch.float32  # float32 weights returned, rounded from float64 ones
    single = rounds and pbox is None  # float32 cells far from the solution
    cold = weights is None
    if weights is None:
        weights = torch.zeros(n, dtype=torch.float64, device=points.device)
    else:
        weights = check_weights(points, weights, "power_weights").double()
        weights = weights - weights.mean() if n else weights
    if n == 0:
        cells, _ = power_cells(points, weights.to(points.dtype), box_tensor, None, memory_budget)
        return PowerWeights(weights.to(points.dtype), 0, 0.0, cells)

    hint = None  # the last cells' radii

    def evaluate(w, faces, in_float32=False):
        """(cells, faces for _jacobian (or the function that computes them) or None,
        volumes (float64)): the power diagram of weights w, `in_float32` of the
        float32 points and weights (their cells and faces in float32 where
        they pass its checks)."""
        nonlocal hint
        if in_float32:
            cells, found = power_cells(points, w.float(), box_tensor, None, memory_budget, faces=faces and "later",
                                       radius_hint=hint, float32_faces=True)
            found = _faces_in_float64(found) if found is not None else None
            hint = cells.radius
        elif pbox is None:
            # faces gathered only for the Jacobian of a step taken and not the last
            cells, found = power_cells(work, w, box64, None, memory_budget, faces=faces and "later", radius_hint=hint)
            hint = cells.radius
        elif faces:
            graph = _periodic.voronoi_graph(work, pbox, None, k, memory_budget, w)
            cells, found = graph[0], _periodic_faces(graph, work, pbox.period[0])
        else:
            cells, found = _periodic.voronoi(work, pbox, None, k, memory_budget, weights=w), None
        code = cells.status
        failed = (code != int(CellStatus.SUCCESS)) & (code != _EMPTY)
        if bool(failed.any()):
            if bool((code == int(CellStatus.DUPLICATE)).any()):
                raise ValueError("torchvor.power_weights: points must be distinct (exact copies found)")
            first = int(torch.nonzero(failed)[0])
            raise RuntimeError(f"torchvor.power_weights: the power cell of point {first} could not be computed "
                               f"(status {CellStatus(int(code[first])).name})")
        volume = torch.where(code == _EMPTY, torch.zeros_like(cells.volume), cells.volume).double()
        return cells, found, volume

    # A trial step far from the solution (where steps are halved) is first
    # tried on a sample of the cells: one that fails there fails on all of them.
    sample = (torch.arange(0, n, SAMPLE_STRIDE, device=points.device)
              if pbox is None and n >= SAMPLE_MIN_POINTS else None)

    def sample_refuses(w, least, most, in_float32) -> bool:
        """Whether the sampled cells of weights w (`in_float32` as evaluate)
        already hold a volume below `least` or an error over `most` (a cell
        not computed refuses nothing: the whole evaluation reports it)."""
        if in_float32:
            found, _ = power_cells(points, w.float(), box_tensor, None, memory_budget, rows=sample, radius_hint=hint)
        else:
            found, _ = power_cells(work, w, box64, None, memory_budget, rows=sample, radius_hint=hint)
        code = found.status[sample]
        sampled = torch.where(code == _EMPTY, torch.zeros_like(found.volume[sample]), found.volume[sample]).double()
        refused = (sampled.min() < least) | ((sampled - target[sample]).abs().max() > most)
        return bool(refused & ((code == int(CellStatus.SUCCESS)) | (code == _EMPTY)).all())

    # zero weights' error is unknown (float32 if SINGLE_ERROR allows any); a warm start's is small
    cells, faces, volume = evaluate(weights, True, single and cold and SINGLE_ERROR < math.inf)
    # Newton needs every cell nonempty (its Jacobian is then a connected graph's
    # Laplacian): a start that empties a cell is halved towards zero weights
    # (the Voronoi diagram), whose cells are all nonempty.
    for _halving in range(60):
        if bool((volume > 0).all()):
            break
        weights = weights / 2 if _halving < 59 else torch.zeros_like(weights)
        cells, faces, volume = evaluate(weights, True)
    floor = 0.5 * min(float(volume.min()), float(target.min()))
    error = float(((volume - target).abs() / target).max())
    iterations = 0
    rounding = 0.0
    while True:
        jacobian = None
        if rounds:  # the weights as they would be returned, and what their rounding adds
            if callable(faces):
                faces = faces()
            jacobian = _jacobian(n, faces, work)
            result, rounding = _float32_weights(jacobian, weights, target)
            if tol < error <= ROUNDING_SHARE * rounding and progress:
                print(f"power_weights: error {error:.3e}, under a quarter of the {rounding:.3e} that "
                      "rounding the weights to float32 adds: stopped")
        converged = error <= tol or (rounds and error <= ROUNDING_SHARE * rounding)
        if converged or iterations >= max_iters:
            break
        if jacobian is None:
            if callable(faces):
                faces = faces()
            jacobian = _jacobian(n, faces, work)
        iterations += 1
        # inexact Newton: the step's residual need only fall with the error, and
        # no further than a hundredth of what tol leaves
        step = _conjugate_gradient(jacobian, target - volume, min(1e-2, max(0.1 * error, 0.01 * tol / error)),
                                   10 * n + 100)
        worst = float((volume - target).abs().max())
        in_float32 = single and error > SINGLE_ERROR
        tau = 1.0
        while True:
            trial = weights + tau * step
            if (sample is None or error <= SAMPLE_ERROR
                    or not sample_refuses(trial, floor, (1 - tau / 2) * worst, in_float32)):
                trial_cells, trial_faces, trial_volume = evaluate(trial, True, in_float32)
                trial_worst = float((trial_volume - target).abs().max())
                if float(trial_volume.min()) >= floor and trial_worst <= (1 - tau / 2) * worst:
                    break
            tau /= 2
            if tau < 1e-12:
                raise RuntimeError("torchvor.power_weights: Newton's step found no descent (the cells are "
                                   "ill-conditioned)")
        weights = trial - trial.mean()
        cells, faces, volume = trial_cells, trial_faces, trial_volume
        error = float(((volume - target).abs() / target).max())
        if progress:
            print(f"power_weights: iteration {iterations}: error {error:.3e}, step {tau:g}")
    if not converged:
        warnings.warn(f"torchvor.power_weights: not converged after {iterations} iterations "
                      f"(error {error:.3e} > tol {tol:.1e})", RuntimeWarning, stacklevel=2)
    if rounds:  # the cells and the error of the weights as rounded
        cells, _, volume = evaluate(result.double(), False)
        error = float(((volume - target).abs() / target).max())
    else:
        result = weights
    result_cells = VoronoiCells(*(t.to(points.dtype) if t.dtype == torch.float64 else t for t in cells))
    return PowerWeights(result, iterations, error, result_cells)


def power_lloyd(points: torch.Tensor, box=None, iters: int = 10, *, volumes: Optional[torch.Tensor] = None,
                tol: float = 1e-6, k: Optional[int] = None, progress: bool = False,
                move_tol: Optional[float] = None, periodic=False) -> Tuple[torch.Tensor, torch.Tensor]:
    """Capacity-constrained Lloyd relaxation (de Goes et al. 2012, blue noise
    through optimal transport): each iteration solves the weights that give
    every cell its target volume (:func:`power_weights`, warm-started from the
    previous ones), then moves every point to its power cell's centroid.

    Args:
        points: (N, 3) float32 or float64, distinct, inside ``box``. Not modified.
        box: as :func:`torchvor.voronoi` (one box).
        iters: iterations (>= 0).
        volumes: (N,) target volumes in proportion (default: all equal).
        tol: :func:`power_weights`' tolerance at each iteration.
        k: as :func:`torchvor.voronoi`.
        progress: print each iteration's Newton iterations and error.
        move_tol: stop early once an iteration moves no point farther than
            this times the box's diagonal (None: run all ``iters``).
        periodic: as :func:`torchvor.voronoi` (the box required): the points
            move on the torus, wrapped into the box.

    Returns:
        ``(points, weights)``: the moved points, (N, 3) in the input's dtype,
        and the weights of their last power diagram (before the last move).
    """
    from . import periodic as _periodic
    from .ops import _box_for_call, _check_points, _check_tensor

    _check_tensor(points, "points")
    if not (isinstance(iters, int) and iters >= 0):
        raise ValueError(f"torchvor.power_lloyd: iters must be a non-negative int, got {iters!r}")
    axes = _periodic.periodic_axes(periodic, "power_lloyd")
    pbox = None
    if axes is None:
        box_tensor = _box_for_call(points, box, None)
        check_inputs(points, box_tensor, None)
    else:
        _check_points(points, "power_lloyd")
        pbox = _periodic.periodic_box(points.detach(), box, None, axes, "power_lloyd")
        box_tensor = pbox.box
    lo, hi = box_tensor[0, 0], box_tensor[0, 1]
    current = points.detach().clone() if pbox is None else _periodic.wrap(points.detach(), pbox, None).clone()
    weights = None
    for iteration in range(iters):
        solved = power_weights(current, box_tensor[0], volumes=volumes, tol=tol, k=k, weights=weights,
                               periodic=periodic)
        weights = solved.weights
        moved = solved.cells.centroid
        if progress:
            print(f"power_lloyd: iteration {iteration}: {solved.iterations} Newton iterations, "
                  f"error {solved.error:.2e}")
        # every cell holds its target volume (> 0), so every centroid is finite; clamp rounding
        moved = torch.minimum(torch.maximum(moved, lo), hi) if pbox is None else _periodic.wrap(moved, pbox, None)
        if pbox is not None:  # wrapped across a face: the move is the step, not the jump
            step = _periodic.minimum_image(moved.double() - current.double(), pbox.period[0].double())
        else:
            step = moved.double() - current.double()
        largest_move = float(step.norm(dim=1).max()) if len(current) else 0.0
        current = moved
        if move_tol is not None and largest_move <= move_tol * float((hi - lo).double().norm()):
            break
    if weights is None:
        weights = torch.zeros(points.shape[0], dtype=points.dtype, device=points.device)
    return current, weights
