"""Thin Python layer over ``torch.ops.torchvor``: defaults, named results, fake kernels.

Every op's schema is declared in C++ (csrc/registration.cpp); this module adds
their fake kernels for torch.compile and opcheck, and the Python kernel of
``torchvor::drop_missing_edges``.

Shapes use N for points, M for queries, B for batch elements (point clouds).
Bad input raises ``ValueError`` (wrong shape, values, devices) or ``TypeError``
(wrong dtype), from the C++ checks that name the argument.
"""
from __future__ import annotations

import enum
from typing import NamedTuple, Optional, Sequence, Union

import torch

from ._extension import load_extension

load_extension()  # torchvor._C: the op schemas and the C++/CUDA kernels, or an ImportError that says what to do

# voronoi's default memory_budget, as in the ops' schemas (csrc/registration.cpp).
DEFAULT_MEMORY_BUDGET = 1 << 30

BoxLike = Union[torch.Tensor, Sequence]
PeriodicLike = Union[bool, Sequence[bool], None]


class KNN(NamedTuple):
    """Result of :func:`knn`.

    dist2: (M, k) squared Euclidean distances, points' dtype, increasing along a row.
    idx: (M, k) int64 indices into ``points``; ties broken by the lower index.
    Missing neighbours (a cloud with fewer than k candidates) are ``inf`` / ``-1``.
    """

    dist2: torch.Tensor
    idx: torch.Tensor


class CellStatus(enum.IntEnum):
    """Outcome of one Voronoi cell (``VoronoiCells.status``), as in paper §3.4."""

    NOT_COMPUTED = -1
    SUCCESS = 0
    SECURITY_RADIUS_NOT_REACHED = 1
    TOO_MANY_PLANES = 2
    TOO_MANY_VERTICES = 3
    BOUNDARY_ERROR = 4
    DUPLICATE = 5  # exact copy of a lower-index point: volume 0, centroid = the point
    ILL_CONDITIONED = 6  # the integrals cancel beyond the arithmetic's resolution (retried wider)
    EMPTY = 7  # a power cell (weights) that no point of the box belongs to: volume 0, centroid = the point


class VoronoiCells(NamedTuple):
    """Result of :func:`voronoi`; row i belongs to ``points[i]``.

    volume: (N,) cell volumes.
    centroid: (N, 3) cell centroids (the point itself for an empty cell).
    second_moment: (N,) integral over the cell of ``|x - points[i]|^2`` (CVT energy term).
    status: (N,) int8 :class:`CellStatus` codes.
    neighbors_needed: (N,) int32 number of nearest neighbours the cell
        needed (the radius-of-security criterion was met after that many). A
        cell that would need more than 256 is finished by the empty balls of
        its vertices instead (see :func:`voronoi`): 256 (its list) plus its
        Voronoi neighbours beyond the list.
    radius: (N,) the largest distance from ``points[i]`` to a computed vertex
        of its cell, rounded up to a float32 value: the ball of that radius
        around the point holds the cell (up to the cell's tolerance; a sliver's
        rounded vertex can lie a little beyond the exact cell); 0 for a
        duplicate. Not differentiable.
    Floating outputs have the points' dtype; a cell that could not be computed
    has NaN outputs and a failure status.
    """

    volume: torch.Tensor
    centroid: torch.Tensor
    second_moment: torch.Tensor
    status: torch.Tensor
    neighbors_needed: torch.Tensor
    radius: torch.Tensor


def knn(
    points: torch.Tensor,
    k: int,
    queries: Optional[torch.Tensor] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    query_batch: Optional[torch.Tensor] = None,
    exclude_self: Optional[bool] = None,
    box: Optional[BoxLike] = None,
    periodic: PeriodicLike = False,
) -> KNN:
    """k nearest neighbours of 3D points on a uniform grid (paper §2).

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA.
        k: neighbours per query, ``k >= 1``; any size (large k is slower, not capped).
        queries: (M, 3), same dtype and device; ``None`` queries the points themselves.
        batch: (N,) int64 sorted batch vector (PyG convention) for ragged clouds.
        query_batch: (M,) int64 sorted batch vector of the queries; defaults to
            ``batch`` when ``queries`` is None, and is required with ``batch``
            otherwise. Queries only see points of their own batch element.
        exclude_self: when ``queries`` is None, whether query i skips point i.
            Default True (a point is not its own neighbour; exact duplicates of
            it still are, at distance 0). Must be False/None when queries are given.
        box: the box whose edges are the periods, with ``periodic`` (as
            :func:`voronoi` takes it); unused otherwise.
        periodic: ``True`` or three bools (x, y, z): distances wrap around the
            box along those axes, and each point counts once, at its nearest
            image (the minimum-image convention; a point is never its own
            neighbour through an image). Float32 points are then computed in
            float64 (:mod:`torchvor.periodic`).

    Returns:
        :class:`KNN` ``(dist2, idx)`` of shape (M, k), sorted by distance.
    """
    own = queries is None
    queries, query_batch, exclude_self = _queries_of("knn", points, queries, batch, query_batch, exclude_self)
    if not isinstance(k, int) or isinstance(k, bool):
        raise TypeError(f"torchvor.knn: k must be an int, got {type(k).__name__}")
    axes = _periodic.periodic_axes(periodic, "knn")
    if axes is not None:
        if k < 1:
            raise ValueError(f"torchvor.knn: k must be at least 1, got {k}")
        _check_points(points, "knn")
        pbox = _periodic.periodic_box(points, box, batch, axes, "knn")
        return _periodic.knn(points, k, None if own else queries, batch, query_batch, exclude_self, pbox)
    dist2, idx = torch.ops.torchvor.knn.default(points, queries, k, batch, query_batch, exclude_self)
    return KNN(dist2, idx)


def knn_graph(
    points: torch.Tensor, k: int, batch: Optional[torch.Tensor] = None, loop: bool = False, *,
    box: Optional[BoxLike] = None, periodic: PeriodicLike = False,
) -> torch.Tensor:
    """k-nearest-neighbour graph in PyG's layout.

    Args:
        points: (N, 3) float32/float64.
        k: neighbours per point.
        batch: optional (N,) int64 sorted batch vector.
        loop: include the self-loop i -> i (counted among the k).
        box, periodic: as :func:`knn` (a periodic edge joins i to the nearest image of j).

    Returns:
        edge_index: (2, E) int64 with ``edge_index[0]`` the neighbour (source) and
        ``edge_index[1]`` the centre (target), E = N * k when every cloud has more
        than k points (missing neighbours are dropped, so E can be smaller).
    """
    result = knn(points, k, batch=batch, exclude_self=not loop, box=box, periodic=periodic)
    n = points.shape[0]
    target = torch.arange(n, device=points.device).repeat_interleave(k)
    return torch.ops.torchvor.drop_missing_edges.default(torch.stack([result.idx.reshape(-1), target]))


# torchvor::drop_missing_edges (schema in csrc/registration.cpp): an op of its
# own so that torch.compile sees one data-dependent output size, not a boolean
# index inside the graph.
@torch.library.impl("torchvor::drop_missing_edges", "CompositeExplicitAutograd")
def _drop_missing_edges(edge_index: torch.Tensor) -> torch.Tensor:
    """Drop the columns of a (2, E) int64 edge index whose source is -1 (kNN padding)."""
    return edge_index[:, edge_index[0] >= 0]


@torch.library.register_fake("torchvor::drop_missing_edges")
def _drop_missing_edges_fake(edge_index):
    # The number of real edges depends on the data: a dynamic size for torch.compile.
    edges = torch.library.get_ctx().new_dynamic_size()
    return edge_index.new_empty((2, edges))


def as_box(points: torch.Tensor, box: Optional[BoxLike], batch: Optional[torch.Tensor] = None) -> torch.Tensor:
    """Normalise a box argument to a (B, 2, 3) tensor on the points' device and dtype.

    ``box`` may be None (each cloud's bounding box), a pair ``(lo, hi)`` of
    3-sequences or tensors, a (2, 3) tensor, or a (B, 2, 3) tensor (one box per
    batch element).
    """
    if box is None:
        if batch is None:
            if points.shape[0] == 0:
                return torch.zeros(1, 2, 3, dtype=points.dtype, device=points.device)
            return torch.stack([points.amin(0), points.amax(0)]).unsqueeze(0)
        num = int(batch.max()) + 1 if batch.numel() else 1
        index = batch.unsqueeze(1).expand(-1, 3)
        lo = torch.full((num, 3), float("inf"), dtype=points.dtype, device=points.device)
        hi = torch.full((num, 3), float("-inf"), dtype=points.dtype, device=points.device)
        lo = lo.scatter_reduce(0, index, points, "amin")
        hi = hi.scatter_reduce(0, index, points, "amax")
        empty = ~torch.isfinite(lo).all(1)
        lo[empty] = 0
        hi[empty] = 0
        return torch.stack([lo, hi], 1)
    if isinstance(box, (tuple, list)) and len(box) == 2:
        if all(isinstance(b, (tuple, list)) for b in box):
            # Sequences of numbers, the common case: one tensor op and the
            # copy (the path below takes five tensor ops). Anything malformed
            # goes on to that path, for its checks and messages.
            try:
                values = torch.tensor([box], dtype=points.dtype)
            except (TypeError, ValueError, RuntimeError):
                values = None
            if values is not None and values.shape == (1, 2, 3):
                return values.to(points.device)
        if not any(isinstance(b, torch.Tensor) for b in box):  # plain numbers: one copy to the device
            lo, hi = (torch.as_tensor(b, dtype=points.dtype) for b in box)
        else:
            lo, hi = (torch.as_tensor(b, dtype=points.dtype, device=points.device) for b in box)
        if lo.shape != (3,) or hi.shape != (3,):
            raise ValueError(f"torchvor: box=(lo, hi) needs lo and hi of shape (3,), got {tuple(lo.shape)}, {tuple(hi.shape)}")
        return torch.stack([lo, hi]).unsqueeze(0).to(points.device)
    box = torch.as_tensor(box, dtype=points.dtype, device=points.device)
    if box.shape == (2, 3):
        box = box.unsqueeze(0)
    if box.dim() != 3 or box.shape[1:] != (2, 3):
        raise ValueError(f"torchvor: box must be (lo, hi), (2, 3) or (B, 2, 3); got shape {tuple(box.shape)}")
    return box


# Device copies of the boxes that voronoi() and lloyd() were given as
# numbers, by (values, dtype, device): a call with a box seen before makes no
# tensor and no host-to-device copy, which would otherwise be the first host
# work of every call while the GPU waits. Each copy is a blocking one, so that
# any stream may read it at once; only the ops read them (they never write
# their box), and none is handed to the caller.
_DEVICE_BOXES: dict = {}
_DEVICE_BOXES_KEPT = 16


def _box_for_call(points: torch.Tensor, box: Optional[BoxLike], batch: Optional[torch.Tensor]) -> torch.Tensor:
    """:func:`as_box` for an op call, from ``_DEVICE_BOXES`` where the box is (lo, hi) of numbers."""
    plain = (batch is None and isinstance(box, (tuple, list)) and len(box) == 2
             and all(isinstance(b, (tuple, list)) and len(b) == 3 for b in box)
             and all(isinstance(v, (int, float)) for b in box for v in b))
    if not plain or torch.compiler.is_compiling():
        return as_box(points, box, batch)
    key = (tuple(box[0]), tuple(box[1]), points.dtype, points.device)
    cached = _DEVICE_BOXES.get(key)
    if cached is None:
        cached = torch.tensor([box], dtype=points.dtype).to(points.device)
        if len(_DEVICE_BOXES) >= _DEVICE_BOXES_KEPT:
            _DEVICE_BOXES.clear()
        _DEVICE_BOXES[key] = cached
    return cached


def voronoi(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    k: Optional[int] = None,
    on_failure: str = "warn",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    periodic: PeriodicLike = False,
    weights: Optional[torch.Tensor] = None,
) -> VoronoiCells:
    """Volume, centroid and second moment of every 3D Voronoi cell, clipped to a box.

    Each cell is computed on its own by clipping the box with the bisectors of
    its nearest neighbours until the radius of security proves it exact (Ray et
    al. 2018). Cells that need more neighbours or larger arrays are recomputed
    automatically; cells whose predicates are inconsistent, or whose integrals
    cancel beyond what the arithmetic resolves (needle cells of tight
    clusters), are recomputed in float64, then in double-double arithmetic on
    the CPU. Nothing fails silently.

    The radius of security asks a cell for every point within twice its
    farthest vertex. Where a cell reaches into empty space (a void between
    dense clusters, or towards the walls of a box far wider than the points)
    that can be whole clusters, up to the whole cloud. A cell that would need
    more than 256 neighbours is therefore finished otherwise: from its 256
    nearest, it is clipped by every point of the kNN grid that lies in the
    ball around one of its vertices through the seed (only such a point can
    cut it), until none is left; on CUDA a warp sweeps each such cell. The
    cost of such a cell grows with the grid cells its vertices' balls cover.

    Precision: outputs have the points' dtype and are computed in it (then
    float64, double-double where needed, as above). In float32, cells that a
    thread computes in the first tier (up to 32 planes: the usual cell) hold
    their vertices to 18 mantissa bits, which keeps the GPU's cell state
    small; volumes then differ from float64's by a few parts in a million
    (the environment variable ``TORCHVOR_THREAD_TRIANGLES=full`` keeps full
    float32 vertices, a little slower). Use float64 points for more.

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``.
        box: None (bounding box of the points, per batch element), ``(lo, hi)``,
            a (2, 3) tensor, or (B, 2, 3) with ``batch``.
        batch: optional (N,) int64 sorted batch vector: each cloud is its own diagram.
        k: neighbours fetched per cell in the first pass; cells that need more
            are retried with 1.5 times as many (at least 8 more), up to 256,
            then finished by the empty balls of their vertices (below).
            Default None:
            measured on a pilot sample of about 1000 cells (their 98th
            percentile plus 2), which suits blue noise (~19), perturbed grids
            (~50) and white noise (66) alike. On CUDA the pilot also says how
            unequal the cells' work is, which decides whether a thread or a
            warp computes each cell; over more than 16K points a given k of 40
            or more runs the pilot for that too.
        on_failure: what a cell that cannot be computed even after recovery does:
            ``"raise"`` (RuntimeError), ``"warn"`` (default: RuntimeWarning, NaN
            outputs) or ``"flag"`` (NaN outputs and status only).
        memory_budget: bytes for the neighbour buffer of one chunk of cells
            (4 bytes a neighbour; 1 GiB by default). A chunk holds at least
            1024 cells, so a first pass whose k exceeds ``memory_budget / 4096``
            (262144 by default) takes more; retries ask for at most 256
            neighbours a cell. Fewer chunks are a little faster (each ends in
            a tail of idle GPU); the budget bounds the neighbour buffer, not
            the cells' other working memory.
        periodic: ``True`` or three bools (x, y, z): the box repeats along
            those axes (its edges are the periods; a box is required). Cells
            wrap around: volumes sum to the box's, there are no walls on a
            periodic axis, and each centroid is given next to its point (it
            may lie outside the box). Points outside the box along a periodic
            axis are taken at their image inside. The points near the
            periodic faces are padded with their images; float32 points are
            computed in float64 (:mod:`torchvor.periodic`).
        weights: (N,) the points' dtype and device: the power (Laguerre)
            diagram, cell i = {y : |y - x_i|^2 - w_i <= |y - x_j|^2 - w_j for
            all j} (:mod:`torchvor.power`). A cell may lie away from its point
            or be empty (status EMPTY, volume 0, centroid the point); a copy
            of a point with a larger weight empties its cell. Float32 cells
            are held to float32's guarantee (recomputed in float64 where the
            float32 checks ask), float64 ones computed in float64, each cell
            walking a grid of the points (``k`` unused). Volume, centroid and second moment
            are differentiable in the weights (not in the points: that
            backward raises). With ``periodic``, images carry their point's
            weight.

    Returns:
        :class:`VoronoiCells`. Exact duplicates: the lowest index keeps the cell,
        the others get volume 0, centroid = the point and status DUPLICATE.

    Raises:
        ValueError: bad shapes/values, NaN/Inf, points outside the box, k < 1.
        TypeError: non-floating points or mismatched dtypes.
    """
    _check_on_failure("voronoi", on_failure)
    _check_tensor(points, "points")
    axes = _periodic.periodic_axes(periodic, "voronoi")
    if weights is not None and axes is None:
        box_tensor, weights = _power.checked_call(points, box, batch, weights, "voronoi")
        cells = _power.voronoi(points, weights, box_tensor, batch, k, memory_budget)
        _report_failures("voronoi", cells, on_failure)
        return cells
    if axes is not None:
        _check_points(points, "voronoi")
        pbox = _periodic.periodic_box(points, box, batch, axes, "voronoi")
        if weights is not None:
            weights = _power.check_weights(points, weights, "voronoi")
        cells = _periodic.voronoi(points, pbox, batch, k, memory_budget, weights=weights)
        _report_failures("voronoi", cells, on_failure)
        return cells
    box_tensor = _box_for_call(points, box, batch)
    cells = VoronoiCells(*torch.ops.torchvor.voronoi_cells.default(points, box_tensor, batch, k, memory_budget))
    _report_failures("voronoi", cells, on_failure)
    return cells


def _check_on_failure(caller: str, on_failure: str) -> None:
    if on_failure not in ("raise", "warn", "flag"):
        raise ValueError(f"torchvor.{caller}: on_failure must be 'raise', 'warn' or 'flag', got {on_failure!r}")


def _report_failures(caller: str, cells: VoronoiCells, on_failure: str) -> None:
    """Raise or warn (as `on_failure` says) about cells that could not be computed."""
    if on_failure == "flag" or torch.compiler.is_compiling():
        return
    failed = ((cells.status != CellStatus.SUCCESS) & (cells.status != CellStatus.DUPLICATE)
              & (cells.status != CellStatus.EMPTY))
    if bool(failed.any()):
        count = int(failed.sum())
        codes = sorted({CellStatus(int(c)).name for c in cells.status[failed].unique().cpu()})
        message = f"torchvor.{caller}: {count} cell(s) could not be computed ({', '.join(codes)})"
        if on_failure == "raise":
            raise RuntimeError(message)
        import warnings

        warnings.warn(message, RuntimeWarning, stacklevel=3)


def _voronoi_rows(points: torch.Tensor, box: torch.Tensor, rows: torch.Tensor, batch: Optional[torch.Tensor] = None,
                  k: Optional[int] = None, memory_budget: int = DEFAULT_MEMORY_BUDGET) -> VoronoiCells:
    """The cells of ``points[rows]`` among all of ``points`` (the others are
    not computed), for the periodic and distributed calls, whose padding and
    halo points only bound cells.

    ``box`` is a (B, 2, 3) tensor (:func:`as_box`); ``rows`` (M,) int64.
    Failed cells are flagged, never raised or warned about.

    Returns:
        :class:`VoronoiCells` of M rows, row m the cell of ``points[rows[m]]``;
        differentiable as :func:`voronoi`'s.
    """
    return VoronoiCells(*torch.ops.torchvor.voronoi_cells.default(points, box, batch, k, memory_budget, rows))


def _voronoi_in_grid_order(points: torch.Tensor, box: torch.Tensor, batch: Optional[torch.Tensor] = None,
                           k: Optional[int] = None, memory_budget: int = DEFAULT_MEMORY_BUDGET):
    """The cells of :func:`voronoi` in the op's grid order, for :func:`torchvor.lloyd`.

    ``box`` is a (B, 2, 3) tensor (:func:`as_box`); failed cells are flagged
    (NaN outputs, a failure status), never raised or warned about.

    Returns:
        ``(cells, order)``: :class:`VoronoiCells` whose row i is the cell of
        ``points[order[i]]``, and ``order``, (N,) int64, a permutation that
        sorts the points by grid cell (stably: points of one cell keep their
        relative order). A caller that keeps its points in this order gives
        the next call a nearly sorted input, which it sorts faster.
    """
    *outputs, order = torch.ops.torchvor.voronoi_cells_grid_order.default(points, box, batch, k, memory_budget)
    return VoronoiCells(*outputs), order


def _queries_of(caller: str, points, queries, batch, query_batch, exclude_self):
    """(queries, query_batch, exclude_self) of a neighbour search (knn, radius):
    the points themselves by default, skipping each query's own point unless
    told otherwise; given queries need their own batch vector with `batch`."""
    if queries is None:
        queries = points
        exclude_self = True if exclude_self is None else exclude_self
        if query_batch is None:
            query_batch = batch
    elif exclude_self:
        raise ValueError(f"torchvor.{caller}: exclude_self=True needs queries=None (queries are the points)")
    else:
        exclude_self = False
        if batch is not None and query_batch is None:
            raise ValueError(f"torchvor.{caller}: query_batch is required when batch and queries are given")
    _check_tensor(points, "points")
    _check_tensor(queries, "queries")
    return queries, query_batch, exclude_self


def _check_tensor(value, name: str) -> None:
    if not isinstance(value, torch.Tensor):
        raise TypeError(f"torchvor: {name} must be a torch.Tensor, got {type(value).__name__}")


def _check_points(points: torch.Tensor, caller: str) -> None:
    """What the ops check of points, for the periodic calls that reshape them first."""
    if points.dim() != 2 or points.shape[1] != 3:
        raise ValueError(f"torchvor.{caller}: points must have shape (N, 3), got {tuple(points.shape)}")
    if points.dtype not in (torch.float32, torch.float64):
        raise TypeError(f"torchvor.{caller}: points must be float32 or float64, got {points.dtype}")
    if not bool(torch.isfinite(points).all()):
        raise ValueError(f"torchvor.{caller}: points contain NaN or Inf")


# ---- fake (meta) kernels: output shapes for torch.compile and opcheck -------------------


@torch.library.register_fake("torchvor::knn")
def _knn_fake(points, queries, k, batch=None, query_batch=None, exclude_self=False):
    m = queries.shape[0]
    return queries.new_empty((m, k)), queries.new_empty((m, k), dtype=torch.int64)


# ---- autograd ---------------------------------------------------------------------------
# knn's squared distances are differentiable (d |q - p|^2 = 2 (q - p) . (dq - dp)); the
# indices are piecewise constant. The Voronoi ops' outputs are marked non-differentiable
# until their backward exists: a loss through them raises instead of a silent zero.


def _knn_setup_context(ctx, inputs, output) -> None:
    points, queries = inputs[0], inputs[1]
    _dist2, idx = output
    ctx.mark_non_differentiable(idx)
    ctx.save_for_backward(points, queries, idx)


def _knn_backward(ctx, grad_dist2, _grad_idx):
    points, queries, idx = ctx.saved_tensors
    found = idx >= 0  # padding (-1, dist2 = inf) has no gradient
    neighbor = idx.clamp(min=0)
    weight = torch.where(found, grad_dist2, torch.zeros_like(grad_dist2))
    toward_query = 2 * weight.unsqueeze(-1) * (queries.unsqueeze(1) - points[neighbor])  # (M, k, 3)
    grad_points = grad_queries = None
    if ctx.needs_input_grad[1]:
        grad_queries = toward_query.sum(1)
    if ctx.needs_input_grad[0]:
        grad_points = torch.zeros_like(points).index_add(0, neighbor.reshape(-1), -toward_query.reshape(-1, 3))
    return grad_points, grad_queries, None, None, None, None


def _non_differentiable(ctx, inputs, output) -> None:
    ctx.mark_non_differentiable(*output)


def _no_backward(ctx, *grads):
    raise RuntimeError("torchvor: this op's outputs are not differentiable")


torch.library.register_autograd("torchvor::knn", _knn_backward, setup_context=_knn_setup_context)
# voronoi_cells' gradients are registered in graph.py (they need the faces).
for _op in ("voronoi_cells_grid_order", "lloyd_step"):
    torch.library.register_autograd(f"torchvor::{_op}", _no_backward, setup_context=_non_differentiable)


@torch.library.register_fake("torchvor::voronoi_cells")
def _voronoi_cells_fake(points, box, batch=None, k=None, memory_budget=DEFAULT_MEMORY_BUDGET, rows=None):
    n = points.shape[0] if rows is None else rows.shape[0]
    return (
        points.new_empty((n,)),
        points.new_empty((n, 3)),
        points.new_empty((n,)),
        points.new_empty((n,), dtype=torch.int8),
        points.new_empty((n,), dtype=torch.int32),
        points.new_empty((n,)),
    )


@torch.library.register_fake("torchvor::lloyd_step")
def _lloyd_step_fake(points, box, batch, k, sample_stride, histogram_bins, memory_budget=DEFAULT_MEMORY_BUDGET):
    cells_and_order = _voronoi_cells_grid_order_fake(points, box, batch, k, memory_budget)
    # The measures and the histogram are read to the host inside the op.
    return (points.new_empty((points.shape[0], 3)), *cells_and_order,
            torch.empty((3,), dtype=torch.float64), torch.empty((histogram_bins,), dtype=torch.int32))


@torch.library.register_fake("torchvor::voronoi_cells_grid_order")
def _voronoi_cells_grid_order_fake(points, box, batch=None, k=None, memory_budget=DEFAULT_MEMORY_BUDGET):
    n = points.shape[0]
    return (*_voronoi_cells_fake(points, box, batch, k, memory_budget), points.new_empty((n,), dtype=torch.int64))


# The periodic calls (images of the points near the faces) build on the ops above.
from . import periodic as _periodic  # noqa: E402
# Power diagrams (weights) too.
from . import power as _power  # noqa: E402
