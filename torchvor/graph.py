"""The Voronoi graph: each cell's faces (neighbour, area, centroid) and walls, and
the finite-volume Laplacian built on them.

Thin layer over ``torch.ops.torchvor.voronoi_graph`` (csrc/ops/voronoi_graph.h):
its fake kernel (the edge count depends on the data) and the result types.
"""
from __future__ import annotations

import math
from typing import NamedTuple, Optional

import torch

from .ops import (DEFAULT_MEMORY_BUDGET, BoxLike, PeriodicLike, VoronoiCells, _box_for_call,  # loads torchvor._C
                  _check_on_failure, _check_points, _check_tensor, _no_backward, _non_differentiable,
                  _report_failures, _voronoi_cells_fake)
from . import periodic as _periodic
from . import power as _power


class VoronoiGraph(NamedTuple):
    """Result of :func:`voronoi_graph`.

    edge_index: (2, E) int64, PyG's layout: ``edge_index[0]`` the neighbour j
        (source), ``edge_index[1]`` the cell i (target), sorted by i then j.
        Every face appears in both directions; faces of zero area are not edges.
    area: (E,) the area of the face shared by cells i and j (the same both ways).
    centroid: (E, 3) the face's centroid (the same both ways).
    wall_area: (N, 6) the area of cell i on the box walls -x, +x, -y, +y, -z, +z
        (zero on a periodic axis).
    cells: the :class:`VoronoiCells` of the same call.
    shift: periodic calls only (else None): (E, 3) int8, the image of j that
        cell i meets across the face, ``points[j] + shift * (hi - lo)``. A
        small cloud's cell can meet several images of one point (or of its
        own): one edge each, sorted by i, j, then shift.
    Floating outputs have the points' dtype.
    """

    edge_index: torch.Tensor
    area: torch.Tensor
    centroid: torch.Tensor
    wall_area: torch.Tensor
    cells: VoronoiCells
    shift: Optional[torch.Tensor] = None


def voronoi_graph(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    k: Optional[int] = None,
    on_failure: str = "warn",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
    periodic: PeriodicLike = False,
    weights: Optional[torch.Tensor] = None,
) -> VoronoiGraph:
    """The Voronoi graph: every face between two cells, with its area and centroid.

    The cells are those of :func:`torchvor.voronoi` (same arguments, recovery
    and statuses); each face comes from the same clipping. Cells i and j
    compute their shared face apart; each direction gets the mean of the two
    (area, and centroid weighted by area). Float32 points are computed as
    float64 (outputs rounded to float32), and cells whose faces need it wider. A face whose
    area is below about 1e-20 of the squared distance from its cell's point to
    the face's farthest vertex is rounding noise on an edge or a vertex (four
    or more cospherical points, as in a lattice) and is not an edge; a face
    that only one of its two cells keeps is kept both ways.

    Memory: the passes run once, each cell writing its faces into arrays of
    20 rows a cell (36 bytes a row); where those run out, twice (counting
    each cell's faces, then writing them where the counts say). No N x k
    array is held beyond the neighbour buffer of one chunk (``memory_budget``).

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``.
        box: as :func:`torchvor.voronoi`.
        batch: optional (N,) int64 sorted batch vector: clouds never connect.
        k: as :func:`torchvor.voronoi`.
        on_failure: as :func:`torchvor.voronoi`; a cell that could not be
            computed has no faces.
        memory_budget: as :func:`torchvor.voronoi`.
        periodic: as :func:`torchvor.voronoi`; edges then carry ``shift``, and
            face centroids lie next to cell i's point.
        weights: as :func:`torchvor.voronoi`: the power diagram's faces (an
            empty cell has none), also with ``periodic``.

    Returns:
        :class:`VoronoiGraph`. Exact duplicates (status DUPLICATE) have no edges.
        The outputs are not differentiable (their backward raises).
    """
    _check_on_failure("voronoi_graph", on_failure)
    _check_tensor(points, "points")
    axes = _periodic.periodic_axes(periodic, "voronoi_graph")
    if weights is not None and axes is None:
        box_tensor, weights = _power.checked_call(points, box, batch, weights, "voronoi_graph")
        cells, edge_index, area, centroid, wall_area = _power.voronoi_graph(
            points, weights, box_tensor, batch, k, memory_budget)
        _report_failures("voronoi_graph", cells, on_failure)
        return VoronoiGraph(edge_index, area, centroid, wall_area, cells)
    if axes is not None:
        _check_points(points, "voronoi_graph")
        pbox = _periodic.periodic_box(points, box, batch, axes, "voronoi_graph")
        if weights is not None:
            weights = _power.check_weights(points, weights, "voronoi_graph")
        with torch.no_grad():
            cells, edge_index, area, centroid, wall_area, shift = _periodic.voronoi_graph(
                points, pbox, batch, k, memory_budget, weights)
        _report_failures("voronoi_graph", cells, on_failure)
        return VoronoiGraph(edge_index, area, centroid, wall_area, cells, shift)
    box_tensor = _box_for_call(points, box, batch)
    (*cells, edge_index, area, centroid, wall_area, _moments) = torch.ops.torchvor.voronoi_graph.default(
        points, box_tensor, batch, k, memory_budget)
    cells = VoronoiCells(*cells)
    _report_failures("voronoi_graph", cells, on_failure)
    return VoronoiGraph(edge_index, area, centroid, wall_area, cells)


def voronoi_laplacian(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    k: Optional[int] = None,
    on_failure: str = "warn",
    periodic: PeriodicLike = False,
    weights: Optional[torch.Tensor] = None,
) -> torch.Tensor:
    """The finite-volume Laplacian of the Voronoi cells, a sparse (N, N) matrix.

    Off the diagonal, ``L[i, j] = area_ij / |x_i - x_j|`` for every face of
    :func:`voronoi_graph`; the diagonal makes each row sum to zero, so
    ``(L f)_i = sum_j area_ij (f_j - f_i) / |x_i - x_j|``. The matrix is
    symmetric. For a linear field ``f(x) = a . x`` it is exact: ``(L f)_i = 0``
    for every cell without a wall face (its faces close: ``sum_j area_ij n_ij = 0``).
    Divide row i by the cell's volume for the Laplacian of the field's mean.

    Args:
        points, box, batch, k, on_failure, periodic, weights: as :func:`voronoi_graph`;
            a periodic face's distance is to the image of j that i meets
            (several images of j add up).

    Returns:
        (N, N) sparse COO tensor (coalesced), points' dtype and device.
    """
    graph = voronoi_graph(points, box, batch=batch, k=k, on_failure=on_failure, periodic=periodic, weights=weights)
    source, target = graph.edge_index
    n = points.shape[0]
    across = points[source] - points[target]
    if graph.shift is not None:
        period = _periodic.periodic_box(points, box, batch, _periodic.periodic_axes(periodic, "voronoi_laplacian"),
                                        "voronoi_laplacian").period
        period = period[0].expand(n, 3) if batch is None else period[batch]
        across = across + graph.shift.to(points.dtype) * period[target]
    weight = graph.area / across.norm(dim=1)
    diagonal = torch.zeros(n, dtype=points.dtype, device=points.device).index_add(0, target, -weight)
    rows = torch.arange(n, device=points.device)
    indices = torch.cat([torch.stack([target, source]), torch.stack([rows, rows])], dim=1)
    return torch.sparse_coo_tensor(indices, torch.cat([weight, diagonal]), (n, n), check_invariants=False).coalesce()


@torch.library.register_fake("torchvor::voronoi_graph")
def _voronoi_graph_fake(points, box, batch=None, k=None, memory_budget=DEFAULT_MEMORY_BUDGET, moments=False):
    edges = torch.library.get_ctx().new_dynamic_size()  # depends on the data
    n = points.shape[0]
    return (*_voronoi_cells_fake(points, box, batch, k, memory_budget),
            points.new_empty((2, edges), dtype=torch.int64), points.new_empty((edges,)),
            points.new_empty((edges, 3)), points.new_empty((n, 6)), points.new_empty((edges if moments else 0, 9)))


torch.library.register_autograd("torchvor::voronoi_graph", _no_backward, setup_context=_non_differentiable)


# The gradients of voronoi_cells' volume, centroid and second moment with
# respect to the points (../shared/design GRADIENTS.md): each face moves with
# the points it bisects, the walls stay. The backward recomputes the cells
# (the same cells: the passes are deterministic) and sums each face's terms
# into its cells' points as it goes (torchvor::voronoi_cells_backward).
def _cells_setup_context(ctx, inputs, output) -> None:
    points, box, batch, k, memory_budget, *rows = inputs
    volume, centroid, _second_moment, status, neighbors_needed, radius = output
    ctx.mark_non_differentiable(status, neighbors_needed, radius)
    rows = rows[0] if rows else None  # the outputs' rows (None: every point's)
    ctx.save_for_backward(points, box, batch, volume, centroid, rows)
    ctx.k, ctx.memory_budget = k, memory_budget


def _cells_backward(ctx, grad_volume, grad_centroid, grad_second_moment, _grad_status, _grad_neighbors, _grad_radius):
    points, box, batch, volume, centroid, rows = ctx.saved_tensors
    if not ctx.needs_input_grad[0]:
        return None, None, None, None, None, None
    if rows is not None:  # every point's row (a row asked twice: its gradients add); those not asked give none
        n = points.shape[0]
        volume = volume.new_full((n,), math.nan).index_copy(0, rows, volume)
        centroid = centroid.new_full((n, 3), math.nan).index_copy(0, rows, centroid)
        grad_volume, grad_centroid, grad_second_moment = (
            None if grad is None else grad.new_zeros((n, *grad.shape[1:])).index_add(0, rows, grad)
            for grad in (grad_volume, grad_centroid, grad_second_moment))
    upstream, own = _cell_upstream(points.detach(), volume.detach(), centroid.detach(),
                                   grad_volume, grad_centroid, grad_second_moment)
    moments = grad_centroid is not None or grad_second_moment is not None
    faces = torch.ops.torchvor.voronoi_cells_backward.default(points.detach(), box, batch, ctx.k, ctx.memory_budget,
                                                              upstream, moments)
    return (faces + own).to(points.dtype), None, None, None, None, None


def _cell_upstream(points, volume, centroid, grad_volume, grad_centroid, grad_second_moment):
    """The rows voronoi_cells_backward takes, (N, 5) float64: each cell's dL/dm
    (the centroid's share included), dL/dM (M the first moment about the
    point) and dL/dI, from the outputs' gradients (None: zero); and the cells'
    own term of the second moment, -2 g_I m_i (c_i - x_i) (N, 3), which no
    face carries. The centroid c = x + M / m gives dL/dM = g_c / m and
    dL/dm = g_m - g_c . (c - x) / m; empty or failed cells (m not > 0) none."""
    x = points.double()
    n = x.shape[0]
    zeros = x.new_zeros
    g_m = grad_volume.double() if grad_volume is not None else zeros(n)
    g_c = grad_centroid.double() if grad_centroid is not None else zeros(n, 3)
    g_i = grad_second_moment.double() if grad_second_moment is not None else zeros(n)
    m = volume.double()
    offset = centroid.double() - x  # c_i - x_i
    filled = m > 0
    safe_m = torch.where(filled, m, torch.ones_like(m))
    g_moment = torch.where(filled[:, None], g_c / safe_m[:, None], zeros(n, 3))
    g_m = g_m - torch.where(filled, (g_c * offset).sum(1) / safe_m, zeros(n))
    own = -(2 * g_i * torch.where(filled, m, zeros(n)))[:, None] * torch.nan_to_num(offset)
    return torch.cat([g_m[:, None], g_moment, g_i[:, None]], 1), own


@torch.library.register_fake("torchvor::voronoi_cells_backward")
def _voronoi_cells_backward_fake(points, box, batch, k, memory_budget, upstream, moments):
    return points.new_empty((points.shape[0], 3), dtype=torch.float64)


def _gradient_only(ctx, inputs, output) -> None:
    ctx.mark_non_differentiable(output)


torch.library.register_autograd("torchvor::voronoi_cells_backward", _no_backward, setup_context=_gradient_only)


torch.library.register_autograd("torchvor::voronoi_cells", _cells_backward, setup_context=_cells_setup_context)
