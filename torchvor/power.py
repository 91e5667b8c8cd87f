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
double-double on the CPU), and gathers the faces. The weights that give
every cell a prescribed volume: torchvor/transport.py.
"""
from __future__ import annotations

import math
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
