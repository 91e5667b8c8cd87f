"""The Voronoi graph: each cell's faces (neighbour, area, centroid) and walls, and
the finite-volume Laplacian built on them.

Thin layer over ``torch.ops.torchvor.voronoi_graph`` (csrc/ops/voronoi_graph.h):
its fake kernel (the edge count depends on the data) and the result types.
"""
from __future__ import annotations

from typing import NamedTuple, Optional

import torch

from .ops import (DEFAULT_MEMORY_BUDGET, BoxLike, VoronoiCells, _box_for_call, _check_on_failure,  # loads torchvor._C
                  _check_tensor, _no_backward, _non_differentiable, _report_failures, _voronoi_cells_fake)


class VoronoiGraph(NamedTuple):
    """Result of :func:`voronoi_graph`.

    edge_index: (2, E) int64, PyG's layout: ``edge_index[0]`` the neighbour j
        (source), ``edge_index[1]`` the cell i (target), sorted by i then j.
        Every face appears in both directions; faces of zero area are not edges.
    area: (E,) the area of the face shared by cells i and j (the same both ways).
    centroid: (E, 3) the face's centroid (the same both ways).
    wall_area: (N, 6) the area of cell i on the box walls -x, +x, -y, +y, -z, +z.
    cells: the :class:`VoronoiCells` of the same call.
    Floating outputs have the points' dtype.
    """

    edge_index: torch.Tensor
    area: torch.Tensor
    centroid: torch.Tensor
    wall_area: torch.Tensor
    cells: VoronoiCells


def voronoi_graph(
    points: torch.Tensor,
    box: Optional[BoxLike] = None,
    *,
    batch: Optional[torch.Tensor] = None,
    k: Optional[int] = None,
    on_failure: str = "warn",
    memory_budget: int = DEFAULT_MEMORY_BUDGET,
) -> VoronoiGraph:
    """The Voronoi graph: every face between two cells, with its area and centroid.

    The cells are those of :func:`torchvor.voronoi` (same arguments, recovery
    and statuses); each face comes from the same clipping. Cells i and j
    compute their shared face apart; each direction gets the mean of the two
    (area, and centroid weighted by area). A face whose area is below about
    1e-10 (float32) or 1e-20 (float64) of the squared distance from its cell's
    point to the face's farthest vertex is rounding noise on an edge or a
    vertex (four or more cospherical points, as in a lattice) and is not an
    edge; a face that only one of its two cells keeps is kept both ways.

    Memory: the passes run twice, counting each cell's faces, then writing
    them where the counts say; no N x k array is held beyond the neighbour
    buffer of one chunk (``memory_budget``).

    Args:
        points: (N, 3) float32 or float64, CPU or CUDA, inside ``box``.
        box: as :func:`torchvor.voronoi`.
        batch: optional (N,) int64 sorted batch vector: clouds never connect.
        k: as :func:`torchvor.voronoi`.
        on_failure: as :func:`torchvor.voronoi`; a cell that could not be
            computed has no faces.
        memory_budget: as :func:`torchvor.voronoi`.

    Returns:
        :class:`VoronoiGraph`. Exact duplicates (status DUPLICATE) have no edges.
        The outputs are not differentiable (their backward raises).
    """
    _check_on_failure("voronoi_graph", on_failure)
    _check_tensor(points, "points")
    box_tensor = _box_for_call(points, box, batch)
    (*cells, edge_index, area, centroid, wall_area) = torch.ops.torchvor.voronoi_graph.default(
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
) -> torch.Tensor:
    """The finite-volume Laplacian of the Voronoi cells, a sparse (N, N) matrix.

    Off the diagonal, ``L[i, j] = area_ij / |x_i - x_j|`` for every face of
    :func:`voronoi_graph`; the diagonal makes each row sum to zero, so
    ``(L f)_i = sum_j area_ij (f_j - f_i) / |x_i - x_j|``. The matrix is
    symmetric. For a linear field ``f(x) = a . x`` it is exact: ``(L f)_i = 0``
    for every cell without a wall face (its faces close: ``sum_j area_ij n_ij = 0``).
    Divide row i by the cell's volume for the Laplacian of the field's mean.

    Args:
        points, box, batch, k, on_failure: as :func:`voronoi_graph`.

    Returns:
        (N, N) sparse COO tensor (coalesced), points' dtype and device.
    """
    graph = voronoi_graph(points, box, batch=batch, k=k, on_failure=on_failure)
    source, target = graph.edge_index
    n = points.shape[0]
    weight = graph.area / (points[source] - points[target]).norm(dim=1)
    diagonal = torch.zeros(n, dtype=points.dtype, device=points.device).index_add(0, target, -weight)
    rows = torch.arange(n, device=points.device)
    indices = torch.cat([torch.stack([target, source]), torch.stack([rows, rows])], dim=1)
    return torch.sparse_coo_tensor(indices, torch.cat([weight, diagonal]), (n, n), check_invariants=False).coalesce()


@torch.library.register_fake("torchvor::voronoi_graph")
def _voronoi_graph_fake(points, box, batch=None, k=None, memory_budget=DEFAULT_MEMORY_BUDGET):
    edges = torch.library.get_ctx().new_dynamic_size()  # depends on the data
    n = points.shape[0]
    return (*_voronoi_cells_fake(points, box, batch, k, memory_budget),
            points.new_empty((2, edges), dtype=torch.int64), points.new_empty((edges,)),
            points.new_empty((edges, 3)), points.new_empty((n, 6)))


torch.library.register_autograd("torchvor::voronoi_graph", _no_backward, setup_context=_non_differentiable)
